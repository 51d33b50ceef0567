//! `mrfmap build`: dataset or laser log in, map file out. Also the building blocks that `demo`, `loo`
//! and `compare` share: map options, frame selection, and the integration loop.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use std::sync::Arc;

use mrfmap::atomic_file::write_atomic;
use mrfmap::frames::{Frame, NoiseModel, Poly, RangeScan};
use mrfmap::inference::{
    Allocation, Budget, BuildOptions, Engine, EngineConfig, EngineKind, Extent, KeyframeSelection, Marking, MrfEngine,
    Tiling, check_build, frames_extent, new_engine, scan_extent,
};
use mrfmap::map::Aabb;
use mrfmap::map::{Map, TileKey};
#[cfg(feature = "bags")]
use mrfmap::source::bag::{Bag, BagOptions, DepthStream, bag_frames, bag_scans, for_each_frame};
use mrfmap::source::{BeamSpacing, CarmenLog, CarmenOptions, Dataset, Misses};
use std::io::Write;

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
    /// into the image (project, faster) or by walking every ray (walk); same map.
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
    pub fn open(&self, dataset: &std::path::Path) -> Result<Dataset> {
        let mut ds = Dataset::open(dataset)?;
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
            posed(path, &options.depth_topic, frames.len(), &skipped)?;
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
        posed(path, &options.depth_topic, report.frames, &report.skipped)?;
        Ok(report.frames)
    }

    /// Builds with `build` from the bag's posed depth images, read once: each image is decoded
    /// and handed to `build` as soon as its pose is known, so memory holds a few images
    /// whatever the bag's size. A stream's length is known only at its end, so the memory
    /// estimate is checked as it grows ([`Growth`]) and `--frames` / `--exclude` indices are
    /// checked against the images at the end (before anything is written). Returns the build
    /// and the frames used.
    pub fn build_streamed(
        &self,
        path: &std::path::Path,
        noise: Option<&std::path::Path>,
        (frames, exclude): (&[usize], &[usize]),
        config: &EngineConfig,
        build: &mut FrameBuild<'_>,
    ) -> Result<(BuildReport, Vec<usize>)> {
        #[cfg(not(feature = "bags"))]
        return Err(without_bags(path, (noise, frames, exclude, config, build)));
        #[cfg(feature = "bags")]
        {
            let (bag_options, noise) = self.depth_options(noise)?;
            let topic = bag_options.depth_topic.clone();
            let mut stream = DepthStream::new(Bag::open(path)?, bag_options, noise);
            tracing::info!(
                "{}: depth images of {topic}, engine {}, resolution {} m (streamed)",
                path.display(),
                config.kind.name(),
                config.resolution
            );
            let (mut growth, mut used) = (Growth::new(config), Vec::new());
            let report = {
                let mut chosen = stream.by_ref().filter_map(|frame| {
                    let frame = match frame {
                        Ok(f) if (!frames.is_empty() && !frames.contains(&f.index)) || exclude.contains(&f.index) => {
                            return None;
                        }
                        other => other,
                    };
                    Some(frame.and_then(|f| {
                        growth.add(&f)?;
                        used.push(f.index);
                        Ok((f.index, f))
                    }))
                });
                build(&mut chosen, None)?
            };
            let streamed = stream.report().context("the bag's reader stopped without a report")?;
            posed(path, &topic, streamed.frames, &streamed.skipped)?;
            // (The selection again, now that the number of frames is known: its errors.)
            select_frames(streamed.frames, frames, exclude)?;
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
            posed(path, topic, scans.len(), &skipped)?;
            Ok(scans)
        }
    }
}

/// A build from frames as they come, each with its index, and how many will come if known.
pub type FrameBuild<'a> = dyn FnMut(&mut Readings<'_, Frame>, Option<usize>) -> Result<BuildReport> + 'a;

/// Readings as they come, each with its index.
pub type Readings<'a, R> = dyn Iterator<Item = mrfmap::Result<(usize, R)>> + 'a;

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

