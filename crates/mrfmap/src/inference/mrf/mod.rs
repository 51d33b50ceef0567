//! The MRFMap engine: every depth pixel of every keyframe is a ray factor in a Markov random
//! field over binary voxel occupancies; loopy sum-product belief propagation over all
//! keyframes gives each voxel's marginal (MRFMap secs. III-IV, docs/ALGORITHMS.md 5.3).
//!
//! The files: `params.rs` (the parameters and their defaults), `tiles.rs` (keyframes, their
//! tiles and the bricks they allocate), `trace.rs` (tracing a tile's rays into new messages),
//! `messages.rs` (one ray factor's messages), `schedule.rs` (the change log and the batch
//! schedules) and `online.rs` (the budgeted online schedule); this file holds the engine's
//! state, its public interface and the [`Engine`] implementation.
//!
//! How the pieces fit:
//! - [`ray_messages`] computes one ray factor's outgoing messages in linear time.
//! - Every ray is a factor, as in the model. Each voxel keeps `S = logit(prior) + sum of the
//!   messages (log-odds) of every ray that reaches it`; the marginal is `sigmoid(S)`. A ray's
//!   message counts with its length in the voxel over the voxel edge: a full crossing counts
//!   once, a corner clip a little. (The paper's text averages a keyframe's rays into one
//!   message per voxel; a voxel crossed by 100 rays then gets the evidence of one, walls stay
//!   at 0.2-0.5 and the marginals are under-confident by construction: docs/history/RESULTS.md,
//!   "Every ray a factor".)
//! - **Tiles** are the unit of bookkeeping and of re-tracing: a keyframe's image is cut into
//!   [`TILE`] x [`TILE`] pixel tiles, and each tile keeps, per voxel its rays reach, the sum
//!   of their lengths, its message (the sum of its rays' messages) and the `S` its rays saw
//!   when it last traced. Re-tracing a tile replaces exactly its own messages in `S`, so any
//!   subset of tiles can be re-traced at any time and the sums stay exact. The message into
//!   one ray is the cavity `sigmoid(S - own)`, the ray's own last message taken as its length
//!   times the tile's message per metre (per-ray messages are not stored; a tile's rays
//!   through one voxel are nearly parallel and alike).
//! - Schedules: [`MrfEngine::run`] runs a fixed number of sweeps, each re-tracing every tile
//!   of every keyframe in turn. [`MrfEngine::run_until`] is change-driven: a sweep re-traces
//!   only the tiles for which some voxel's marginal moved by more than a tolerance since
//!   they saw it, whose own last update damping held back by more than it, or which new
//!   bricks may lie on, until no tile is left. The online schedule (`online.rs`:
//!   [`MrfEngine::add_keyframe_within`], [`MrfEngine::refine`]) is anytime work under a
//!   [`Budget`]: a new keyframe's tiles first, then the tiles whose inputs moved most, the
//!   rest kept in a backlog for later. All trace one keyframe's tiles against the same `S`,
//!   then apply them in tile order, damped:
//!   [`MrfParams::damping`] of a tile's old message (log-odds) stays, and a message whose
//!   change keeps reversing direction is damped more (loopy belief propagation can cycle
//!   where voxels compete for one surface). Which tiles a change may affect is found by
//!   projecting the bricks it touched into each keyframe's image. The default of a batch
//!   build ([`MrfParams::default`]) is the paper's: [`DEFAULT_SWEEPS`] full sweeps (chosen by
//!   measurement: as accurate on held-out views as the change-driven schedule run to its cap,
//!   in a third of the time; RESULTS.md).
//! - [`MrfParams::ray_spacing`] optionally traces one ray per block of pixels where pixels
//!   are much smaller than voxels.
//! - Keyframes can be added, removed and re-posed. Removal subtracts the keyframe's messages
//!   exactly (it does not reset the others' and `S` the way the reference code does, which
//!   would double-count). A new brick marks stale the tiles of other keyframes whose rays may
//!   cross it (the brick projected into their images, nearer than their rays reach), and
//!   lowers their near bounds (`z_near`, where a trace starts its rays' walks) to it; a new
//!   or re-posed keyframe's tiles start with the bound of every brick allocated then; a freed
//!   brick leaves every tile, and the tiles that reached it are marked stale.
//!
//! **A tile's life, and the change clock.** The engine counts keyframe updates in an
//! `epoch`. A tile is
//! - *stale* when it must be traced whatever moved: never traced (`traced_at == 0`: a new or
//!   re-posed keyframe's), or a brick its rays may cross came (a new keyframe allocated it) or
//!   went (its entries there were dropped);
//! - *suspect* while a check looks at it: a brick logged since its keyframe's last check
//!   (`checked_at`) projects onto it;
//! - *dirty* when a check finds a voxel of it whose marginal moved by more than the tolerance
//!   since the `seen` value it traced with (`largest_move`), or it is stale, or its last
//!   update was *held back* by damping by more than the tolerance;
//! - *in the backlog* (online schedule) while its `priority`, the largest such move the
//!   checks found, is above the tolerance; a trace resets it.
//!
//! Every change to a sum goes through `apply_run`, which compares the voxel with the `logged`
//! copy of its sum: past a quarter of the tolerance, the brick is stamped with the epoch
//! (`stamps`) and appended to the `log`. A check of keyframe `k` reads the log after
//! `checked_at`; log entries every keyframe has checked are dropped (`trim_log`). When the log
//! outgrows a few entries per brick it is cleared and `log_floor` raised: keyframes checked
//! before the floor treat every tile as suspect and read the brick stamps instead. A voxel no
//! log entry names has moved by at most two log thresholds since any tile that reaches it was
//! last checked, so a move that no check sees stays below 1.5 tolerances.
//!
//! Allocation is at brick granularity. [`Allocation::Band`] (the reference's choice, default)
//! allocates the bricks within one voxel of each back-projected depth point, so free space
//! far from surfaces stays unknown and rays skip it; [`Allocation::Full`] also allocates every
//! brick a ray crosses from the camera on. Rays are truncated 3 std beyond the measurement
//! (bias removed); the chance that the surface lies beyond that point is the ray's "beyond"
//! term: the forward model averaged over one more voxel past the truncation, or, where the
//! map's bounds or the max range cut the ray short, over the stretch cut off (the surface is
//! then outside the map; [`crate::rays::Segment::beyond`]). An allocated
//! voxel whose belief the rays moved by less than [`MrfParams::min_evidence`] from the prior
//! (behind surfaces, outside every view) is unknown: [`Engine::map`] leaves it out, so that a
//! planner does not read a wall's unseen inside as "probably free".
//!
//! Each voxel's likelihood is the forward model averaged over the voxel's extent along the
//! ray ([`NoiseModel::likelihood_over`]), so voxels stay informative when the sensor's noise
//! is much smaller than a voxel. Tiles are traced on all cores and applied in a fixed order,
//! so results do not depend on the number of threads.

