//! Flag groups that several commands share (how a map is built, how a laser log is read,
//! where a bag's images and poses are), what they turn into for the library, and the
//! library's build loop with progress bars ([`build_engine_of`], [`build_map`]).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result, bail};

use crate::progress::Bars;
use mrfmap::frames::{Frame, NoiseModel, Poly, RangeScan};
#[cfg(feature = "bags")]
use mrfmap::inference::MapOutput;
use mrfmap::inference::{Allocation, BuildOptions, EngineConfig, EngineKind, KeyframeSelection, Marking};
use mrfmap::map::Aabb;
use mrfmap::pipeline::{BuildReport, Built, Reading, Readings, build_engine, read_ahead};
#[cfg(feature = "bags")]
use mrfmap::pipeline::{check_posed, stream_bag};
#[cfg(feature = "bags")]
use mrfmap::source::bag::{Bag, BagOptions, bag_frames, bag_scans, for_each_frame};
use mrfmap::source::{BeamSpacing, CarmenLog, CarmenOptions, Misses};

/// Options that shape how any map is built from a dataset.
#[derive(clap::Args, Clone)]
pub struct MapOptions {
    /// Cut readings beyond this range (metres); they then mark free space only.
    #[arg(long, value_parser = super::positive, allow_hyphen_values = true)]
    pub max_range: Option<f64>,
    /// Map only this box: XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX (metres).
    #[arg(long, allow_hyphen_values = true)]
    pub bounds: Option<String>,
    /// Noise model file (default: the dataset's noise.toml when present).
    #[arg(long)]
    pub noise: Option<PathBuf>,
    /// MRF: sweeps of belief propagation (at least 1). Alone: exactly N sweeps over every
    /// tile of every keyframe (default 3, the paper's). With --tolerance: at most N sweeps
    /// (default 10).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub iterations: Option<u32>,
    /// MRF: prior occupancy of every voxel.
    #[arg(long, default_value_t = BuildOptions::default().prior)]
    pub prior: f64,
    /// MRF: allocate bricks around depth points only (band) or along whole rays (full).
    #[arg(long, default_value = "band", value_parser = super::choice::<Allocation>())]
    pub allocation: Allocation,
    /// MRF: every frame is a keyframe (all), or only frames 0.2 m / 0.2 rad from every
    /// keyframe so far (auto).
    #[arg(long, default_value = "all", value_parser = super::choice::<KeyframeSelection>())]
    pub keyframes: KeyframeSelection,
    /// MRF: share of a tile's old message kept when it is replaced, in [0, 1) (0, the
    /// default, is the paper's plain update; messages whose change reverses are halved
    /// whatever this says).
    #[arg(long, default_value_t = BuildOptions::default().damping)]
    pub damping: f64,
    /// MRF: change-driven belief propagation: sweep until no marginal moves by more than this,
    /// re-tracing only the 16x16-pixel tiles whose voxels moved since they last traced, at
    /// most --iterations sweeps (default 10). A log line says the sweeps, tiles and rays it
    /// traced. With --online: moves up to this are not followed (default 0.001).
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// MRF: trace every tile once, then the tiles whose voxels moved most first, for at most
    /// this many sweeps' worth of tile traces in all (stopping early when nothing moves by
    /// more than the tolerance): the online schedule's order, used for a batch build.
    #[arg(long, value_parser = super::positive)]
    pub work: Option<f64>,
    /// MRF: trace one ray per block of pixels where pixels are much smaller than voxels: the
    /// largest block (2x2 up to 8x8) whose rays lie at most this many voxel edges apart at a
    /// tile's nearest depth; 0 (default) traces every pixel. 0.5 builds 3x faster at 0.05 m
    /// and costs accuracy (RESULTS.md).
    #[arg(long, default_value_t = BuildOptions::default().ray_spacing, value_parser = super::non_negative)]
    pub ray_spacing: f64,
    /// MRF: voxels whose log-odds moved less than this from the prior are unknown (left out
    /// of the map). Default ln 3: a Bayes factor below 3 is "not worth more than a bare
    /// mention" (Kass and Raftery); 0 keeps every voxel a ray reached.
    #[arg(long, default_value_t = BuildOptions::default().min_evidence, value_parser = super::non_negative)]
    pub min_evidence: f64,
    /// CRM: particles per voxel pdf (memory per voxel is 4 * (particles + 1) bytes).
    #[arg(long, default_value_t = BuildOptions::default().particles as u16, value_parser = clap::value_parser!(u16).range(2..))]
    pub particles: u16,
    /// Log-odds: find the voxels a depth image's rays cross by projecting boxes of voxels
    /// into the image (project, faster) or by walking every ray (walk), the same map; or
    /// decide each voxel by its centre against its nearest pixel's depth (centres, faster
    /// again; not OctoMap's voxels: docs/ALGORITHMS.md 5.1).
    #[arg(long, default_value = "project", value_parser = super::choice::<Marking>())]
    pub marking: Marking,
    /// Log-odds: clamping thresholds as probabilities, "MIN,MAX" (default: OctoMap's
    /// 0.1192,0.971).
    #[arg(long, value_parser = parse_clamp)]
    pub clamp: Option<(f64, f64)>,
}

