//! `mrfmap build`: a dataset, laser log or bag in; a map file, or a folder of tiles, out.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};

use super::options::{BagArgs, LaserOptions, MapOptions, build_engine_of, check_output_folder};
use crate::progress::Bars;
use mrfmap::atomic_file::write_atomic;
use mrfmap::frames::{Frame, RangeScan};
use mrfmap::inference::{Budget, EngineConfig, EngineKind, MapOutput, Tiling, check_build, scan_extent};
use mrfmap::map::TileKey;
use mrfmap::pipeline::{
    BUILD_ADVICE, Built, Readings, Snapshots, build_engine, build_online, dataset_extent, format_ranges, read_ahead,
    select_frames,
};
use mrfmap::source::FrameCache;

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
        let snapshots = Snapshots::new(every, &dir).with_context(|| format!("--snapshot-every: {}", dir.display()))?;
        Ok(Some(match &self.mcap_timeline {
            Some(t) => {
                check_output_folder(t)?;
                snapshots.with_timeline(t)
            }
            None => snapshots,
        }))
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

/// Feeds frames as they come to an MRF engine on its online schedule
/// ([`mrfmap::pipeline::build_online`]), with progress bars and the timings CSV `online` asks for.
fn build_online_with(
    readings: &mut Readings<'_, Frame>,
    count: Option<usize>,
    config: &EngineConfig,
    online: &OnlineArgs,
    snapshots: Option<Snapshots>,
) -> Result<Built> {
    let budget = Budget { ms: online.budget_ms, tiles: online.budget_tiles };
    let r = build_online(config, readings, count, budget, online.finish, &mut Bars::default(), snapshots)?;
    if let Some(path) = &online.timings {
        write_atomic(path, |w| {
            writeln!(w, "keyframe,ms,traced_tiles,backlog_tiles")?;
            for (n, k) in r.keyframes.iter().enumerate() {
                writeln!(w, "{},{:.3},{},{}", n + 1, k.elapsed.as_secs_f64() * 1e3, k.tiles, k.backlog)?;
            }
            Ok(())
        })?;
    }
    Ok(r.build)
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
    // Depth frames, from a dataset or a bag, go through one of the two loops.
    // (`config` as a parameter: a dataset's, which knows its camera before the first frame.)
    let mut frames_build =
        |readings: &mut Readings<'_, Frame>, count: Option<usize>, config: &EngineConfig| match online {
            Some(o) => build_online_with(readings, count, config, o, snapshots.take()),
            None => Ok(build_engine(config, readings, count, &mut Bars::default(), snapshots.take())?),
        };
    let mut up = None;
    let (report, indices_used) = if let (true, Some(topic)) = (BagArgs::is_bag(&a.dataset), &a.bag.scan_topic) {
        let mut scans = a.bag.scans(&a.dataset, topic, a.options.noise.as_deref())?;
        scans.iter_mut().for_each(|s| a.laser.apply_misses(s));
        let indices = select_frames(scans.len(), &a.frames, &a.exclude)?;
        let chosen: Vec<RangeScan> = indices.iter().map(|&i| scans[i].clone()).collect();
        check_build(&config, scan_extent(&chosen, &config), MapOutput::Saved, BUILD_ADVICE)?;
        tracing::info!("{}: {} of {} scans, engine {kind}", a.dataset.display(), indices.len(), scans.len());
        (build_engine_of(&indices, &config, |i| Ok(scans[i].clone()))?, indices)
    } else if BagArgs::is_bag(&a.dataset) {
        let pick = (a.frames.as_slice(), a.exclude.as_slice());
        a.bag.build_streamed(&a.dataset, a.options.noise.as_deref(), pick, &config, &mut frames_build)?
    } else if a.dataset.is_file() {
        let log = a.laser.open(&a.dataset)?;
        let scans = a.laser.scans(&log, a.resolution, a.options.noise.as_deref())?;
        let indices = select_frames(scans.len(), &a.frames, &a.exclude)?;
        let chosen: Vec<RangeScan> = indices.iter().map(|&i| scans[i].clone()).collect();
        check_build(&config, scan_extent(&chosen, &config), MapOutput::Saved, BUILD_ADVICE)?;
        tracing::info!(
            "{}: {} of {} laser scans, engine {kind}, resolution {} m",
            a.dataset.display(),
            indices.len(),
            log.readings.len(),
            a.resolution
        );
        (build_engine_of(&indices, &config, |i| Ok(scans[i].clone()))?, indices)
    } else {
        let dataset = a.options.open(&a.dataset)?;
        let indices = select_frames(dataset.len(), &a.frames, &a.exclude)?;
        check_build(&config, dataset_extent(&dataset, &indices, &config)?, MapOutput::Saved, BUILD_ADVICE)?;
        tracing::info!(
            "{}: {} of {} frames, engine {kind}, resolution {} m",
            a.dataset.display(),
            indices.len(),
            dataset.len(),
            a.resolution
        );
        up = dataset.up();
        let config = EngineConfig { camera: Some(*dataset.camera()), ..config };
        let built = read_ahead(
            &indices,
            |i| dataset.frame(i),
            |readings| frames_build(readings, Some(indices.len()), &config),
        )?;
        (built, indices)
    };
    // What went in, so `eval` can tell held-out views from views the map was built from.
    let mut params = BTreeMap::new();
    params.insert("source".into(), a.dataset.display().to_string());
    params.insert("frames".into(), format_ranges(&indices_used));
    // The world's up axis, which `view` stands the map on.
    if let Some(up) = up {
        params.insert("up".into(), up.to_string());
    }
    // Straight from the engine to the file: no finished map held beside the engine's state.
    let saved = report.engine.save_map(&a.output, &params)?;
    println!(
        "{}: {} frames, {} voxels ({} occupied), {:.2} ms/frame",
        a.output.display(),
        report.frames,
        saved.voxels,
        saved.occupied,
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
        "{}: {} tiles, {} frames, {voxels} voxels ({occupied} occupied), {:.2} ms/frame",
        a.output.display(),
        index.tiles.len(),
        indices.len(),
        elapsed.as_secs_f64() * 1e3 / indices.len() as f64
    );
    Ok(())
}

/// What a tiled build refused for memory can change.
const TILE_ADVICE: &str = "use smaller --tile, a coarser --resolution, or --max-range";