mod messages;
mod online;
mod params;
mod schedule;
mod tiles;
mod trace;

use crate::map::EngineKind;
use std::sync::Arc;

use rustc_hash::{FxHashMap, FxHashSet};

pub use messages::{MAX_LOG_ODDS, MU_EPS, ray_log_messages, ray_messages};
pub use online::{Budget, MAX_BATCH, StepReport};
pub use params::{
    Allocation, DEFAULT_MAX_SWEEPS, DEFAULT_MIN_EVIDENCE, DEFAULT_SWEEPS, DEFAULT_TOLERANCE, KeyframeSelection,
    MrfParams,
};
pub use schedule::RunReport;
pub use tiles::TILE;
use tiles::{Entry, Keyframe};

use super::{Engine, logit, sigmoid};
use crate::error::{Error, Result};
use crate::frames::{Frame, NoiseModel, Pose, default_noise_model, moved_beyond};
use crate::map::{BrickKey, Grid, Map, MapVoxel, VoxelKey};
use crate::rays::RayLimits;

/// Identifies a keyframe of an [`MrfEngine`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyframeId(pub u64);

/// A voxel whose `S` is within this many log-odds of the prior's was reached by no ray (or
/// only by occluded ones, whose messages are 1/2): unknown whatever
/// [`MrfParams::min_evidence`] says.
const UNOBSERVED: f64 = 0.01;

