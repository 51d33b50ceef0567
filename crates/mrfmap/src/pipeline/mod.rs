//! The pipeline: readings from a source, through an engine, into a map (the build loop). `mrfmap build`,
//! the commands that build on the way to something else (`demo`, `loo`, experiments) and
//! Python (`build_dataset`, `Mapper.add_bag`) all run it, so the same readings with the same
//! options make the same map whichever door they came through.
//!
//! - [`Reading`] is what an engine integrates: a depth [`Frame`] or a [`RangeScan`];
//! - [`integrate`] feeds readings to an engine, reporting [`Progress`] and writing
//!   [`Snapshots`]; [`build`] makes the engine, feeds it and runs its deferred inference;
//!   [`build_engine`] keeps the engine ([`Built`]), to save its map straight to a file;
//!   [`build_online`] feeds an MRF frame by frame on its anytime schedule, as a robot would;
//! - [`read_ahead`]: the next frame read while the engine integrates this one;
//! - which frames, and how a map records them: [`select_frames`], [`format_ranges`];
//! - memory, before and during a build: [`dataset_extent`], [`Growth`];
//! - [`stream_bag`] (feature `bags`): a ROS bag's depth images streamed into any of these.
//!
//! ```no_run
//! use mrfmap::pipeline::{build, select_frames};
//! use mrfmap::inference::{BuildOptions, EngineKind};
//! use mrfmap::source::Dataset;
//!
//! let dataset = Dataset::open("../shared/data/coffin-world".as_ref())?;
//! let options = BuildOptions { max_range: Some(4.0), ..BuildOptions::default() };
//! let config = options.config(EngineKind::Mrf, 0.05)?;
//! let chosen = select_frames(dataset.len(), &[], &[3, 7])?; // views 3 and 7 held out
//! let mut frames = chosen.iter().map(|&i| dataset.frame(i).map(|f| (i, f)));
//! let report = build(&config, &mut frames, Some(chosen.len()), &mut (), None)?;
//! println!("{} frames, {} voxels", report.frames, report.map.voxels.len());
//! # Ok::<(), mrfmap::Error>(())
//! ```

mod ahead;
mod memory;
mod selection;
mod snapshots;
#[cfg(feature = "bags")]
mod stream;

use std::time::{Duration, Instant};

pub use ahead::read_ahead;
pub use memory::{BUILD_ADVICE, Growth, SAMPLE_FRAMES, dataset_extent};
pub use selection::{check_indices, format_ranges, parse_ranges, select_frames};
pub use snapshots::Snapshots;
#[cfg(feature = "bags")]
pub use stream::{check_posed, stream_bag};

use crate::error::{Error, Result};
use crate::frames::{Frame, RangeScan};
use crate::inference::{Budget, Engine, EngineConfig, MrfEngine, StepReport, new_engine};
use crate::map::Map;

/// A reading an engine integrates: a depth image or a range scan.
pub trait Reading {
    /// Adds this reading's evidence to `engine`.
    fn integrate_into(&self, engine: &mut dyn Engine) -> Result<()>;
    /// The reading's recording time (seconds), if it has one.
    fn timestamp(&self) -> Option<f64>;
}

impl Reading for Frame {
    fn integrate_into(&self, engine: &mut dyn Engine) -> Result<()> {
        engine.integrate(self)
    }

    fn timestamp(&self) -> Option<f64> {
        Some(self.timestamp)
    }
}

impl Reading for RangeScan {
    fn integrate_into(&self, engine: &mut dyn Engine) -> Result<()> {
        engine.integrate_scan(self)
    }

    fn timestamp(&self) -> Option<f64> {
        None
    }
}

/// Readings as they come, each with its index in the source.
pub type Readings<'a, R> = dyn Iterator<Item = Result<(usize, R)>> + 'a;

/// How a build reports as it goes (a terminal bar, a log, nothing). Every method has a
/// default that does nothing, and `()` reports nothing.
pub trait Progress {
    /// A stage begins: `what` (the engine's name, "inference", ...) over `total` steps if known.
    fn stage(&mut self, what: &str, total: Option<usize>) {
        let _ = (what, total);
    }
    /// `done` steps of the stage are done, of `total` if known.
    fn advance(&mut self, done: usize, total: Option<usize>) {
        let _ = (done, total);
    }
    /// A short status for the stage (the online schedule's last keyframe and backlog).
    fn status(&mut self, text: &str) {
        let _ = text;
    }
    /// The stage is over.
    fn end(&mut self) {}
}

impl Progress for () {}

/// What a build did.
pub struct BuildReport {
    /// The map.
    pub map: Map,
    /// Readings fed to the engine.
    pub frames: usize,
    /// Time spent in the engine: integration and inference (not reading or decoding).
    pub integrate_time: Duration,
}

/// What a build did, its engine kept: its map is made by [`Built::into_report`], or written
/// without being held in memory by [`Engine::save_map`] (what `mrfmap build` does).
pub struct Built {
    /// The engine, every reading in and its inference run.
    pub engine: Box<dyn Engine>,
    /// Readings fed to the engine.
    pub frames: usize,
    /// Time spent in the engine: integration and inference (not reading or decoding).
    pub integrate_time: Duration,
}

impl Built {
    /// The build's report with the engine's map ([`Engine::into_map`]).
    pub fn into_report(self) -> BuildReport {
        BuildReport { map: self.engine.into_map(), frames: self.frames, integrate_time: self.integrate_time }
    }
}

