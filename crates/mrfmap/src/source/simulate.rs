//! Renders a [`Scene`] to a dataset in the layout [`crate::source::Dataset`] reads.

use std::io::Write;
use std::path::Path;

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::frames::{NoiseModel, Poly, pose_to_tum};
use crate::source::Scene;
use crate::source::depth_png::write_depth_png;

/// What [`simulate`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SimulationSummary {
    /// Frames rendered.
    pub frames: usize,
    /// Valid (non-zero) noise-free pixels over all frames.
    pub valid_pixels: usize,
}

/// Renders every view of `scene` into `out`: `depth/` (noisy, seeded), `gt_depth/` (exact),
/// `depth.txt`, `groundtruth.txt` (timestamps 0, 1, 2, ... s), `camera.toml` and `noise.toml`
/// (the scene's model; a zero model for noise-free scenes).
pub fn simulate(scene: &Scene, out: &Path, seed: u64) -> Result<SimulationSummary> {
    for dir in [out.to_path_buf(), out.join("depth"), out.join("gt_depth")] {
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    let mut depth_list = String::from("# timestamp filename\n");
    let mut poses = String::from("# timestamp tx ty tz qx qy qz qw\n");
    let mut valid_pixels = 0;
    for (i, pose) in scene.views.iter().enumerate() {
        let truth = scene.render(pose);
        valid_pixels += truth.valid_count();
        let noisy = scene.add_noise(&truth, seed, i);
        let name = format!("{i:06}.png");
        write_depth_png(&out.join("gt_depth").join(&name), &truth, scene.camera.depth_scale)?;
        write_depth_png(&out.join("depth").join(&name), &noisy, scene.camera.depth_scale)?;
        let t = i as f64;
        depth_list.push_str(&format!("{t:.6} depth/{name}\n"));
        let p = pose_to_tum(pose);
        poses.push_str(&format!(
            "{t:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
            p[0], p[1], p[2], p[3], p[4], p[5], p[6]
        ));
    }
    let zero = NoiseModel::aggregate(Poly([0.0; 3]), Poly([0.0; 3]));
    let noise = scene.noise.as_ref().unwrap_or(&zero);
    for (name, text) in [
        ("depth.txt", depth_list),
        ("groundtruth.txt", poses),
        ("camera.toml", scene.camera.to_toml()),
        ("noise.toml", noise.to_toml()),
    ] {
        write_atomic(&out.join(name), |w| w.write_all(text.as_bytes()))?;
    }
    Ok(SimulationSummary { frames: scene.views.len(), valid_pixels })
}