/// clap parser for `--clamp MIN,MAX`: two numbers (their range is checked with the rest of
/// the options, [`BuildOptions::config`]).
fn parse_clamp(s: &str) -> Result<(f64, f64), String> {
    let (lo, hi) = s.split_once(',').ok_or("expected MIN,MAX")?;
    let lo: f64 = lo.trim().parse().map_err(|e| format!("MIN: {e}"))?;
    let hi: f64 = hi.trim().parse().map_err(|e| format!("MAX: {e}"))?;
    Ok((lo, hi))
}

impl MapOptions {
    /// Opens `dataset` with the noise override applied.
    pub fn open(&self, dataset: &std::path::Path) -> Result<mrfmap::source::Dataset> {
        let mut ds = mrfmap::source::Dataset::open(dataset)?;
        if let Some(n) = &self.noise {
            ds.set_noise_file(n)?;
        }
        Ok(ds)
    }

    /// The library's options these flags set.
    pub fn build_options(&self) -> Result<BuildOptions> {
        Ok(BuildOptions {
            max_range: self.max_range,
            bounds: self.bounds.as_deref().map(Aabb::parse).transpose()?,
            iterations: self.iterations.map(|n| n as usize),
            tolerance: self.tolerance,
            work: self.work,
            prior: self.prior,
            allocation: self.allocation,
            keyframes: self.keyframes,
            damping: self.damping,
            ray_spacing: self.ray_spacing,
            min_evidence: self.min_evidence,
            particles: self.particles as usize,
            marking: self.marking,
            clamp: self.clamp,
        })
    }

    /// The engine configuration for `kind` at `resolution`.
    pub fn config(&self, kind: EngineKind, resolution: f64) -> Result<EngineConfig> {
        Ok(self.build_options()?.config(kind, resolution)?)
    }
}

/// How a planar laser log (CARMEN) is read and thinned.
#[derive(clap::Args, Clone)]
pub struct LaserOptions {
    /// Laser logs: keep every N-th beam of each scan (the CRM paper's real-data test gives
    /// its maps every tenth).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub beams_every: u32,
    /// Laser logs: keep every N-th scan.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub scans_every: u32,
    /// Laser logs: FLASER/RLASER beams are pi/n apart (n) or pi/(n-1) apart (n-1).
    #[arg(long, default_value = "n", value_parser = super::choice::<BeamSpacing>())]
    pub beam_spacing: BeamSpacing,
    /// Laser logs: FLASER/RLASER ranges at or beyond this are misses (no return).
    #[arg(long, default_value_t = 80.0, value_parser = super::positive)]
    pub laser_max_range: f64,
    /// Laser logs and scan topics: misses clear space up to --miss-range (free) or are
    /// dropped (ignore).
    #[arg(long, default_value = "free", value_parser = super::choice::<Misses>())]
    pub misses: Misses,
    /// Laser logs and scan topics: how far a miss clears space (metres; `inf`: up to the
    /// laser's range, --laser-max-range or a LaserScan's range_max, as
    /// OctoMap reads a max-range beam). Default 5, Cartographer's `missing_data_ray_length`:
    /// a miss is as often glass, a dark or grazing wall as open space, and 80 m of free space
    /// through it would clear walls behind; 5 m clears a room's open floor.
    #[arg(long, default_value_t = 5.0, value_parser = super::positive_or_infinite)]
    pub miss_range: f64,
    /// Laser logs: range noise std in metres for CRM (constant; --noise replaces it).
    #[arg(long, default_value_t = 0.03, value_parser = super::positive)]
    pub laser_std: f64,
}

impl LaserOptions {
    /// Reads the log at `path`.
    pub fn open(&self, path: &std::path::Path) -> Result<CarmenLog> {
        Ok(CarmenLog::open(path, CarmenOptions { spacing: self.beam_spacing, max_range: self.laser_max_range })?)
    }

    /// Applies `--misses` and `--miss-range` to a scan (a laser log's or a bag's): beams
    /// without a return are dropped, or clear space up to the miss range.
    pub fn apply_misses(&self, scan: &mut RangeScan) {
        if self.misses == Misses::Ignore {
            scan.beams.retain(|b| b.range.is_some());
        }
        scan.max_range = scan.max_range.min(self.miss_range);
    }