/// Merging MRF maps ([`super::merge`]): the marginals as independent evidence about the
/// same `prior`.
pub(super) fn merge_rule(prior: f64) -> impl Fn(MapVoxel, MapVoxel) -> MapVoxel {
    let prior = logit(prior);
    move |a, b| MapVoxel {
        occupancy: sigmoid(logit(a.occupancy as f64) + logit(b.occupancy as f64) - prior) as f32,
        variance: 0.0,
    }
}

/// MRFMap inference over keyframes.
///
/// ```
/// use mrfmap::inference::{MrfEngine, MrfParams};
/// let engine = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
/// assert_eq!(engine.keyframe_count(), 0);
/// ```
pub struct MrfEngine {
    params: MrfParams,
    limits: RayLimits,
    /// Per voxel `S = logit(prior) + sum of every tile's message`; allocated = the union of
    /// keyframes' bricks.
    sums: Grid<f32>,
    brick_refs: FxHashMap<BrickKey, u32>,
    keyframes: Vec<Keyframe>,
    next_id: u64,
    default_noise: Arc<NoiseModel>,
    /// Bricks allocated or freed since the last `run` (keyframes added, moved, removed).
    changed: FxHashSet<BrickKey>,
    /// Keyframes updated per iteration by the last `run`.
    last_run: usize,
    /// Counts keyframe updates; stamps what changed when.
    epoch: u64,
    /// Per voxel, `S` when its brick was last logged (allocated like `sums`).
    logged: Grid<f32>,
    /// A marginal's change since `logged` that gets its brick logged: a quarter of the
    /// tolerance of `run_until` (the smallest it was called with).
    log_threshold: f64,
    /// Per brick, the epoch when it was last logged.
    stamps: FxHashMap<BrickKey, u64>,
    /// The same changes in epoch order, for finding the tiles they may affect; entries up to
    /// `log_floor` were dropped (a keyframe checked before it checks all its tiles).
    log: Vec<(u64, BrickKey)>,
    log_floor: u64,
    /// Measured wall time per traced tile (ms), which sizes the online schedule's batches.
    tile_ms: Option<f64>,
}

impl MrfEngine {
    /// The map voxel of a marginal's log-odds sum `S`: none where the evidence is too weak
    /// (`S` within [`MrfParams::min_evidence`], and at least [`UNOBSERVED`], of the prior),
    /// so unreached and occluded space stays unknown.
    fn map_voxel(&self, s: f32) -> Option<MapVoxel> {
        ((s as f64 - logit(self.params.prior)).abs() > self.params.min_evidence.max(UNOBSERVED))
            .then(|| MapVoxel { occupancy: sigmoid(s as f64) as f32, variance: 0.0 })
    }

    /// An empty engine.
    pub fn new(resolution: f64, limits: RayLimits, params: MrfParams) -> Result<Self> {
        if !(params.prior > 0.0 && params.prior < 1.0) {
            return Err(Error::Invalid(format!("MRF prior must be in (0, 1), got {}", params.prior)));
        }
        if params.tolerance.is_some_and(|t| !(t > 0.0 && t < 1.0)) {
            return Err(Error::Invalid(format!("MRF tolerance must be in (0, 1), got {:?}", params.tolerance)));
        }
        if !(params.ray_spacing >= 0.0 && params.ray_spacing.is_finite()) {
            return Err(Error::Invalid(format!("MRF ray spacing must be 0 or more, got {}", params.ray_spacing)));
        }
        if !(params.min_evidence >= 0.0 && params.min_evidence.is_finite()) {
            return Err(Error::Invalid(format!("MRF minimum evidence must be 0 or more, got {}", params.min_evidence)));
        }
        if params.work.is_some_and(|w| !(w > 0.0 && w.is_finite())) {
            return Err(Error::Invalid(format!("MRF work must be a positive number of sweeps, got {:?}", params.work)));
        }
        if !(0.0..1.0).contains(&params.damping) {
            return Err(Error::Invalid(format!("MRF damping must be in [0, 1), got {}", params.damping)));
        }
        Ok(MrfEngine {
            params,
            limits,
            sums: Grid::new(resolution)?,
            logged: Grid::new(resolution)?,
            log_threshold: DEFAULT_TOLERANCE / 4.0,
            brick_refs: FxHashMap::default(),
            keyframes: Vec::new(),
            next_id: 0,
            default_noise: Arc::new(default_noise_model()),
            changed: FxHashSet::default(),
            last_run: 0,
            epoch: 0,
            stamps: FxHashMap::default(),
            log: Vec::new(),
            log_floor: 0,
            tile_ms: None,
        })
    }