/// A warning for the `skipped` messages, or an error when none of them had a pose (`count`).
#[cfg(feature = "bags")]
fn posed(path: &std::path::Path, topic: &str, count: usize, skipped: &[String]) -> Result<()> {
    if let Some(first) = skipped.first() {
        tracing::warn!(
            "{}: {topic}: {} message(s) skipped without a pose (first: {first})",
            path.display(),
            skipped.len()
        );
    }
    if count == 0 {
        bail!("{}: no image or scan of {topic} has a pose", path.display());
    }
    Ok(())
}

/// The memory check of a streamed build: the map's estimate from the poses so far and a few
/// frames spread over them, checked each time the number of frames doubles (a recording's
/// length is known only at its end), and the resident size at every frame (between two
/// estimates the map may double).
#[cfg(feature = "bags")]
struct Growth<'a> {
    config: &'a EngineConfig,
    poses: Vec<mrfmap::frames::Pose>,
    /// Every `stride`-th frame, at most `SAMPLE_FRAMES` of them (the stride doubles).
    sample: Vec<Frame>,
    stride: usize,
}

#[cfg(feature = "bags")]
impl<'a> Growth<'a> {
    fn new(config: &'a EngineConfig) -> Self {
        Growth { config, poses: Vec::new(), sample: Vec::new(), stride: 1 }
    }