    /// The scans of `log` this asks for, planar at the middle of the map's layer 0 (`z = r / 2`),
    /// with the noise model of `noise_file` (its aggregate) or `--laser-std`.
    pub fn scans(
        &self,
        log: &CarmenLog,
        resolution: f64,
        noise_file: Option<&std::path::Path>,
    ) -> Result<Vec<RangeScan>> {
        let noise = match noise_file {
            Some(path) => {
                let n = NoiseModel::load(path)?;
                NoiseModel::aggregate(n.bias, n.std)
            }
            None => NoiseModel::aggregate(Poly([0.0; 3]), Poly([self.laser_std, 0.0, 0.0])),
        };
        let noise = Some(Arc::new(noise));
        log.readings
            .iter()
            .step_by(self.scans_every as usize)
            .enumerate()
            .map(|(i, r)| {
                let mut scan = r
                    .to_scan(i, 0.5 * resolution, self.beams_every as usize, self.misses, noise.clone())
                    .with_context(|| format!("{} line {}", log.path.display(), r.line))?;
                self.apply_misses(&mut scan);
                Ok(scan)
            })
            .collect()
    }
}

/// Where a ROS 2 or ROS 1 bag's depth images and poses are.
#[derive(clap::Args, Clone)]
pub struct BagArgs {
    /// Bags: the depth image topic (sensor_msgs/Image, 16UC1 mm or 32FC1 m).
    #[arg(long)]
    pub depth_topic: Option<String>,
    /// Bags: a sensor_msgs/LaserScan or PointCloud2 topic to map instead of depth images
    /// (logodds, crm); a cloud's points are beams from the sensor's origin.
    #[arg(long, visible_alias = "cloud-topic", conflicts_with = "depth_topic")]
    pub scan_topic: Option<String>,
    /// Bags: the CameraInfo topic (default: camera_info beside the depth topic).
    #[arg(long)]
    pub camera_info_topic: Option<String>,
    /// Bags: poses from /tf and /tf_static, of each image's frame in this frame.
    #[arg(long)]
    pub fixed_frame: Option<String>,
    /// Bags: poses from this PoseStamped or Odometry topic (the camera's pose) instead.
    #[arg(long)]
    pub pose_topic: Option<String>,
    /// Bags: images between two pose samples farther apart than this (seconds) are skipped.
    #[arg(long, default_value_t = 0.1, value_parser = super::positive)]
    pub max_pose_gap: f64,
}

impl BagArgs {
    /// Is `path` a bag (a `.mcap`, `.db3` or ROS 1 `.bag` file, or a folder with `metadata.yaml`)?
    pub fn is_bag(path: &std::path::Path) -> bool {
        path.extension().is_some_and(|e| e == "mcap" || e == "db3" || e == "bag")
            || path.join("metadata.yaml").is_file()
    }

    #[cfg(feature = "bags")]
    fn options(&self, depth_topic: String) -> BagOptions {
        BagOptions {
            depth_topic,
            camera_info_topic: self.camera_info_topic.clone(),
            fixed_frame: self.fixed_frame.clone(),
            pose_topic: self.pose_topic.clone(),
            max_pose_gap: self.max_pose_gap,
        }
    }

    /// The options of a depth-image build (`--depth-topic` is required), and the noise model.
    #[cfg(feature = "bags")]
    fn depth_options(&self, noise: Option<&std::path::Path>) -> Result<(BagOptions, Option<NoiseModel>)> {
        let depth_topic =
            self.depth_topic.clone().context("a bag needs --depth-topic or --scan-topic (see `mrfmap bag info`)")?;
        Ok((self.options(depth_topic), noise.map(NoiseModel::load).transpose()?))
    }

    /// The bag's depth frames with poses; skipped images are summarised in a warning.
    pub fn frames(&self, path: &std::path::Path, noise: Option<&std::path::Path>) -> Result<Vec<Frame>> {
        #[cfg(not(feature = "bags"))]
        return Err(without_bags(path, noise));
        #[cfg(feature = "bags")]
        {
            let (options, noise) = self.depth_options(noise)?;
            let (frames, skipped) = bag_frames(&Bag::open(path)?, &options, noise)?;
            check_posed(path, &options.depth_topic, frames.len(), &skipped)?;
            Ok(frames)
        }
    }

    /// Calls `visit` with the bag's posed depth frames one at a time, in stamp order, in one
    /// pass, and returns how many there were (skipped images are summarised in a warning;
    /// none posed is an error).
    #[cfg(feature = "bags")]
    pub fn each_frame(&self, path: &std::path::Path, mut visit: impl FnMut(Frame) -> Result<()>) -> Result<usize> {
        let (options, _) = self.depth_options(None)?;
        let mut failed = None;
        let report = for_each_frame(&Bag::open(path)?, &options, None, |frame| {
            Ok(match visit(frame) {
                Ok(()) => std::ops::ControlFlow::Continue(()),
                Err(e) => {
                    failed = Some(e);
                    std::ops::ControlFlow::Break(())
                }
            })
        })?;
        if let Some(e) = failed {
            return Err(e);
        }
        check_posed(path, &options.depth_topic, report.frames, &report.skipped)?;
        Ok(report.frames)
    }