    /// Number of keyframes.
    pub fn keyframe_count(&self) -> usize {
        self.keyframes.len()
    }

    /// Ids of the keyframes, in the order they were added.
    pub fn keyframe_ids(&self) -> Vec<KeyframeId> {
        self.keyframes.iter().map(|k| k.id).collect()
    }

    /// Adds a keyframe and allocates its bricks; call [`MrfEngine::run`] or
    /// [`MrfEngine::run_until`] to infer. Fails on an image that does not match its camera or
    /// a non-finite pose.
    pub fn add_keyframe(&mut self, frame: Frame) -> Result<KeyframeId> {
        check_frame(&frame)?;
        let noise = frame.noise.clone().unwrap_or_else(|| self.default_noise.clone());
        noise.check_camera(&frame.camera).map_err(Error::Invalid)?;
        let id = KeyframeId(self.next_id);
        self.next_id += 1;
        let mut kf = Keyframe { id, frame, noise, bricks: Vec::new(), tiles: Vec::new(), tiles_x: 0, checked_at: 0 };
        kf.reset_tiles();
        kf.bricks = self.allocation_of(&kf);
        let new = self.reference_bricks(&kf.bricks);
        self.mark_tiles_reaching(&new);
        kf.bound_tiles(self.brick_refs.keys(), self.brick_edge());
        self.changed.extend(kf.bricks.iter().copied());
        self.keyframes.push(kf);
        Ok(id)
    }

    /// Removes a keyframe: its messages leave the sums and the bricks only it allocated are
    /// freed. Call [`MrfEngine::run`] or [`MrfEngine::run_until`] to let the other keyframes
    /// re-converge.
    pub fn remove_keyframe(&mut self, id: KeyframeId) -> Result<()> {
        let i = self.index_of(id)?;
        self.withdraw_messages(i);
        let kf = self.keyframes.remove(i);
        self.changed.extend(kf.bricks.iter().copied());
        self.release_bricks(&kf.bricks);
        Ok(())
    }

    /// Moves a keyframe (e.g. after a loop closure): its messages are withdrawn and its bricks
    /// re-allocated for the new pose. Call [`MrfEngine::run`] or [`MrfEngine::run_until`] to
    /// re-infer.
    pub fn set_pose(&mut self, id: KeyframeId, pose: Pose) -> Result<()> {
        let i = self.index_of(id)?;
        let mut frame = self.keyframes[i].frame.clone();
        frame.pose = pose;
        check_frame(&frame)?;
        self.withdraw_messages(i);
        let old = std::mem::take(&mut self.keyframes[i].bricks);
        self.keyframes[i].frame = frame;
        let bricks = self.allocation_of(&self.keyframes[i]);
        let new = self.reference_bricks(&bricks);
        self.mark_tiles_reaching(&new);
        let edge = self.brick_edge();
        self.keyframes[i].bound_tiles(self.brick_refs.keys(), edge);
        self.changed.extend(old.iter().chain(&bricks).copied());
        self.keyframes[i].bricks = bricks;
        self.release_bricks(&old);
        Ok(())
    }

    /// Marginal occupancy of a voxel, `None` if unallocated (a voxel no ray has reached holds
    /// the prior; [`Engine::map`] leaves such voxels out).
    pub fn marginal(&self, key: VoxelKey) -> Option<f64> {
        self.sums.get(key).map(|s| sigmoid(*s as f64))
    }

