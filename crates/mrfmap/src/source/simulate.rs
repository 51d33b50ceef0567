//! Writes simulated datasets in the layout [`crate::source::Dataset`] reads: a [`Scene`]
//! rendered ([`simulate`]), or a noise-free dataset made noisy by a sensor model
//! ([`add_noise`]). Both go through one [`DatasetWriter`].

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::frames::{Camera, DepthImage, NoiseModel, Pose, Up, pose_to_tum};
use crate::source::depth_png::{quantise_depth, write_depth_png};
use crate::source::{Dataset, DepthNoise, NoiseStatistics, Scene, noise_statistics};

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
/// (the scene's model; none for a noise-free scene, whose dataset the engines then map with
/// their default model).
pub fn simulate(scene: &Scene, out: &Path, seed: u64) -> Result<SimulationSummary> {
    let mut writer = DatasetWriter::create(out, scene.camera, true)?;
    let mut valid_pixels = 0;
    for (i, pose) in scene.views.iter().enumerate() {
        let truth = scene.render(pose);
        valid_pixels += truth.valid_count();
        let noisy = scene.add_noise(&truth, seed, i);
        writer.add(i as f64, pose, &noisy, Some(&truth))?;
    }
    // (A noise-free scene has no model to write: a zero std is no forward model, and a dataset
    // holding one could not be opened.)
    writer.finish(scene.noise.as_ref())?;
    Ok(SimulationSummary { frames: scene.views.len(), valid_pixels })
}

/// What [`add_noise`] wrote: frames, and the noise statistics of each frame against its clean
/// depth (`None` for a frame with no pixel valid in both).
#[derive(Clone, Debug, PartialEq)]
pub struct NoisySummary {
    /// Frames written.
    pub frames: usize,
    /// Per frame, [`noise_statistics`] of the noisy depth as stored.
    pub statistics: Vec<Option<NoiseStatistics>>,
}

/// Writes `dataset` with noisy depth to `out`: `depth/` from `noise` (seeded; frame `i` is
/// view `i`), `gt_depth/` the input's depth, the input's timestamps, poses, camera and up axis, and
/// `noise.toml` the forward model of `noise` (what the engines should map it with).
/// `out` must not exist; the dataset is written beside it and renamed into place when complete,
/// so a failure leaves nothing half-written. `progress` is called after each frame.
pub fn add_noise(
    dataset: &Dataset,
    out: &Path,
    noise: &DepthNoise,
    seed: u64,
    mut progress: impl FnMut(usize),
) -> Result<NoisySummary> {
    let camera = *dataset.camera();
    if let DepthNoise::Model(model) = noise {
        model.check_camera(&camera).map_err(|m| Error::Invalid(format!("noise model: {m}")))?;
    }
    if out.exists() {
        return Err(Error::file(out, "already exists: choose a new folder for the noisy dataset"));
    }
    let name = out.file_name().ok_or_else(|| Error::file(out, "not a folder name"))?;
    let partial = out.with_file_name(format!(".{}.partial-{}", name.to_string_lossy(), std::process::id()));
    let written = (|| {
        let mut writer = DatasetWriter::create(&partial, camera, true)?;
        writer.up = dataset.up();
        let mut statistics = Vec::with_capacity(dataset.len());
        for (i, info) in dataset.frames().iter().enumerate() {
            let clean = dataset.frame(i)?.depth;
            let noisy = quantise_depth(&noise.apply(&clean, &camera, seed, i as u64), camera.depth_scale);
            statistics.push(noise_statistics(&noisy, &clean, camera.depth_scale));
            writer.add(info.timestamp, &info.pose, &noisy, Some(&clean))?;
            progress(i + 1);
        }
        let frames = writer.finish(Some(&noise.forward_model(&camera)))?;
        Ok(NoisySummary { frames, statistics })
    })();
    match written {
        Ok(summary) => {
            std::fs::rename(&partial, out).map_err(|e| Error::io(out, e))?;
            Ok(summary)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            Err(e)
        }
    }
}

/// Writes a dataset in the layout [`crate::source::Dataset`] reads, frame by frame: depth
/// PNGs (and exact ones in `gt_depth/`), then `depth.txt`, `groundtruth.txt`, `camera.toml`
/// and, when given, `noise.toml` and `world.toml` (the up axis). What the simulator and `mrfmap export-dataset` share.
pub struct DatasetWriter {
    out: PathBuf,
    camera: Camera,
    /// The world's up axis, written as `world.toml` when set.
    pub up: Option<Up>,
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
            up: None,
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
        if let Some(up) = self.up {
            files.push(("world.toml", format!("up = \"{up}\"\n")));
        }
        for (name, text) in files {
            write_atomic(&self.out.join(name), |w| w.write_all(text.as_bytes()))?;
        }
        Ok(self.frames)
    }
}