/// An error while integrating reading `index`, saying so (errors naming a file already say
/// where they come from).
fn at_reading(index: usize, e: Error) -> Error {
    match e {
        Error::Invalid(m) => Error::Invalid(format!("integrating reading {index}: {m}")),
        other => other,
    }
}

/// Feeds `readings` (`count` of them, if known) to `engine`, writing `snapshots` as it goes;
/// returns how many there were and the time spent in the engine.
pub fn integrate<R: Reading>(
    engine: &mut dyn Engine,
    readings: &mut Readings<'_, R>,
    count: Option<usize>,
    progress: &mut dyn Progress,
    mut snapshots: Option<&mut Snapshots>,
) -> Result<(usize, Duration)> {
    progress.stage(engine.name(), count);
    let (mut time, mut frames) = (Duration::ZERO, 0);
    for reading in readings {
        let (i, reading) = reading?;
        let t = Instant::now();
        reading.integrate_into(engine).map_err(|e| at_reading(i, e))?;
        time += t.elapsed();
        frames += 1;
        if let Some(s) = snapshots.as_deref_mut() {
            s.after(reading.timestamp(), engine)?;
        }
        progress.advance(frames, count);
    }
    progress.end();
    Ok((frames, time))
}

/// The map of `readings` (`count` of them, if known) built by the engine `config` asks for:
/// every reading integrated ([`integrate`]), then the engine's deferred inference (the MRF's
/// sweeps), then the map. `snapshots`, if any, are finished before the inference.
pub fn build<R: Reading>(
    config: &EngineConfig,
    readings: &mut Readings<'_, R>,
    count: Option<usize>,
    progress: &mut dyn Progress,
    snapshots: Option<Snapshots>,
) -> Result<BuildReport> {
    Ok(build_engine(config, readings, count, progress, snapshots)?.into_report())
}

/// [`build`], the engine kept instead of its map made.
pub fn build_engine<R: Reading>(
    config: &EngineConfig,
    readings: &mut Readings<'_, R>,
    count: Option<usize>,
    progress: &mut dyn Progress,
    mut snapshots: Option<Snapshots>,
) -> Result<Built> {
    let mut engine = new_engine(config)?;
    let (frames, mut integrate_time) = integrate(engine.as_mut(), readings, count, progress, snapshots.as_mut())?;
    if let Some(s) = snapshots {
        let written = s.finish(engine.as_ref())?;
        tracing::info!("{written} snapshots written");
    }
    let t = Instant::now();
    progress.stage("inference", Some(0));
    engine.finish_with_progress(&mut |done, total| progress.advance(done, Some(total)))?;
    progress.end();
    integrate_time += t.elapsed();
    Ok(Built { engine, frames, integrate_time })
}

/// What [`build_online`] did: the build, and each keyframe's step (time, tiles, backlog).
pub struct OnlineReport {
    /// The engine as it stood after the last frame (or after `finish`).
    pub build: Built,
    /// One report per keyframe, in order.
    pub keyframes: Vec<StepReport>,
}

/// Feeds frames as they come (`count` of them, if known) to an MRF engine in order on its
/// online schedule ([`MrfEngine::add_keyframe_within`] with `budget`), as a robot would: the
/// map is what the robot had after the last frame, unless `finish` runs the batch schedule
/// afterwards.
pub fn build_online(
    config: &EngineConfig,
    readings: &mut Readings<'_, Frame>,
    count: Option<usize>,
    budget: Budget,
    finish: bool,
    progress: &mut dyn Progress,
    mut snapshots: Option<Snapshots>,
) -> Result<OnlineReport> {
    config.limits.validate()?;
    let mut engine = MrfEngine::new(config.resolution, config.limits, config.mrf)?;
    progress.stage("mrf online", count);
    let mut steps = Vec::new();
    let (mut integrate_time, mut frames) = (Duration::ZERO, 0);
    for reading in readings {
        let (i, frame) = reading?;
        frames += 1;
        let frame_time = frame.timestamp;
        if engine.is_new_keyframe(&frame.pose) {
            let (_, r) = engine.add_keyframe_within(frame, budget).map_err(|e| at_reading(i, e))?;
            integrate_time += r.elapsed;
            steps.push(r);
            progress.status(&format!(
                "kf {} {:.0} ms, backlog {}",
                steps.len(),
                r.elapsed.as_secs_f64() * 1e3,
                r.backlog
            ));
            tracing::debug!("frame {i}: keyframe {}: {r:?}", steps.len());
        }
        if let Some(s) = &mut snapshots {
            s.after(Some(frame_time), &engine)?;
        }
        progress.advance(frames, count);
    }
    progress.end();
    if let Some(s) = snapshots {
        let written = s.finish(&engine)?;
        tracing::info!("{written} snapshots written");
    }
    let (last_backlog, settled) = steps.last().map_or((0, true), |r| (r.backlog, r.settled));
    if finish {
        let t = Instant::now();
        engine.finish()?;
        integrate_time += t.elapsed();
    } else if !settled {
        tracing::info!("MRF online: {last_backlog} tiles still in the backlog (finishing would infer them first)");
    }
    Ok(OnlineReport { build: Built { engine: Box::new(engine), frames, integrate_time }, keyframes: steps })
}