    /// Marginal occupancy at a world point, `None` where nothing is allocated.
    pub fn marginal_at(&self, p: [f64; 3]) -> Option<f64> {
        self.marginal(VoxelKey::from_point(p, self.resolution()))
    }

    /// All allocated voxels with their marginals.
    pub fn marginals(&self) -> impl Iterator<Item = (VoxelKey, f64)> + '_ {
        self.sums.iter().map(|(k, s)| (k, sigmoid(*s as f64)))
    }

    /// Would a frame at `pose` be a new keyframe under the engine's [`KeyframeSelection`]?
    pub fn is_new_keyframe(&self, pose: &Pose) -> bool {
        match self.params.keyframes {
            KeyframeSelection::All => true,
            KeyframeSelection::Auto { translation, rotation } => {
                self.keyframes.iter().all(|k| moved_beyond(&k.frame.pose, pose, translation, rotation))
            }
        }
    }

    /// Bytes held by the keyframes' tiles (their per-voxel bookkeeping).
    pub fn tile_bytes(&self) -> usize {
        let (per, run) = (std::mem::size_of::<Entry>(), std::mem::size_of::<(BrickKey, u32)>());
        self.keyframes.iter().flat_map(|k| &k.tiles).map(|t| t.entries.capacity() * per + t.runs.capacity() * run).sum()
    }

    fn index_of(&self, id: KeyframeId) -> Result<usize> {
        self.keyframes.iter().position(|k| k.id == id).ok_or_else(|| Error::Invalid(format!("no keyframe {id:?}")))
    }
}

fn check_frame(frame: &Frame) -> Result<()> {
    let (w, h) = (frame.depth.width(), frame.depth.height());
    if (w, h) != (frame.camera.width, frame.camera.height) {
        return Err(Error::Invalid(format!(
            "keyframe {}: depth image is {w}x{h} but the camera is {}x{}",
            frame.index, frame.camera.width, frame.camera.height
        )));
    }
    let t = frame.pose.translation.vector;
    let q = frame.pose.rotation.quaternion();
    if [t.x, t.y, t.z, q.i, q.j, q.k, q.w].iter().any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!("keyframe {}: pose has a NaN or infinite value", frame.index)));
    }
    Ok(())
}

impl Engine for MrfEngine {
    fn kind(&self) -> EngineKind {
        EngineKind::Mrf
    }

    fn resolution(&self) -> f64 {
        self.sums.resolution()
    }

    /// Adds the frame as a keyframe if the [`KeyframeSelection`] takes it (inference runs in
    /// [`Engine::finish`]).
    fn integrate(&mut self, frame: &Frame) -> Result<()> {
        if !self.is_new_keyframe(&frame.pose) {
            tracing::debug!("frame {} is close to an existing keyframe; skipped", frame.index);
            return Ok(());
        }
        self.add_keyframe(frame.clone()).map(|_| ())
    }

    fn finish(&mut self) -> Result<()> {
        self.finish_with_progress(&mut |_, _| {})
    }

    fn finish_with_progress(&mut self, progress: &mut dyn FnMut(usize, usize)) -> Result<()> {
        if let Some(w) = self.params.work {
            return self.finish_by_work(w, progress);
        }
        let r = match self.params.tolerance {
            Some(t) => self.run_until_with_progress(t, self.params.iterations, progress),
            None => self.run_with_progress(self.params.iterations, progress),
        };
        tracing::info!(
            "MRF: {} sweeps over {} keyframes: {} keyframe updates, {} tiles, {} rays traced ({} MiB of tile messages){}",
            r.sweeps,
            self.keyframes.len(),
            r.keyframe_updates,
            r.tiles,
            r.rays,
            self.tile_bytes() >> 20,
            match self.params.tolerance {
                Some(_) if r.converged => ", converged".to_string(),
                // Whether it matters: held-out accuracy does not need convergence (the default
                // is a fixed 3 sweeps for that reason), so say so where the cap is reached.
                Some(_) => format!(
                    ", not converged within the {} sweeps --iterations allows (held-out accuracy does not \
                     need convergence, RESULTS.md \"The online MRF\"; raise --iterations to go on)",
                    self.params.iterations
                ),
                None => String::new(),
            }
        );
        Ok(())
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.map_voxel(*self.sums.get(key)?)
    }

