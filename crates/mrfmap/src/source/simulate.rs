//! Renders a [`Scene`] to a dataset in the layout [`crate::source::Dataset`] reads.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::frames::{Camera, DepthImage, NoiseModel, Poly, Pose, pose_to_tum};
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
    let mut writer = DatasetWriter::create(out, scene.camera, true)?;
    let mut valid_pixels = 0;
    for (i, pose) in scene.views.iter().enumerate() {
        let truth = scene.render(pose);
        valid_pixels += truth.valid_count();
        let noisy = scene.add_noise(&truth, seed, i);
        writer.add(i as f64, pose, &noisy, Some(&truth))?;
    }
    let zero = NoiseModel::aggregate(Poly([0.0; 3]), Poly([0.0; 3]));
    writer.finish(Some(scene.noise.as_ref().unwrap_or(&zero)))?;
    Ok(SimulationSummary { frames: scene.views.len(), valid_pixels })
}

/// Writes a dataset in the layout [`crate::source::Dataset`] reads, frame by frame: depth
/// PNGs (and exact ones in `gt_depth/`), then `depth.txt`, `groundtruth.txt`, `camera.toml`
/// and, when given, `noise.toml`. What the simulator and `mrfmap export-dataset` share.
pub struct DatasetWriter {
    out: PathBuf,
    camera: Camera,
    depth_list: String,
    poses: String,
    frames: usize,
}

impl DatasetWriter {
    /// Creates `out/depth` (and `out/gt_depth` when `truth` is set).
    pub fn create(out: &Path, camera: Camera, truth: bool) -> Result<Self> {
        let mut dirs = vec![out.to_path_buf(), out.join("depth")];
        if truth {
            dirs.push(out.join("gt_depth"));
        }
        for dir in dirs {
            std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
        Ok(DatasetWriter {
            out: out.to_path_buf(),
            camera,
            depth_list: String::from("# timestamp filename\n"),
            poses: String::from("# timestamp tx ty tz qx qy qz qw\n"),
            frames: 0,
        })
    }

    /// Adds one frame at `timestamp` seconds.
    pub fn add(&mut self, timestamp: f64, pose: &Pose, depth: &DepthImage, truth: Option<&DepthImage>) -> Result<()> {
        let name = format!("{:06}.png", self.frames);
        if let Some(truth) = truth {
            write_depth_png(&self.out.join("gt_depth").join(&name), truth, self.camera.depth_scale)?;
        }
        write_depth_png(&self.out.join("depth").join(&name), depth, self.camera.depth_scale)?;
        let t = timestamp;
        self.depth_list.push_str(&format!("{t:.6} depth/{name}\n"));
        let p = pose_to_tum(pose);
        self.poses.push_str(&format!(
            "{t:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
            p[0], p[1], p[2], p[3], p[4], p[5], p[6]
        ));
        self.frames += 1;
        Ok(())
    }

    /// Writes the lists, `camera.toml` and `noise.toml` (when given).
    pub fn finish(self, noise: Option<&NoiseModel>) -> Result<usize> {
        let mut files = vec![
            ("depth.txt", self.depth_list),
            ("groundtruth.txt", self.poses),
            ("camera.toml", self.camera.to_toml()),
        ];
        if let Some(n) = noise {
            files.push(("noise.toml", n.to_toml()));
        }
        for (name, text) in files {
            write_atomic(&self.out.join(name), |w| w.write_all(text.as_bytes()))?;
        }
        Ok(self.frames)
    }
}