    fn add(&mut self, frame: &Frame) -> mrfmap::Result<()> {
        let n = self.poses.len();
        self.poses.push(frame.pose);
        if n.is_multiple_of(self.stride) {
            self.sample.push(frame.clone());
            if self.sample.len() > SAMPLE_FRAMES {
                // Frames 0, s, 2s, ... are kept: those at even places are the multiples of 2s.
                self.stride *= 2;
                let mut place = 0;
                self.sample.retain(|_| {
                    place += 1;
                    place % 2 == 1
                });
            }
        }
        // Between estimates the map may double: the resident size is checked at every frame.
        let limit = mrfmap::limits::max_memory();
        if let Some(resident) = mrfmap::limits::resident_memory().filter(|&r| r > limit) {
            return Err(mrfmap::Error::Invalid(format!(
                "the map outgrew the memory limit after {} frames ({} resident, limit {}; {BUILD_ADVICE}, or raise \
                 the limit with --max-memory / MRFMAP_MAX_MEMORY)",
                n + 1,
                mrfmap::limits::human(resident as f64),
                mrfmap::limits::human(limit as f64)
            )));
        }
        if !(n + 1).is_power_of_two() {
            return Ok(());
        }
        check_build(self.config, frames_extent(self.poses.iter().copied(), &self.sample, self.config), BUILD_ADVICE)
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder (TUM / ICL-NUIM layout with camera.toml), a CARMEN laser log file
    /// (plain or .gz; a one-voxel-thick map at z = 0 to one voxel), or a ROS 2 bag (.mcap, .db3 or
    /// a bag folder) or ROS 1 .bag (with --depth-topic and --fixed-frame or --pose-topic).
    dataset: PathBuf,
    /// Output map file.
    #[arg(short, long)]
    output: PathBuf,
    /// Inference engine: logodds, mrf or crm.
    #[arg(long, default_value = "logodds", value_parser = super::choice::<EngineKind>())]
    engine: EngineKind,
    /// Voxel edge in metres.
    #[arg(long, value_parser = super::positive, allow_hyphen_values = true)]
    resolution: f64,
    /// Frame indices to leave out (held-out views), e.g. 3,7.
    #[arg(long, value_delimiter = ',')]
    exclude: Vec<usize>,
    /// Only these frame indices (default: all).
    #[arg(long, value_delimiter = ',')]
    frames: Vec<usize>,
    /// Build a tiled map: OUTPUT is then a folder of tiles of this edge (metres; a whole
    /// number of 8-voxel bricks) and their index, each tile built alone from the frames that
    /// reach it, so memory holds one tile at a time (dataset folders).
    #[arg(long, value_parser = super::positive)]
    tile: Option<f64>,
    /// With --tile: also cut tiles in z, into layers of this height (metres, whole bricks);
    /// without it tiles are columns through every height (what a building or a campus needs).
    #[arg(long, requires = "tile", value_parser = super::positive)]
    tile_height: Option<f64>,
    /// With --tile: metres around each tile that its build maps too, then cuts away (default
    /// 1 m for mrf and crm; 0 for logodds, whose tiles equal the map built whole anyway).
    #[arg(long, requires = "tile", value_parser = super::non_negative)]
    tile_margin: Option<f64>,
    #[command(flatten)]
    options: MapOptions,
    #[command(flatten)]
    laser: LaserOptions,
    #[command(flatten)]
    bag: BagArgs,
    #[command(flatten)]
    online: OnlineArgs,
    #[command(flatten)]
    snapshots: SnapshotArgs,
}

/// Live output while a map is built (`--snapshot-every`, `--mcap-timeline`).
#[derive(clap::Args, Clone)]
pub struct SnapshotArgs {
    /// Depth frames: also write the map as it was every SECONDS of recording time (the
    /// frames' stamps; the first after the first frame) into the folder DIR, as
    /// DIR/NNNNN_TIME.mrfmap, each written atomically so that a robot stack or a viewer can
    /// pick them up; the last frame's map is written too. The MRF needs --online for this.
    #[arg(long, num_args = 2, value_names = ["SECONDS", "DIR"], allow_hyphen_values = true)]
    pub snapshot_every: Option<Vec<String>>,
    /// With --snapshot-every: also write the snapshots as a Foxglove timeline (MCAP): one
    /// foxglove.SceneUpdate per snapshot at its recording time, holding the bricks whose cubes
    /// changed and deleting the bricks left without any (cubes above 0.5, coloured by
    /// occupancy).
    #[arg(long, requires = "snapshot_every")]
    pub mcap_timeline: Option<PathBuf>,
}

impl SnapshotArgs {
    /// The snapshot writer these options ask for, checked before any work.
    fn snapshots(&self) -> Result<Option<Snapshots>> {
        let Some(v) = &self.snapshot_every else { return Ok(None) };
        let every: f64 = v[0]
            .parse()
            .ok()
            .filter(|s: &f64| *s > 0.0 && s.is_finite())
            .with_context(|| format!("--snapshot-every: {:?} is not a positive number of seconds", v[0]))?;
        let dir = PathBuf::from(&v[1]);
        std::fs::create_dir_all(&dir).with_context(|| format!("--snapshot-every: cannot create {}", dir.display()))?;
        if let Some(t) = &self.mcap_timeline {
            check_output_folder(t)?;
        }
        let timeline = self.mcap_timeline.clone().map(|path| (path, None));
        Ok(Some(Snapshots { every, dir, next: None, last: None, written: 0, timeline }))
    }
}

/// Writes the map as it is built, every `every` seconds of recording time: map files into
/// `dir`, and optionally a Foxglove timeline.
pub struct Snapshots {
    every: f64,
    dir: PathBuf,
    /// The recording time of the next snapshot (`None` before the first frame).
    next: Option<f64>,
    /// The time of the last frame integrated, and whether a snapshot holds it.
    last: Option<(f64, bool)>,
    written: usize,
    /// The timeline's path and, once the first snapshot is taken, its writer.
    timeline: Option<(PathBuf, Option<mrfmap::outputs::SceneTimeline>)>,
}

impl Snapshots {
    /// After a reading stamped `time` went into `engine`: a snapshot if one is due.
    fn after(&mut self, time: Option<f64>, engine: &dyn Engine) -> Result<()> {
        let Some(time) = time else { bail!("--snapshot-every needs readings with timestamps (depth frames)") };
        let next = *self.next.get_or_insert(time);
        self.last = Some((time, false));
        if time >= next {
            self.next = Some(next + self.every * ((time - next) / self.every).floor() + self.every);
            self.write(time, engine)?;
        }
        Ok(())
    }

    fn write(&mut self, time: f64, engine: &dyn Engine) -> Result<()> {
        let mut map = engine.map();
        map.params.insert("snapshot_time".into(), format!("{time:.6}"));
        let path = self.dir.join(format!("{:05}_{time:.3}.mrfmap", self.written));
        map.save(&path)?;
        if let Some((file, timeline)) = &mut self.timeline {
            if timeline.is_none() {
                *timeline = Some(mrfmap::outputs::SceneTimeline::create(file, &map, Default::default())?);
            }
            timeline.as_mut().expect("just made").add(&map, time)?;
        }
        self.written += 1;
        self.last = Some((time, true));
        Ok(())
    }