    fn map(&self) -> Map {
        let mut map = Map::new(self.kind(), self.resolution()).expect("valid resolution");
        for (key, s) in self.sums.iter() {
            if let Some(v) = self.map_voxel(*s) {
                map.voxels.insert(key, v);
            }
        }
        let p = self.params;
        map.params.insert("prior".into(), p.prior.to_string());
        map.params.insert("iterations".into(), p.iterations.to_string());
        map.params.insert("allocation".into(), format!("{:?}", p.allocation).to_lowercase());
        map.params.insert("damping".into(), p.damping.to_string());
        map.params.insert("ray_spacing".into(), p.ray_spacing.to_string());
        map.params.insert("min_evidence".into(), p.min_evidence.to_string());
        if let Some(t) = p.tolerance {
            map.params.insert("tolerance".into(), t.to_string());
        }
        map.params.insert("keyframes".into(), self.keyframes.len().to_string());
        if let KeyframeSelection::Auto { translation, rotation } = p.keyframes {
            map.params.insert("keyframe_selection".into(), format!("auto ({translation} m, {rotation} rad)"));
        }
        map
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::source::Scene;

    /// A floor and a box seen by `views` cameras on a circle.
    pub(super) fn test_scene(views: usize) -> Scene {
        let toml = format!(
            "[camera]\nfx = 60.0\nfy = 60.0\ncx = 39.5\ncy = 29.5\nwidth = 80\nheight = 60\ndepth_scale = 5000.0\n\
             [[box]]\nmin = [-2.0, -2.0, -0.1]\nmax = [2.0, 2.0, 0.0]\n[[box]]\nmin = [-0.3, -0.3, 0.0]\nmax = [0.3, 0.3, 0.6]\n\
             [orbit]\ncenter = [0.0, 0.0, 0.3]\nradius = 2.0\nheight = 1.3\nviews = {views}\n"
        );
        Scene::from_toml(&toml, "t.toml".as_ref()).unwrap()
    }

    /// Every tile's largest marginal move since it traced, `(keyframe, tile, move)`, checked
    /// against every brick (each counted as changed), not only those the change log names.
    pub(super) fn moves_against_every_brick(e: &mut MrfEngine) -> Vec<(usize, usize, f64)> {
        for v in e.stamps.values_mut() {
            *v = u64::MAX;
        }
        let e = &*e;
        let tiles = e
            .keyframes
            .iter()
            .enumerate()
            .flat_map(|(k, kf)| kf.tiles.iter().enumerate().map(move |(t, tile)| (k, t, tile)));
        tiles.map(|(k, t, tile)| (k, t, schedule::largest_move(&e.sums, &e.stamps, tile, None, 0.0, 1.0))).collect()
    }

    /// Noisy frames of every view of [`test_scene`]`(views)`.
    pub(super) fn test_frames(views: usize) -> Vec<Frame> {
        let scene = test_scene(views);
        scene.views.iter().enumerate().map(|(i, p)| scene.frame(i, p, Some(i as u64))).collect()
    }

    #[test]
    fn bad_parameters_are_refused() {
        for (params, word) in [
            (MrfParams { ray_spacing: -1.0, ..MrfParams::default() }, "ray spacing"),
            (MrfParams { ray_spacing: f64::NAN, ..MrfParams::default() }, "ray spacing"),
            (MrfParams { tolerance: Some(0.0), ..MrfParams::default() }, "tolerance"),
            (MrfParams { damping: 1.0, ..MrfParams::default() }, "damping"),
            (MrfParams { work: Some(0.0), ..MrfParams::default() }, "work"),
            (MrfParams { work: Some(f64::INFINITY), ..MrfParams::default() }, "work"),
        ] {
            let err = MrfEngine::new(0.05, Default::default(), params).err().expect("refused");
            assert!(err.to_string().contains(word), "{err}");
        }
    }
}
