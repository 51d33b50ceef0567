//! `mrfmap bench`: per-frame integration time at several resolutions, frames (or a laser
//! log's scans) preloaded so only the engine is timed. Build with `--release`; the peer script
//! compares it with OctoMap.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use mrfmap::inference::{
    CrmParams, EngineConfig, EngineKind, LogOddsParams, Marking, MrfEngine, MrfParams, new_engine,
};

use super::options::{BagArgs, LaserOptions};
use mrfmap::frames::Frame;
use mrfmap::pipeline::Reading;
use mrfmap::source::Dataset;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder, a CARMEN laser log file, or a ROS bag (with --depth-topic and
    /// --fixed-frame or --pose-topic).
    dataset: PathBuf,
    /// Engine to time: logodds, mrf or crm.
    #[arg(long, default_value = "logodds", value_parser = super::choice::<EngineKind>())]
    engine: EngineKind,
    /// Resolutions (metres).
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.02, 0.01])]
    resolutions: Vec<f64>,
    /// Builds per resolution; the fastest is reported (least disturbed by other load).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
    /// MRF only: also time adding the last frame as a keyframe to a map of all the others,
    /// inferred to convergence first (not timed), and inferring again with the change-driven
    /// schedule (tolerance 0.001, at most 10 sweeps; median of --repeat runs). `build --online
    /// --timings` times the online schedule.
    #[arg(long)]
    incremental: bool,
    /// MRF only: trace one ray per block of pixels whose rays lie at most this many voxel
    /// edges apart (build's --ray-spacing); 0 (default) traces every pixel.
    #[arg(long, default_value_t = 0.0, value_parser = super::non_negative)]
    ray_spacing: f64,
    /// CRM only: particles per voxel.
    #[arg(long, default_value_t = 101)]
    particles: usize,
    /// Log-odds only: find crossed voxels by projection or by walking every ray, or decide
    /// them by their centres (`build --marking`).
    #[arg(long, default_value = "project", value_parser = super::choice::<Marking>())]
    marking: Marking,
    #[command(flatten)]
    laser: LaserOptions,
    #[command(flatten)]
    bag: BagArgs,
}

impl Args {
    /// The MRF's parameters: the defaults with `--ray-spacing`.
    fn mrf_params(&self) -> MrfParams {
        MrfParams { ray_spacing: self.ray_spacing, ..MrfParams::default() }
    }
}

/// Sweeps allowed for inferring the map that a keyframe is added to (not timed).
pub(crate) const BASE_SWEEPS: usize = 300;

/// Time to add the last frame to an inferred MRF of the others and infer again with the
/// change-driven schedule ([`MrfEngine::run_until`], at most
/// [`mrfmap::inference::DEFAULT_MAX_SWEEPS`] sweeps): the median of `repeat` runs. The map it is
/// added to is inferred to convergence first (at most [`BASE_SWEEPS`] sweeps), as a robot's
/// map is after many keyframes; between runs the keyframe is removed and the map re-inferred
/// the same way (not timed).
fn incremental_mrf(frames: &[Frame], resolution: f64, repeat: u32, params: MrfParams) -> Result<f64> {
    let (last, rest) = frames.split_last().ok_or_else(|| anyhow::anyhow!("no frames"))?;
    let tolerance = params.tolerance.unwrap_or(mrfmap::inference::DEFAULT_TOLERANCE);
    let mut engine = MrfEngine::new(resolution, Default::default(), params)?;
    for f in rest {
        engine.add_keyframe(f.clone())?;
    }
    let base = engine.run_until(tolerance, BASE_SWEEPS);
    tracing::info!("map of {} keyframes at {resolution} m inferred: {base:?}", rest.len());
    let mut times = Vec::new();
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        let id = engine.add_keyframe(last.clone())?;
        engine.run_until(tolerance, mrfmap::inference::DEFAULT_MAX_SWEEPS);
        times.push(t.elapsed().as_secs_f64());
        engine.remove_keyframe(id)?;
        engine.run_until(tolerance, BASE_SWEEPS);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

pub fn run(a: Args) -> Result<()> {
    let kind = a.engine;
    if a.incremental && kind != EngineKind::Mrf {
        anyhow::bail!("--incremental is for --engine mrf");
    }
    if a.ray_spacing > 0.0 && kind != EngineKind::Mrf {
        anyhow::bail!("--ray-spacing is for --engine mrf");
    }
    let incremental = |frames: &[Frame], r: f64| -> Result<String> {
        Ok(if a.incremental {
            format!("\t{:.0}", incremental_mrf(frames, r, a.repeat, a.mrf_params())? * 1e3)
        } else {
            String::new()
        })
    };
    if BagArgs::is_bag(&a.dataset) {
        let frames = a.bag.frames(&a.dataset, None)?;
        return table(&a, kind, frames.len(), "frames", |_| Ok(frames.clone()), incremental);
    }
    if a.dataset.is_file() {
        if a.incremental {
            anyhow::bail!("--incremental needs a depth dataset, not a laser log");
        }
        let log = a.laser.open(&a.dataset)?;
        // Scans depend on the resolution only through their height (the middle of layer 0).
        let scans = |r: f64| a.laser.scans(&log, r, None);
        return table(&a, kind, scans(a.resolutions[0])?.len(), "scans", scans, |_, _| Ok(String::new()));
    }
    let dataset = Dataset::open(&a.dataset)?;
    let frames = (0..dataset.len()).map(|i| dataset.frame(i)).collect::<mrfmap::Result<Vec<_>>>()?;
    table(&a, kind, frames.len(), "frames", |_| Ok(frames.clone()), incremental)
}

/// Prints the table: per resolution the best time per reading of a full build, the map's
/// size, and `extra`'s columns.
fn table<R: Reading>(
    a: &Args,
    kind: EngineKind,
    count: usize,
    what: &str,
    readings: impl Fn(f64) -> Result<Vec<R>>,
    extra: impl Fn(&[R], f64) -> Result<String>,
) -> Result<()> {
    println!(
        "# {count} {what} of {}, engine {kind}{}, {} threads, best of {}",
        a.dataset.display(),
        if kind == EngineKind::LogOdds {
            format!(" (marking: {})", mrfmap::Choice::name(a.marking))
        } else {
            String::new()
        },
        rayon::current_num_threads(),
        a.repeat
    );
    println!(
        "resolution\tms_per_frame\toccupied\tvoxels\tmemory_mib{}",
        if a.incremental { "\tincremental_ms" } else { "" }
    );
    for &resolution in &a.resolutions {
        let items = readings(resolution)?;
        let mut best = f64::INFINITY;
        let mut last = None;
        for _ in 0..a.repeat.max(1) {
            let config = EngineConfig {
                crm: CrmParams { particles: a.particles },
                logodds: LogOddsParams { marking: a.marking, ..Default::default() },
                mrf: a.mrf_params(),
                ..EngineConfig::new(kind, resolution)
            };
            let mut engine = new_engine(&config)?;
            let t = Instant::now();
            for item in &items {
                item.integrate_into(engine.as_mut())?;
            }
            engine.finish()?;
            best = best.min(t.elapsed().as_secs_f64());
            last = Some(engine.map());
        }
        let map = last.expect("at least one run");
        println!(
            "{resolution}\t{:.2}\t{}\t{}\t{:.1}{}",
            best * 1e3 / items.len() as f64,
            map.occupied_count(),
            map.voxels.len(),
            map.voxels.memory_bytes() as f64 / (1 << 20) as f64,
            extra(&items, resolution)?
        );
    }
    Ok(())
}
