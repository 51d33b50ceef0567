//! Inference engines: turn frames into voxel occupancy beliefs.
//!
//! Every engine implements [`Engine`]: frames go in through [`Engine::integrate`], a
//! finished [`Map`] comes out of [`Engine::map`], or goes straight to a file through
//! [`Engine::save_map`] (log-odds converts its grid a brick at a time, never holding the
//! map). Engines read rays through [`crate::rays`] and keep their state in a
//! [`crate::map::Grid`]. Available:
//!
//! - [`LogOddsEngine`]: OctoMap's occupancy grid update (docs/ALGORITHMS.md 5.1), the baseline
//!   and the fast everyday mode; also the CRM paper's ramp inverse sensor model
//!   ([`SensorModel`]).
//! - [`MrfEngine`]: MRFMap's ray Markov random field with loopy belief propagation over
//!   keyframes (docs/ALGORITHMS.md 5.3); keyframes can be added, removed and re-posed.
//! - [`CrmEngine`]: confidence-rich mapping, a pdf over occupancy per voxel (mean and
//!   variance) updated through the sensor cause model (docs/ALGORITHMS.md 5.2).
//!
//! Log-odds and CRM also take range scans ([`Engine::integrate_scan`]). [`Tiling`] builds a
//! map in tiles (`tiles.rs`), each from the frames that reach it, with any engine.
//! [`BuildOptions`] is what a user sets for a build, turned into an [`EngineConfig`] in one
//! place for the command line and Python alike.

mod crm;
mod estimate;
mod logodds;
mod merge;
mod mrf;
mod options;
mod tiles;

/// Which engine: defined with the maps, which record it.
pub use crate::map::EngineKind;
pub use crm::{CrmEngine, CrmParams, crm_ray_factors};
pub use estimate::{
    ANNOUNCED_MEMORY, BASE_MEMORY, Extent, MapOutput, check_build, estimate_memory, frames_extent,
    frames_extent_loaded, poses_bound, scan_extent,
};
pub use logodds::{LogOddsEngine, LogOddsParams, Marking, SensorModel};
pub use merge::merge;
pub use mrf::{
    Allocation, Budget, DEFAULT_MAX_SWEEPS, DEFAULT_MIN_EVIDENCE, DEFAULT_SWEEPS, DEFAULT_TOLERANCE, KeyframeId,
    KeyframeSelection, MAX_BATCH, MAX_LOG_ODDS, MU_EPS, MrfEngine, MrfParams, RunReport, StepReport, TILE,
    ray_log_messages, ray_messages,
};
pub use options::BuildOptions;
pub use tiles::{TileBuild, Tiling, default_margin};

use std::collections::BTreeMap;
use std::path::Path;

use crate::error::{Error, Result};
use crate::frames::{Camera, Frame, RangeScan};
use crate::map::{Map, MapVoxel, VoxelKey};
use crate::rays::RayLimits;

/// Log-odds of a probability.
pub(crate) fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// Probability of a log-odds value.
pub(crate) fn sigmoid(l: f64) -> f64 {
    1.0 / (1.0 + (-l).exp())
}