    /// After the last reading: its map too (if no snapshot holds it yet), and the timeline put
    /// in place. Returns the snapshots written.
    fn finish(mut self, engine: &dyn Engine) -> Result<usize> {
        if let Some((time, false)) = self.last {
            self.write(time, engine)?;
        }
        if let Some((_, Some(timeline))) = self.timeline {
            timeline.finish()?;
        }
        Ok(self.written)
    }
}

/// The MRF's online schedule (`--online`).
#[derive(clap::Args, Clone)]
pub struct OnlineArgs {
    /// MRF: feed the frames in order as a robot would: each keyframe is traced as it
    /// arrives, then belief propagation works on the tiles whose inputs moved most until
    /// --budget-ms / --budget-tiles is spent; the rest waits for the next keyframes. The map
    /// written is what the robot had after the last frame (no extra sweeps without --finish).
    #[arg(long)]
    pub online: bool,
    /// With --online: wall-clock milliseconds per keyframe, from its arrival (decoded) to
    /// the map being readable again, its own tracing included (the keyframe is traced whole
    /// even when that takes longer).
    #[arg(long, requires = "online", value_parser = super::non_negative)]
    pub budget_ms: Option<f64>,
    /// With --online: tiles traced per keyframe, its own included (a budget that gives the
    /// same map on any machine). Neither budget: every keyframe is inferred until settled.
    #[arg(long, requires = "online")]
    pub budget_tiles: Option<usize>,
    /// With --online: write one CSV row per keyframe: keyframe,ms,traced_tiles,backlog_tiles.
    #[arg(long, requires = "online")]
    pub timings: Option<PathBuf>,
    /// With --online: after the last frame, run the batch schedule (--iterations,
    /// --tolerance) to finish the inference before the map is written.
    #[arg(long, requires = "online")]
    pub finish: bool,
}

/// Fails unless `path`'s folder exists (checked before the work, not after it).
pub fn check_output_folder(path: &std::path::Path) -> Result<()> {
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
    if !folder.is_dir() {
        bail!("{}: the output folder {} does not exist", path.display(), folder.display());
    }
    Ok(())
}

/// What a build did.
pub struct BuildReport {
    pub map: Map,
    pub frames: usize,
    pub integrate_time: Duration,
}

/// Checks that every index names a frame of a dataset with `len` frames.
pub fn check_indices(len: usize, indices: &[usize]) -> Result<()> {
    match indices.iter().find(|&&i| i >= len) {
        Some(i) => bail!("frame index {i} is out of range: the dataset has {len} frames (0..{})", len - 1),
        None => Ok(()),
    }
}

/// The frames to use: `frames` (or all) minus `exclude`; indices must exist.
pub fn select_frames(len: usize, frames: &[usize], exclude: &[usize]) -> Result<Vec<usize>> {
    check_indices(len, frames)?;
    check_indices(len, exclude)?;
    let chosen: Vec<usize> = if frames.is_empty() { (0..len).collect() } else { frames.to_vec() };
    let chosen: Vec<usize> = chosen.into_iter().filter(|i| !exclude.contains(i)).collect();
    if chosen.is_empty() {
        bail!("no frames left to integrate after --frames / --exclude");
    }
    Ok(chosen)
}

/// A reading an engine integrates: a depth image or a range scan.
pub trait Reading {
    /// Adds this reading's evidence to `engine`.
    fn integrate_into(&self, engine: &mut dyn Engine) -> mrfmap::Result<()>;
    /// The reading's recording time (seconds), if it has one.
    fn timestamp(&self) -> Option<f64>;
}

impl Reading for Frame {
    fn integrate_into(&self, engine: &mut dyn Engine) -> mrfmap::Result<()> {
        engine.integrate(self)
    }

    fn timestamp(&self) -> Option<f64> {
        Some(self.timestamp)
    }
}

impl Reading for RangeScan {
    fn timestamp(&self) -> Option<f64> {
        None
    }