    /// Builds with `build` from the bag's posed depth images, streamed
    /// ([`mrfmap::pipeline::stream_bag`]), its memory checked for a map saved from the engine
    /// (as `mrfmap build` writes it); returns the build and the frames used.
    pub fn build_streamed(
        &self,
        path: &std::path::Path,
        noise: Option<&std::path::Path>,
        pick: (&[usize], &[usize]),
        config: &EngineConfig,
        build: &mut FrameBuild<'_>,
    ) -> Result<(Built, Vec<usize>)> {
        #[cfg(not(feature = "bags"))]
        return Err(without_bags(path, (noise, pick, config, build)));
        #[cfg(feature = "bags")]
        {
            let (options, noise) = self.depth_options(noise)?;
            let (report, used) = stream_bag(path, options, noise, pick, (config, MapOutput::Saved), |frames| {
                build(frames, None, config).map_err(|e| mrfmap::Error::Invalid(format!("{e:#}")))
            })?;
            Ok((report, used))
        }
    }

    /// The bag's laser scans with poses (noise: `--noise`'s aggregate, else the engine's).
    pub fn scans(
        &self,
        path: &std::path::Path,
        topic: &str,
        noise: Option<&std::path::Path>,
    ) -> Result<Vec<RangeScan>> {
        #[cfg(not(feature = "bags"))]
        return Err(without_bags(path, (topic, noise)));
        #[cfg(feature = "bags")]
        {
            let noise = noise.map(|p| NoiseModel::load(p).map(|n| NoiseModel::aggregate(n.bias, n.std))).transpose()?;
            let (scans, skipped) = bag_scans(&Bag::open(path)?, topic, &self.options(String::new()), noise)?;
            check_posed(path, topic, scans.len(), &skipped)?;
            Ok(scans)
        }
    }
}

/// A build from frames as they come, each with its index, and how many will come if known,
/// with this engine configuration.
pub type FrameBuild<'a> = dyn FnMut(&mut Readings<'_, Frame>, Option<usize>, &EngineConfig) -> Result<Built> + 'a;

/// The error for a bag given to a binary built without the `bags` feature (`_unused`: the
/// arguments only a bag reader would read).
#[cfg(not(feature = "bags"))]
fn without_bags<T>(path: &std::path::Path, _unused: T) -> anyhow::Error {
    anyhow::anyhow!(
        "{}: this mrfmap was built without ROS bag support (the `bags` feature); \
         rebuild with default features, e.g. `cargo install --path crates/mrfmap-cli`",
        path.display()
    )
}

/// Fails unless `path`'s folder exists (checked before the work, not after it).
pub fn check_output_folder(path: &std::path::Path) -> Result<()> {
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
    if !folder.is_dir() {
        bail!("{}: the output folder {} does not exist", path.display(), folder.display());
    }
    Ok(())
}

/// Integrates the readings `indices` (fetched through `reading`, the next one while this one
/// is integrated: [`read_ahead`]) with the engine `config` describes, with progress bars; the
/// engine is kept ([`Built`]).
pub fn build_engine_of<R: Reading + Send>(
    indices: &[usize],
    config: &EngineConfig,
    reading: impl Fn(usize) -> mrfmap::Result<R> + Sync,
) -> Result<Built> {
    let count = Some(indices.len());
    Ok(read_ahead(indices, reading, |readings| build_engine(config, readings, count, &mut Bars::default(), None))?)
}

/// [`build_engine_of`], with the engine's map made.
pub fn build_map<R: Reading + Send>(
    indices: &[usize],
    config: &EngineConfig,
    reading: impl Fn(usize) -> mrfmap::Result<R> + Sync,
) -> Result<BuildReport> {
    Ok(build_engine_of(indices, config, reading)?.into_report())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(clap::Parser)]
    struct Flags {
        #[command(flatten)]
        options: MapOptions,
    }

    /// The flags' defaults are the library's (one set of defaults, shown in `--help`).
    #[test]
    fn flags_default_to_the_library_options() {
        let flags = Flags::try_parse_from(["mrfmap"]).unwrap();
        assert_eq!(flags.options.build_options().unwrap(), BuildOptions::default());
        let flags = Flags::try_parse_from(["mrfmap", "--tolerance", "0.01", "--clamp", "0.2,0.9"]).unwrap();
        let config = flags.options.config(EngineKind::Mrf, 0.1).unwrap();
        assert_eq!((config.mrf.tolerance, config.logodds.clamp_max), (Some(0.01), 0.9));
    }
}