/// An occupancy inference engine.
pub trait Engine: Send + Sync {
    /// Which engine this is (what its maps record).
    fn kind(&self) -> EngineKind;
    /// The engine's name (`logodds`, ...), as on the command line and in map files.
    fn name(&self) -> &'static str {
        self.kind().name()
    }
    /// Voxel edge in metres.
    fn resolution(&self) -> f64;
    /// Makes ready for depth frames from `camera` before the first comes: the log-odds
    /// engine sizes its per-pixel buffers for the camera's images, which the first frame's
    /// integration would otherwise make (a fifth of it at 640 x 480), as a mapper that knows
    /// its camera does at start-up. Frames from another camera still work. The others have
    /// nothing to ready.
    fn prepare(&mut self, camera: &Camera) {
        let _ = camera;
    }
    /// Adds one frame's evidence.
    fn integrate(&mut self, frame: &Frame) -> Result<()>;
    /// Adds one range scan's evidence (planar lasers, lidars). Engines that work on depth
    /// images only (the MRF's keyframes) refuse.
    fn integrate_scan(&mut self, scan: &RangeScan) -> Result<()> {
        let _ = scan;
        Err(Error::Invalid(format!(
            "the {} engine takes depth images only; range scans work with logodds and crm",
            self.name()
        )))
    }
    /// Runs any inference deferred until all frames are in (the MRF's iterations); online
    /// engines have nothing to do.
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
    /// [`Engine::finish`], calling `progress(done, total)` as its work advances (the MRF:
    /// after each sweep of its change-driven schedule, or each keyframe of a fixed sweep).
    fn finish_with_progress(&mut self, progress: &mut dyn FnMut(usize, usize)) -> Result<()> {
        let _ = progress;
        self.finish()
    }
    /// The current map: occupancy (and variance where the engine has one) per voxel.
    fn map(&self) -> Map;
    /// [`Engine::map`], giving up the engine: its memory goes as the map's comes (log-odds
    /// frees each brick once it is copied, so the peak is about the map, not the map and the
    /// engine).
    fn into_map(self: Box<Self>) -> Map {
        self.map()
    }
    /// Saves [`Engine::map`] to `path` (temp file + rename) with `params` added to the
    /// engine's own. Log-odds writes its grid a brick at a time ([`Map::save_converted`]),
    /// never holding the finished map beside its own state: that copy, 8 bytes a voxel against
    /// the engine's 4, was over half of a large build's peak.
    fn save_map(&self, path: &Path, params: &BTreeMap<String, String>) -> Result<SavedMap> {
        let mut map = self.map();
        map.params.extend(params.clone());
        map.save(path)?;
        Ok(SavedMap { voxels: map.voxels.len(), occupied: map.occupied_count() })
    }
    /// One voxel of [`Engine::map`], read from the live state without building the map
    /// (what queries on a running engine use); `None` where the map would have no voxel.
    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel>;
    /// True when [`MapVoxel::variance`] is the engine's own (CRM); otherwise queries use the
    /// Bernoulli variance of the occupancy.
    fn has_variance(&self) -> bool {
        false
    }
}

/// What [`Engine::save_map`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SavedMap {
    /// Voxels in the map.
    pub voxels: usize,
    /// Of those, voxels above [`crate::map::OCCUPIED_THRESHOLD`].
    pub occupied: usize,
}

/// What every engine is built from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EngineConfig {
    /// Which engine.
    pub kind: EngineKind,
    /// Voxel edge in metres.
    pub resolution: f64,
    /// Max range and bounding box applied to every ray.
    pub limits: RayLimits,
    /// Parameters of the log-odds engine (ignored by the others).
    pub logodds: LogOddsParams,
    /// Parameters of the MRF engine (ignored by the others).
    pub mrf: MrfParams,
    /// Parameters of the CRM engine (ignored by the others).
    pub crm: CrmParams,
    /// The camera the depth frames will come from, when it is known before the first (a
    /// dataset's `camera.toml`): the engine is made ready for its images
    /// ([`Engine::prepare`]). `None` (the default): ready when the first frame comes.
    pub camera: Option<Camera>,
}

impl EngineConfig {
    /// `kind` at `resolution` with no ray limits and default engine parameters.
    pub fn new(kind: EngineKind, resolution: f64) -> Self {
        EngineConfig {
            kind,
            resolution,
            limits: RayLimits::default(),
            logodds: LogOddsParams::default(),
            mrf: MrfParams::default(),
            crm: CrmParams::default(),
            camera: None,
        }
    }
}

/// Builds the engine `config` asks for.
///
/// ```
/// use mrfmap::inference::{EngineConfig, EngineKind, new_engine};
/// let config = EngineConfig::new(EngineKind::LogOdds, 0.05);
/// assert_eq!(new_engine(&config).unwrap().name(), "logodds");
/// assert!(new_engine(&EngineConfig { resolution: -1.0, ..config }).is_err());
/// ```
pub fn new_engine(config: &EngineConfig) -> Result<Box<dyn Engine>> {
    config.limits.validate()?;
    let mut engine: Box<dyn Engine> = match config.kind {
        EngineKind::LogOdds => Box::new(LogOddsEngine::new(config.resolution, config.limits, config.logodds)?),
        EngineKind::Mrf => Box::new(MrfEngine::new(config.resolution, config.limits, config.mrf)?),
        EngineKind::Crm => Box::new(CrmEngine::new(config.resolution, config.limits, config.crm)?),
    };
    if let Some(camera) = &config.camera {
        engine.prepare(camera);
    }
    Ok(engine)
}