    fn integrate_into(&self, engine: &mut dyn Engine) -> mrfmap::Result<()> {
        engine.integrate_scan(self)
    }
}

/// `0-5,7,9-11` for the sorted indices.
pub fn format_ranges(indices: &[usize]) -> String {
    let mut sorted = indices.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let mut parts = Vec::new();
    let mut i = 0;
    while i < sorted.len() {
        let mut j = i;
        while j + 1 < sorted.len() && sorted[j + 1] == sorted[j] + 1 {
            j += 1;
        }
        parts.push(if i == j { sorted[i].to_string() } else { format!("{}-{}", sorted[i], sorted[j]) });
        i = j + 1;
    }
    parts.join(",")
}

/// The indices of [`format_ranges`]' text (malformed parts are skipped).
pub fn parse_ranges(text: &str) -> Vec<usize> {
    text.split(',')
        .flat_map(|part| match part.split_once('-') {
            Some((a, b)) => match (a.parse::<usize>(), b.parse::<usize>()) {
                (Ok(a), Ok(b)) if b >= a && b - a < 10_000_000 => (a..=b).collect(),
                _ => Vec::new(),
            },
            None => part.parse().ok().into_iter().collect(),
        })
        .collect()
}

/// Frames decoded for the memory estimate, at most.
const SAMPLE_FRAMES: usize = 8;

/// What a build refused for memory can change.
pub const BUILD_ADVICE: &str = "use a coarser --resolution, or map less with --bounds or --max-range";

/// Where the frames `indices` of `dataset` look, estimated from every pose and a few decoded
/// frames (decoding every frame twice would double the I/O).
pub fn dataset_extent(dataset: &Dataset, indices: &[usize], config: &EngineConfig) -> Result<Option<Extent>> {
    let step = indices.len().div_ceil(SAMPLE_FRAMES).max(1);
    let sampled = indices.iter().step_by(step).map(|&i| dataset.frame(i)).collect::<mrfmap::Result<Vec<_>>>()?;
    let poses = indices.iter().map(|&i| dataset.frames()[i].pose);
    Ok(frames_extent(poses, &sampled, config))
}

/// Integrates the readings `indices` (fetched through `reading`) with the engine `config`
/// describes, with a progress bar.
pub fn build_map<R: Reading>(
    indices: &[usize],
    config: &EngineConfig,
    mut reading: impl FnMut(usize) -> mrfmap::Result<R>,
) -> Result<BuildReport> {
    let mut readings = indices.iter().map(|&i| reading(i).map(|r| (i, r)));
    build_map_with(&mut readings, Some(indices.len()), config, None)
}

/// [`build_map`] from readings as they come (`count` of them, if known), writing `snapshots`
/// as it goes.
pub fn build_map_with<R: Reading>(
    readings: &mut Readings<'_, R>,
    count: Option<usize>,
    config: &EngineConfig,
    mut snapshots: Option<Snapshots>,
) -> Result<BuildReport> {
    let mut engine = new_engine(config)?;
    let bar = crate::progress::bar(count, config.kind.name());
    let (mut integrate_time, mut frames) = (Duration::ZERO, 0);
    for reading in readings {
        let (i, reading) = reading?;
        frames += 1;
        let t = Instant::now();
        reading.integrate_into(engine.as_mut()).with_context(|| format!("integrating reading {i}"))?;
        integrate_time += t.elapsed();
        if let Some(s) = &mut snapshots {
            s.after(reading.timestamp(), engine.as_ref())?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if let Some(s) = snapshots {
        // (Not inside the log macro: with the level off, it would not run.)
        let written = s.finish(engine.as_ref())?;
        tracing::info!("{written} snapshots written");
    }
    let t = Instant::now();
    let bar = crate::progress::bar(Some(0), "inference");
    engine.finish_with_progress(&mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    integrate_time += t.elapsed();
    Ok(BuildReport { map: engine.into_map(), frames, integrate_time })
}

/// Feeds frames as they come (`count` of them, if known) to an MRF engine in order on its
/// online schedule ([`MrfEngine::add_keyframe_within`]), with a progress bar of keyframes,
/// per-keyframe milliseconds and backlog, and the timings CSV `online` asks for.
pub fn build_online(
    readings: &mut Readings<'_, Frame>,
    count: Option<usize>,
    config: &EngineConfig,
    online: &OnlineArgs,
    mut snapshots: Option<Snapshots>,
) -> Result<BuildReport> {
    config.limits.validate()?;
    let mut engine = MrfEngine::new(config.resolution, config.limits, config.mrf)?;
    let budget = Budget { ms: online.budget_ms, tiles: online.budget_tiles };
    let bar = crate::progress::bar(count, "mrf online");
    let mut rows = Vec::new();
    let (mut integrate_time, mut frames) = (Duration::ZERO, 0);
    for reading in readings {
        let (i, frame) = reading?;
        frames += 1;
        let frame_time = frame.timestamp;
        if engine.is_new_keyframe(&frame.pose) {
            let (_, r) = engine.add_keyframe_within(frame, budget).with_context(|| format!("integrating frame {i}"))?;
            integrate_time += r.elapsed;
            rows.push(r);
            bar.set_message(format!(
                "kf {} {:.0} ms, backlog {}",
                rows.len(),
                r.elapsed.as_secs_f64() * 1e3,
                r.backlog
            ));
            tracing::debug!("frame {i}: keyframe {}: {r:?}", rows.len());
        }
        if let Some(s) = &mut snapshots {
            s.after(Some(frame_time), &engine)?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if let Some(s) = snapshots {
        let written = s.finish(&engine)?;
        tracing::info!("{written} snapshots written");
    }
    let (last_backlog, settled) = rows.last().map_or((0, true), |r| (r.backlog, r.settled));
    if online.finish {
        let t = Instant::now();
        engine.finish()?;
        integrate_time += t.elapsed();
    } else if !settled {
        tracing::info!(
            "MRF online: {last_backlog} tiles still in the backlog (--finish would infer them before writing)"
        );
    }
    if let Some(path) = &online.timings {
        write_atomic(path, |w| {
            writeln!(w, "keyframe,ms,traced_tiles,backlog_tiles")?;
            for (n, r) in rows.iter().enumerate() {
                writeln!(w, "{},{:.3},{},{}", n + 1, r.elapsed.as_secs_f64() * 1e3, r.tiles, r.backlog)?;
            }
            Ok(())
        })?;
    }
    Ok(BuildReport { map: engine.map(), frames, integrate_time })
}

pub fn run(a: Args) -> Result<()> {
    let kind = a.engine;
    check_output_folder(&a.output)?;
    if let Some(edge) = a.tile {
        return build_tiled(&a, edge);
    }
    // A map named like another format would be a .mrfmap file under a misleading name.
    let extension = a.output.extension().map(|e| e.to_string_lossy().to_lowercase());
    if let Some(ext) = extension.filter(|e| ["bt", "ot", "ply", "mcap", "png", "pgm", "yaml"].contains(&e.as_str())) {
        bail!(
            "{}: build writes .mrfmap maps; for .{ext} build a .mrfmap and convert it with `mrfmap export` \
             (or `project` for a 2D grid)",
            a.output.display()
        );
    }
    let scans = !BagArgs::is_bag(&a.dataset) && a.dataset.is_file() || a.bag.scan_topic.is_some();
    if scans && kind == EngineKind::Mrf {
        // Said before the memory estimate, which cannot size an MRF from range scans.
        bail!(
            "{}: the mrf engine takes depth images only (a dataset or a bag's --depth-topic); range scans work \
             with logodds and crm",
            a.dataset.display()
        );
    }
    let online = a.online.online.then_some(&a.online);
    if let Some(o) = online {
        if kind != EngineKind::Mrf {
            bail!("--online is the MRF's schedule (--engine mrf); log-odds and CRM integrate each frame as it comes");
        }
        if let Some(t) = &o.timings {
            check_output_folder(t)?;
        }
    }
    let config = a.options.config(kind, a.resolution)?;
    if a.snapshots.snapshot_every.is_some() && (scans || kind == EngineKind::Mrf && online.is_none()) {
        bail!(
            "--snapshot-every takes depth frames (a dataset or a bag's --depth-topic), and with --engine mrf \
             --online: the batch MRF infers only after the last frame"
        );
    }
    let mut snapshots = a.snapshots.snapshots()?;
    let mut build = |readings: &mut Readings<'_, Frame>, count: Option<usize>| match online {
        Some(o) => build_online(readings, count, &config, o, snapshots.take()),
        None => build_map_with(readings, count, &config, snapshots.take()),
    };
    let mut up = None;
    let (report, indices_used) = if let (true, Some(topic)) = (BagArgs::is_bag(&a.dataset), &a.bag.scan_topic) {
        let mut scans = a.bag.scans(&a.dataset, topic, a.options.noise.as_deref())?;
        scans.iter_mut().for_each(|s| a.laser.apply_misses(s));
        let indices = select_frames(scans.len(), &a.frames, &a.exclude)?;
        let chosen: Vec<RangeScan> = indices.iter().map(|&i| scans[i].clone()).collect();
        check_build(&config, scan_extent(&chosen, &config), BUILD_ADVICE)?;
        tracing::info!("{}: {} of {} scans, engine {kind}", a.dataset.display(), indices.len(), scans.len());
        (build_map(&indices, &config, |i| Ok(scans[i].clone()))?, indices)
    } else if BagArgs::is_bag(&a.dataset) {
        let pick = (a.frames.as_slice(), a.exclude.as_slice());
        a.bag.build_streamed(&a.dataset, a.options.noise.as_deref(), pick, &config, &mut build)?
    } else if a.dataset.is_file() {
        let log = a.laser.open(&a.dataset)?;
        let scans = a.laser.scans(&log, a.resolution, a.options.noise.as_deref())?;
        let indices = select_frames(scans.len(), &a.frames, &a.exclude)?;
        let chosen: Vec<RangeScan> = indices.iter().map(|&i| scans[i].clone()).collect();
        check_build(&config, scan_extent(&chosen, &config), BUILD_ADVICE)?;
        tracing::info!(
            "{}: {} of {} laser scans, engine {kind}, resolution {} m",
            a.dataset.display(),
            indices.len(),
            log.readings.len(),
            a.resolution
        );
        (build_map(&indices, &config, |i| Ok(scans[i].clone()))?, indices)
    } else {
        let dataset = a.options.open(&a.dataset)?;
        let indices = select_frames(dataset.len(), &a.frames, &a.exclude)?;
        check_build(&config, dataset_extent(&dataset, &indices, &config)?, BUILD_ADVICE)?;
        tracing::info!(
            "{}: {} of {} frames, engine {kind}, resolution {} m",
            a.dataset.display(),
            indices.len(),
            dataset.len(),
            a.resolution
        );
        up = dataset.up();
        let mut readings = indices.iter().map(|&i| dataset.frame(i).map(|f| (i, f)));
        (build(&mut readings, Some(indices.len()))?, indices)
    };
    let mut map = report.map;
    // What went in, so `eval` can tell held-out views from views the map was built from.
    map.params.insert("source".into(), a.dataset.display().to_string());
    map.params.insert("frames".into(), format_ranges(&indices_used));
    // The world's up axis, which `view` stands the map on.
    if let Some(up) = up {
        map.params.insert("up".into(), up.to_string());
    }
    map.save(&a.output)?;
    println!(
        "{}: {} frames, {} voxels ({} occupied), {:.1} ms/frame",
        a.output.display(),
        report.frames,
        map.voxels.len(),
        map.occupied_count(),
        report.integrate_time.as_secs_f64() * 1e3 / report.frames as f64
    );
    Ok(())
}

/// `build --tile`: the dataset's frames planned onto tiles (each frame read once), every
/// tile's memory estimate checked, then the tiles built one at a time into the folder
/// `--output`, its index written last.
fn build_tiled(a: &Args, edge: f64) -> Result<()> {
    if a.online.online || a.snapshots.snapshot_every.is_some() {
        bail!("--tile builds a map tile by tile; --online and --snapshot-every follow one map as it grows");
    }
    if BagArgs::is_bag(&a.dataset) || a.dataset.is_file() {
        bail!(
            "{}: --tile takes a dataset folder (a bag's depth images become one with `mrfmap export-dataset`)",
            a.dataset.display()
        );
    }
    if a.output.exists() && !a.output.is_dir() {
        bail!("{}: --tile writes a folder of tiles, and this is a file", a.output.display());
    }
    let config = a.options.config(a.engine, a.resolution)?;
    let tiling = Tiling::new(&config, edge, a.tile_height, a.tile_margin)?;
    let dataset = a.options.open(&a.dataset)?;
    let indices = select_frames(dataset.len(), &a.frames, &a.exclude)?;
    let bar = crate::progress::bar(Some(indices.len()), "planning");
    let plan = tiling.plan(&config, &indices, |i| {
        bar.inc(1);
        dataset.frame(i)
    })?;
    bar.finish_and_clear();
    if plan.is_empty() {
        bail!("{}: no frame reaches any tile (no valid depth within the bounds)", a.dataset.display());
    }
    // Neighbouring tiles share frames: decoded ones are kept for the next tiles.
    let mut cache = FrameCache::new(&dataset);
    // Every tile's estimate before the first is built: a refusal comes before any work.
    let mut largest = (0.0, TileKey([0; 3]));
    for (key, frames) in &plan {
        let pose = |i: usize| dataset.frames()[i].pose;
        let estimate = tiling.estimate(&config, *key, frames, pose, |i| cache.get(i))?;
        if estimate > largest.0 {
            largest = (estimate, *key);
        }
    }
    mrfmap::limits::check_memory(
        &format!("tile {:?}, the largest, as a {} map at {} m", largest.1.0, a.engine, a.resolution),
        largest.0,
        TILE_ADVICE,
    )?;
    let integrations: usize = plan.values().map(Vec::len).sum();
    tracing::info!(
        "{}: {} frames onto {} tiles of {} m ({integrations} tile-frames, margin {} m), engine {}",
        a.dataset.display(),
        indices.len(),
        plan.len(),
        tiling.grid.edge(),
        tiling.margin,
        a.engine
    );
    std::fs::create_dir_all(&a.output).with_context(|| format!("{}: cannot create the folder", a.output.display()))?;
    let bar = crate::progress::bar(Some(plan.len()), "tiles");
    let started = Instant::now();
    let mut entries = Vec::with_capacity(plan.len());
    let mut params = BTreeMap::new();
    for (key, frames) in &plan {
        let (entry, tile_params) = tiling
            .build_into(&a.output, &config, *key, frames.iter().map(|&i| cache.get(i)))
            .with_context(|| format!("tile {:?}", key.0))?;
        if params.is_empty() {
            params = tile_params;
        }
        entries.push(entry);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let elapsed = started.elapsed();
    params.insert("source".into(), a.dataset.display().to_string());
    params.insert("frames".into(), format_ranges(&indices));
    if let Some(up) = dataset.up() {
        params.insert("up".into(), up.to_string());
    }
    let mut index = tiling.index(&config, params);
    index.tiles = entries;
    index.save(&a.output)?;
    let (voxels, occupied): (u64, u64) = index.tiles.iter().fold((0, 0), |(v, o), t| (v + t.voxels, o + t.occupied));
    println!(
        "{}: {} tiles, {} frames, {voxels} voxels ({occupied} occupied), {:.1} ms/frame",
        a.output.display(),
        index.tiles.len(),
        indices.len(),
        elapsed.as_secs_f64() * 1e3 / indices.len() as f64
    );
    Ok(())
}

/// Decoded frames of a dataset kept for reuse, the oldest dropped first beyond a budget of
/// memory (a tenth of the limit, at most 1 GiB).
struct FrameCache<'a> {
    dataset: &'a Dataset,
    frames: std::collections::HashMap<usize, Arc<Frame>>,
    order: std::collections::VecDeque<usize>,
    bytes: usize,
    budget: usize,
}

impl<'a> FrameCache<'a> {
    fn new(dataset: &'a Dataset) -> Self {
        let budget = (mrfmap::limits::max_memory() / 10).min(1 << 30) as usize;
        FrameCache { dataset, frames: Default::default(), order: Default::default(), bytes: 0, budget }
    }

    fn get(&mut self, index: usize) -> mrfmap::Result<Arc<Frame>> {
        if let Some(f) = self.frames.get(&index) {
            return Ok(f.clone());
        }
        let frame = Arc::new(self.dataset.frame(index)?);
        let size = |f: &Frame| std::mem::size_of_val(f.depth.data());
        self.bytes += size(&frame);
        self.frames.insert(index, frame.clone());
        self.order.push_back(index);
        while self.bytes > self.budget && self.order.len() > 1 {
            let old = self.order.pop_front().expect("more than one");
            if let Some(f) = self.frames.remove(&old) {
                self.bytes -= size(&f);
            }
        }
        Ok(frame)
    }
}

/// What a tiled build refused for memory can change.
const TILE_ADVICE: &str = "use smaller --tile, a coarser --resolution, or --max-range";

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
