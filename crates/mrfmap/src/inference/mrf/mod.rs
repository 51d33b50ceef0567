//! The MRFMap engine: every depth pixel of every keyframe is a ray factor in a Markov random
//! field over binary voxel occupancies; loopy sum-product belief propagation over all
//! keyframes gives each voxel's marginal (MRFMap secs. III-IV, docs/ALGORITHMS.md 5.3).
//!
//! How the pieces fit:
//! - [`ray_messages`] computes one ray factor's outgoing messages in linear time.
//! - Each keyframe sends every voxel its rays reach one message `W_k` (log-odds). Each voxel
//!   keeps `S = logit(prior) + sum_k W_k`; the marginal is `sigmoid(S)`. A keyframe stores
//!   one f32 per voxel from which `W_k` follows (see `Keyframe::messages`).
//! - How a keyframe's rays through one voxel make `W_k` is [`Aggregation`]:
//!   - [`Aggregation::Sum`] (default): every ray is a factor, as in the model. `W_k` is the
//!     sum of the rays' log-odds messages, each weighted by its length in the voxel over the
//!     voxel edge (a full crossing counts once, a corner clip a little). The message into
//!     one ray is the cavity `sigmoid(S - own)`, where the ray's own last message is taken
//!     as its length times the keyframe's message per metre, `W_k / L_k` with `L_k` the
//!     length of all its rays in the voxel (per-ray messages are not stored; rays of one
//!     keyframe through one voxel are nearly parallel and alike). That per-metre message is
//!     what the keyframe stores: `L_k` is geometry, summed again by every trace, so
//!     `W_k = L_k W_k / L_k` is recovered when the message is replaced; removing or re-posing
//!     a keyframe walks its rays once more for their lengths.
//!   - [`Aggregation::Average`]: the paper's text (sec. IV-A): the length-weighted average
//!     message, counted once per keyframe, with cavity `sigmoid(S - W_k)`. A voxel seen
//!     by 100 rays of a keyframe then gets the evidence of one, so surfaces stay near the
//!     prior (walls at 0.2-0.5) and the marginals are under-confident by construction; the
//!     reference viewer draws such maps at threshold 0.1.
//! - One iteration traces every keyframe in turn with the current cavities and replaces its
//!   messages in `S`, damped: `MrfParams::damping` of the old message (log-odds) stays.
//!   [`MrfEngine::run`] runs a fixed number of iterations; [`MrfEngine::run_until`] sweeps
//!   until no marginal moves by more than a tolerance, re-tracing only the keyframes whose
//!   bricks changed since their last trace.
//! - Keyframes can be added, removed and re-posed; removal subtracts the keyframe's messages
//!   (it does not reset the others' and `S` the way the reference code does, which would
//!   double-count), then [`MrfEngine::run`] iterates again from where the map stands.
//!
//! Allocation is at brick granularity. [`Allocation::Band`] (the reference's choice, default)
//! allocates the bricks within one voxel of each back-projected depth point, so free space
//! far from surfaces stays unknown and rays skip it; [`Allocation::Full`] also allocates every
//! brick a ray crosses from the camera on. Rays are truncated 3 std beyond the measurement
//! (bias removed); the chance that the surface lies beyond that point is the ray's "beyond"
//! term: the forward model averaged over one more voxel past the truncation. An allocated
//! voxel whose belief no ray moved from the prior (behind surfaces, outside every view) is
//! unknown: [`Engine::map`] leaves it out, so that a planner does not read a wall's unseen
//! inside as "probably free" (`UNOBSERVED`).
//!
//! Each voxel's likelihood is the forward model averaged over the voxel's extent along the
//! ray ([`NoiseModel::likelihood_over`]), so voxels stay informative when the sensor's noise
//! is much smaller than a voxel. Tracing runs on all cores over fixed blocks of image rows
//! whose partial sums are merged in a fixed order, so results do not depend on the number of
//! threads.

mod messages;

use std::ops::ControlFlow;
use std::sync::Arc;

use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

pub use messages::{MU_EPS, ray_messages};

use super::{Engine, logit, sigmoid};
use crate::error::{Error, Result};
use crate::frames::{Frame, NoiseModel, Pose, default_noise_model};
use crate::map::{BRICK_EDGE, BRICK_VOXELS, BrickKey, Grid, Map, MapVoxel, VoxelKey};
use crate::rays::{FrameRays, PixelRay, RayLimits, for_each_crossing};

/// Which bricks a keyframe allocates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Allocation {
    /// Bricks within one voxel of the back-projected depth points (the reference's choice).
    Band,
    /// Also every brick the rays cross from the camera on (free space becomes known).
    Full,
}

/// Which integrated frames become keyframes (MRFMap sec. V-A.2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KeyframeSelection {
    /// Every frame (the default for datasets).
    All,
    /// A frame whose translation or rotation angle from *every* existing keyframe exceeds
    /// these thresholds (metres, radians; defaults 0.2 and 0.2).
    Auto {
        /// Translation threshold (m).
        translation: f64,
        /// Rotation threshold (rad).
        rotation: f64,
    },
}

impl KeyframeSelection {
    /// `Auto` with the default thresholds.
    pub const AUTO: KeyframeSelection = KeyframeSelection::Auto { translation: 0.2, rotation: 0.2 };
}

/// Parameters of the MRF engine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MrfParams {
    /// Prior occupancy of every voxel (the paper: 0.1).
    pub prior: f64,
    /// Belief-propagation iterations run by [`Engine::finish`] (the paper: 3).
    pub iterations: usize,
    /// Brick allocation mode.
    pub allocation: Allocation,
    /// Which frames [`Engine::integrate`] turns into keyframes.
    pub keyframes: KeyframeSelection,
    /// How a keyframe's rays through one voxel combine into its message.
    pub messages: Aggregation,
    /// Share of a keyframe's old message (log-odds) kept when it is replaced, in `[0, 1)`.
    /// Undamped, the sequential schedule can settle into a two-sweep cycle (a voxel of the
    /// test scenes alternates between 0.95 and 0.89 forever); 0.3 removes it there and scores
    /// better on held-out views (RESULTS.md).
    pub damping: f64,
    /// With `Some(t)`, [`Engine::finish`] runs [`MrfEngine::run_until`] with tolerance `t`
    /// and at most `iterations` sweeps instead of `iterations` full sweeps.
    pub tolerance: Option<f64>,
}

/// How the messages of one keyframe's rays into a voxel combine (MRFMap sec. IV-A; see the
/// module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Aggregation {
    /// Every ray is a factor: the sum of the rays' log-odds messages, each weighted by its
    /// length in the voxel over the voxel edge (the default).
    Sum,
    /// The length-weighted average message, counted once per keyframe (the paper's text and
    /// the reference code; under-confident).
    Average,
}

impl std::str::FromStr for Aggregation {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "sum" => Ok(Aggregation::Sum),
            "average" => Ok(Aggregation::Average),
            _ => Err(Error::Invalid(format!("unknown message aggregation {s:?}; available: sum, average"))),
        }
    }
}

impl Default for MrfParams {
    fn default() -> Self {
        MrfParams {
            prior: 0.1,
            iterations: 3,
            allocation: Allocation::Band,
            keyframes: KeyframeSelection::All,
            messages: Aggregation::Sum,
            damping: 0.3,
            tolerance: None,
        }
    }
}

/// Identifies a keyframe of an [`MrfEngine`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyframeId(pub u64);

struct Keyframe {
    id: KeyframeId,
    frame: Frame,
    noise: Arc<NoiseModel>,
    /// Bricks this keyframe allocated (counted in `MrfEngine::brick_refs`).
    bricks: Vec<BrickKey>,
    /// Per voxel, under [`Aggregation::Sum`]: the keyframe's message per metre of its rays
    /// inside the voxel, `W_k / L_k`. A ray's own share is that times its length, and `W_k`
    /// that times `L_k`, which is geometry: every trace of the keyframe sums the same lengths.
    /// Under [`Aggregation::Average`]: `W_k` itself. One value per voxel, as for the paper's
    /// average.
    messages: Grid<f32>,
    /// The `MrfEngine::epoch` of its last trace (`None`: not traced since added or moved).
    traced_at: Option<u64>,
}

/// Messages are kept away from 0 and 1 so that their log-odds stay finite.
const MSG_EPS: f64 = 1e-6;

/// A voxel whose `S` is within this many log-odds of the prior's carries no evidence and is
/// left out of [`Engine::map`] (unknown). Rays that reach a voxel move it by far more; rays
/// that are occluded before it send messages of 1/2 and move it by nothing. Results hardly
/// depend on the value (0.001 to 0.2 change the demo room's MAE by 0.006).
const UNOBSERVED: f64 = 0.01;

/// Image rows per block of parallel work; fixed so results do not depend on thread count.
const ROWS_PER_BLOCK: u32 = 16;

/// Default tolerance of [`MrfEngine::run_until`] on a marginal's change in one update.
pub const DEFAULT_TOLERANCE: f64 = 1e-3;

/// Blocks traced before their partial sums are merged (bounds the memory of a keyframe pass).
const BLOCKS_IN_FLIGHT: usize = 8;

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
    /// Per voxel `S = logit(prior) + sum_k logit(msg_k)`; allocated = the union of keyframes' bricks.
    sums: Grid<f32>,
    brick_refs: FxHashMap<BrickKey, u32>,
    keyframes: Vec<Keyframe>,
    next_id: u64,
    default_noise: Arc<NoiseModel>,
    /// Bricks whose evidence changed since the last `run` (keyframes added, moved, removed).
    changed: FxHashSet<BrickKey>,
    /// Keyframes updated per iteration by the last `run`.
    last_run: usize,
    /// Counts keyframe updates and withdrawals; stamps what changed when.
    epoch: u64,
    /// Per brick, the epoch when a marginal in it last moved by more than the tolerance of
    /// [`MrfEngine::run_until`] (or a keyframe's messages left it).
    stamps: FxHashMap<BrickKey, u64>,
    /// The tolerance the stamps are taken at (`run_until` sets it).
    tolerance: f64,
}

/// What [`MrfEngine::run_until`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RunReport {
    /// Sweeps over the keyframes (each updates only those whose inputs moved).
    pub sweeps: usize,
    /// Keyframe updates in all.
    pub keyframe_updates: usize,
    /// Rays traced in all.
    pub rays: usize,
    /// Whether the last sweep had nothing left to update.
    pub converged: bool,
}

impl MrfEngine {
    /// The map voxel of a marginal's log-odds sum `S`: none where no ray reached the voxel
    /// (`S` within [`UNOBSERVED`] of the prior), so unreached space stays unknown.
    fn map_voxel(&self, s: f32) -> Option<MapVoxel> {
        ((s as f64 - logit(self.params.prior)).abs() > UNOBSERVED)
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
        if !(0.0..1.0).contains(&params.damping) {
            return Err(Error::Invalid(format!("MRF damping must be in [0, 1), got {}", params.damping)));
        }
        Ok(MrfEngine {
            params,
            limits,
            sums: Grid::new(resolution)?,
            brick_refs: FxHashMap::default(),
            keyframes: Vec::new(),
            next_id: 0,
            default_noise: Arc::new(default_noise_model()),
            changed: FxHashSet::default(),
            last_run: 0,
            epoch: 0,
            stamps: FxHashMap::default(),
            tolerance: DEFAULT_TOLERANCE,
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

    /// Adds a keyframe and allocates its bricks; call [`MrfEngine::run`] to infer.
    /// Fails on an image that does not match its camera or a non-finite pose.
    pub fn add_keyframe(&mut self, frame: Frame) -> Result<KeyframeId> {
        check_frame(&frame)?;
        let noise = frame.noise.clone().unwrap_or_else(|| self.default_noise.clone());
        noise.check_camera(&frame.camera).map_err(Error::Invalid)?;
        let id = KeyframeId(self.next_id);
        self.next_id += 1;
        let mut kf =
            Keyframe { id, frame, noise, bricks: Vec::new(), messages: Grid::new(self.resolution())?, traced_at: None };
        kf.bricks = self.allocation_of(&kf);
        self.reference_bricks(&kf.bricks);
        self.changed.extend(kf.bricks.iter().copied());
        self.keyframes.push(kf);
        Ok(id)
    }

    /// Removes a keyframe: its messages leave the sums and the bricks only it allocated are
    /// freed. Call [`MrfEngine::run`] to let the other keyframes re-converge.
    pub fn remove_keyframe(&mut self, id: KeyframeId) -> Result<()> {
        let i = self.index_of(id)?;
        self.withdraw_messages(i);
        let kf = self.keyframes.remove(i);
        self.changed.extend(kf.bricks.iter().copied());
        self.release_bricks(&kf.bricks);
        self.stamps.retain(|b, _| self.brick_refs.contains_key(b));
        Ok(())
    }

    /// Moves a keyframe (e.g. after a loop closure): its messages are withdrawn and its bricks
    /// re-allocated for the new pose. Call [`MrfEngine::run`] to re-infer.
    pub fn set_pose(&mut self, id: KeyframeId, pose: Pose) -> Result<()> {
        let i = self.index_of(id)?;
        let mut frame = self.keyframes[i].frame.clone();
        frame.pose = pose;
        check_frame(&frame)?;
        self.withdraw_messages(i);
        let old = std::mem::take(&mut self.keyframes[i].bricks);
        self.keyframes[i].frame = frame;
        let new = self.allocation_of(&self.keyframes[i]);
        self.reference_bricks(&new);
        self.changed.extend(old.iter().chain(&new).copied());
        self.keyframes[i].bricks = new;
        self.keyframes[i].traced_at = None;
        self.release_bricks(&old);
        Ok(())
    }

    /// Belief propagation until nothing moves: sweeps over the keyframes, re-tracing only
    /// those whose inputs changed. A keyframe is re-traced when, since its last trace, a
    /// marginal in a brick its rays reach moved by more than `tolerance` in one update by
    /// another keyframe (or a keyframe's messages left the brick); new and moved keyframes
    /// are always traced. Stops when a sweep traces nothing, or after `max_sweeps` sweeps.
    /// Changes below the tolerance are not tracked, so the result is within a small multiple
    /// of it of a fixed point, not at it.
    pub fn run_until(&mut self, tolerance: f64, max_sweeps: usize) -> RunReport {
        self.tolerance = tolerance;
        let mut report = RunReport::default();
        for _ in 0..max_sweeps {
            let mut updated = 0;
            for i in 0..self.keyframes.len() {
                let kf = &self.keyframes[i];
                let stale = match kf.traced_at {
                    None => true,
                    Some(t) => kf.messages.bricks().any(|(b, _)| self.stamps.get(b).is_some_and(|&e| e > t)),
                };
                if stale {
                    self.update_keyframe(i);
                    updated += 1;
                    report.rays += self.keyframes[i].frame.depth.valid_count();
                }
            }
            report.sweeps += 1;
            report.keyframe_updates += updated;
            if updated == 0 {
                report.converged = true;
                break;
            }
        }
        self.changed.clear();
        report
    }

    /// Runs `iterations` rounds of belief propagation. After keyframes were added, moved or
    /// removed, only the keyframes that share a brick with them are re-traced: the others'
    /// voxels did not change, so their messages would come out the same. (Effects two or more
    /// overlaps away are left to later runs.) With no such edits pending it sweeps every
    /// keyframe, so repeated calls keep converging.
    pub fn run(&mut self, iterations: usize) {
        self.run_with_progress(iterations, &mut |_, _| {});
    }

    /// [`MrfEngine::run`], calling `progress(done, total)` after each keyframe update.
    pub fn run_with_progress(&mut self, iterations: usize, progress: &mut dyn FnMut(usize, usize)) {
        let active: Vec<usize> = if self.changed.is_empty() {
            (0..self.keyframes.len()).collect()
        } else {
            let changed = &self.changed;
            (0..self.keyframes.len())
                .filter(|&i| self.keyframes[i].bricks.iter().any(|b| changed.contains(b)))
                .collect()
        };
        let total = iterations * active.len();
        for round in 0..iterations {
            for (n, &i) in active.iter().enumerate() {
                self.update_keyframe(i);
                progress(round * active.len() + n + 1, total);
            }
        }
        self.changed.clear();
        self.last_run = active.len();
    }

    /// Runs `iterations` rounds over every keyframe, whatever changed.
    pub fn run_all(&mut self, iterations: usize) {
        self.changed.clear();
        self.run(iterations);
    }

    /// Keyframes the last [`MrfEngine::run`] updated in each iteration.
    pub fn last_run_keyframes(&self) -> usize {
        self.last_run
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
            KeyframeSelection::Auto { translation, rotation } => self.keyframes.iter().all(|k| {
                let d = k.frame.pose.inverse() * pose;
                d.translation.vector.norm() > translation || d.rotation.angle() > rotation
            }),
        }
    }

    fn index_of(&self, id: KeyframeId) -> Result<usize> {
        self.keyframes.iter().position(|k| k.id == id).ok_or_else(|| Error::Invalid(format!("no keyframe {id:?}")))
    }

    /// Takes keyframe `i`'s messages out of the sums and forgets them. Under
    /// [`Aggregation::Sum`] this walks its rays again for their lengths (no forward model).
    fn withdraw_messages(&mut self, i: usize) {
        let mode = self.params.messages;
        let lengths = (mode == Aggregation::Sum).then(|| self.trace_keyframe(i, true));
        self.epoch += 1;
        let kf = &mut self.keyframes[i];
        for (bk, _) in kf.messages.bricks() {
            self.stamps.insert(*bk, self.epoch);
        }
        for (key, stored) in kf.messages.iter() {
            let length = lengths.as_ref().and_then(|g| g.get(key)).map_or(0.0, |e| e.1);
            if let Some(s) = self.sums.get_mut(key) {
                *s -= message_of(mode, *stored, length);
            }
        }
        kf.messages = Grid::new(self.sums.resolution()).expect("valid resolution");
    }

    fn reference_bricks(&mut self, bricks: &[BrickKey]) {
        let prior = logit(self.params.prior) as f32;
        // New bricks start at the prior; a brick already allocated keeps its sums.
        for &b in bricks {
            let refs = self.brick_refs.entry(b).or_insert(0);
            *refs += 1;
            if *refs == 1 {
                let brick = self.sums.brick_or_insert(b);
                for slot in 0..BRICK_VOXELS {
                    brick.get_or_insert(slot, prior);
                }
            }
        }
    }

    /// Drops a reference to each brick; bricks nobody references leave the map, with every
    /// keyframe's messages in them (as if they had never been allocated).
    fn release_bricks(&mut self, bricks: &[BrickKey]) {
        let mut freed = Vec::new();
        for b in bricks {
            if let Some(refs) = self.brick_refs.get_mut(b) {
                *refs -= 1;
                if *refs == 0 {
                    self.brick_refs.remove(b);
                    freed.push(*b);
                }
            }
        }
        if freed.is_empty() {
            return;
        }
        self.sums.remove_bricks(&freed);
        for kf in &mut self.keyframes {
            kf.messages.remove_bricks(&freed);
        }
    }

    /// The bricks keyframe `kf` allocates.
    fn allocation_of(&self, kf: &Keyframe) -> Vec<BrickKey> {
        let r = self.resolution();
        let rays = FrameRays::new(&kf.frame);
        let full = self.params.allocation == Allocation::Full;
        let limits = self.limits;
        let mut bricks: Vec<BrickKey> = (0..rays.rows())
            .into_par_iter()
            .fold(Vec::new, |mut out: Vec<BrickKey>, v| {
                for ray in rays.row(v) {
                    let Some(seg) = limits.forward_model_segment(&ray, &kf.noise) else { continue };
                    if seg.hits_surface {
                        // Bricks of the voxels within one voxel of the depth point.
                        let p = FrameRays::endpoint(&ray);
                        let k = VoxelKey::from_point(p, r);
                        for dz in -1..=1 {
                            for dy in -1..=1 {
                                for dx in -1..=1 {
                                    out.push(VoxelKey([k.0[0] + dx, k.0[1] + dy, k.0[2] + dz]).brick());
                                }
                            }
                        }
                    }
                    if full {
                        let edge = r * BRICK_EDGE as f64;
                        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, edge, |c| {
                            out.push(BrickKey(c.key.0));
                            ControlFlow::Continue(())
                        });
                    }
                }
                out.sort_unstable();
                out.dedup();
                out
            })
            .reduce(Vec::new, |mut a, b| {
                a.extend(b);
                a
            });
        bricks.sort_unstable();
        bricks.dedup();
        bricks
    }

    /// Traces keyframe `i` with the current cavities and replaces its messages in the sums.
    fn update_keyframe(&mut self, i: usize) {
        let total = self.trace_keyframe(i, false);
        let mode = self.params.messages;
        self.epoch += 1;
        let (epoch, tolerance, damping) = (self.epoch, self.tolerance, self.params.damping as f32);
        let kf = &self.keyframes[i];
        let mut messages: Grid<f32> = Grid::new(self.resolution()).expect("valid resolution");
        // Voxel by voxel, out with the old message and in with the new. This trace reached the
        // same voxels with the same lengths as the last one (a freed brick left every
        // keyframe's messages), so its lengths also turn the stored values into old messages.
        for (bk, brick) in total.bricks() {
            let old = kf.messages.brick(*bk);
            let Some(sums) = self.sums.brick_mut(*bk) else { continue }; // traced means allocated
            let target = messages.brick_or_insert(*bk);
            let mut moved = false;
            for (slot, &(wm, w)) in brick.iter() {
                let Some(s) = sums.get_mut(slot) else { continue };
                let old = old.and_then(|b| b.get(slot)).map_or(0.0, |q| message_of(mode, *q, w));
                // Damped in log-odds: part of the old message stays (a keyframe's first
                // message, with no old one, goes in whole).
                let fresh = message_of(mode, stored_of(mode, wm, w), w);
                let msg = if old != 0.0 { damping * old + (1.0 - damping) * fresh } else { fresh };
                let stored = match mode {
                    Aggregation::Sum if w > 0.0 => msg / w,
                    Aggregation::Sum => 0.0,
                    Aggregation::Average => msg,
                };
                let before = *s;
                *s += message_of(mode, stored, w) - old;
                // |d sigmoid| <= |dS| / 4: the exponentials only for changes that may matter.
                if !moved && (*s - before).abs() as f64 > 4.0 * tolerance {
                    moved = (sigmoid(*s as f64) - sigmoid(before as f64)).abs() > tolerance;
                }
                *target.get_or_insert(slot, 0.0) = stored;
            }
            if moved {
                self.stamps.insert(*bk, epoch);
            }
        }
        self.keyframes[i].messages = messages;
        self.keyframes[i].traced_at = Some(epoch);
    }

    /// Traces keyframe `i`: per voxel the sum of its rays' contributions (see [`Aggregation`])
    /// and the sum of their lengths; with `lengths_only`, the lengths alone (no forward model).
    fn trace_keyframe(&self, i: usize, lengths_only: bool) -> Grid<(f32, f32)> {
        let kf = &self.keyframes[i];
        let rays = FrameRays::new(&kf.frame);
        let blocks: Vec<u32> = (0..rays.rows().div_ceil(ROWS_PER_BLOCK)).collect();
        // Per block: voxel -> (sum of the rays' contributions, sum of length), in bricks so
        // that a ray's consecutive voxels share one lookup. Blocks are traced a few at a time
        // and merged in block order: the same sums whatever the number of threads, and only a
        // few blocks' partial grids in memory at once.
        let mut total: Grid<(f32, f32)> = Grid::new(self.resolution()).expect("valid resolution");
        for chunk in blocks.chunks(BLOCKS_IN_FLIGHT) {
            let partials: Vec<Grid<(f32, f32)>> = chunk
                .par_iter()
                .map(|&b| {
                    let mut acc = Grid::new(self.resolution()).expect("valid resolution");
                    let mut scratch = RayScratch::default();
                    let rows = b * ROWS_PER_BLOCK..((b + 1) * ROWS_PER_BLOCK).min(rays.rows());
                    for v in rows {
                        for ray in rays.row(v) {
                            self.trace_ray(kf, &ray, lengths_only, &mut scratch, &mut acc);
                        }
                    }
                    acc
                })
                .collect();
            for part in partials {
                for (bk, brick) in part.bricks() {
                    let target = total.brick_or_insert(*bk);
                    for (slot, (wm, w)) in brick.iter() {
                        let e = target.get_or_insert(slot, (0.0, 0.0));
                        e.0 += wm;
                        e.1 += w;
                    }
                }
            }
        }
        total
    }

    /// One ray: gather the allocated voxels it crosses, their cavities and likelihoods, and
    /// add its outgoing messages to `acc`; with `lengths_only`, only its lengths.
    fn trace_ray(
        &self,
        kf: &Keyframe,
        ray: &PixelRay,
        lengths_only: bool,
        scratch: &mut RayScratch,
        acc: &mut Grid<(f32, f32)>,
    ) {
        let Some(seg) = self.limits.forward_model_segment(ray, &kf.noise) else { return };
        let r = self.resolution();
        let measured = ray.range * ray.cz;
        let mode = self.params.messages;
        scratch.clear();
        let edge = r * BRICK_EDGE as f64;
        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, edge, |b| {
            let key = BrickKey(b.key.0);
            let (Some(sums), msgs) = (self.sums.brick(key), kf.messages.brick(key)) else {
                return ControlFlow::Continue(()); // unallocated: skipped, as the reference does
            };
            for_each_crossing(ray.origin, ray.dir, b.s_in, b.s_out, r, |c| {
                let (s, m) = if c.key.brick() == key {
                    (sums.get(c.key.slot()), msgs.and_then(|g| g.get(c.key.slot())))
                } else {
                    (self.sums.get(c.key), kf.messages.get(c.key)) // rounding at a brick face
                };
                match s {
                    Some(_) if lengths_only => scratch.push(c.key, c.length(), 0.0, 0.0),
                    Some(s) => {
                        // The cavity: everything the voxel heard except this ray's own message.
                        let own = m.map_or(0.0, |q| message_of(mode, *q, c.length() as f32));
                        let cavity = sigmoid((*s - own) as f64);
                        let nu = kf.noise.likelihood_over(ray.u, ray.v, c.s_in * ray.cz, c.s_out * ray.cz, measured);
                        scratch.push(c.key, c.length(), cavity, nu);
                    }
                    None => {}
                }
                ControlFlow::Continue(())
            });
            ControlFlow::Continue(())
        });
        if scratch.keys.is_empty() {
            return;
        }
        if !lengths_only {
            let z_end = seg.end * ray.cz;
            let beyond = if seg.hits_surface {
                kf.noise.likelihood_over(ray.u, ray.v, z_end, z_end + r * ray.cz, measured)
            } else {
                0.0
            };
            ray_messages(&scratch.mu, &scratch.nu, beyond, &mut scratch.out);
        }
        let inv_r = 1.0 / r;
        let mut j = 0;
        while j < scratch.keys.len() {
            // One brick lookup per run of voxels in the same brick.
            let bk = scratch.keys[j].brick();
            let brick = acc.brick_or_insert(bk);
            while j < scratch.keys.len() && scratch.keys[j].brick() == bk {
                let l = scratch.length[j];
                let e = brick.get_or_insert(scratch.keys[j].slot(), (0.0, 0.0));
                if !lengths_only {
                    let m = scratch.out[j];
                    e.0 += match mode {
                        Aggregation::Average => (l * m) as f32,
                        Aggregation::Sum => (l * inv_r * logit(m.clamp(MSG_EPS, 1.0 - MSG_EPS))) as f32,
                    };
                }
                e.1 += l as f32;
                j += 1;
            }
        }
    }
}

/// What a keyframe stores for a voxel whose trace summed `wm` (the rays' contributions) over
/// `w` metres of ray ([`Keyframe::messages`]).
fn stored_of(mode: Aggregation, wm: f32, w: f32) -> f32 {
    if w <= 0.0 {
        return 0.0; // only crossings of zero length: no evidence
    }
    match mode {
        Aggregation::Average => logit((wm as f64 / w as f64).clamp(MSG_EPS, 1.0 - MSG_EPS)) as f32,
        Aggregation::Sum => wm / w,
    }
}

/// The message (log-odds) that `stored` stands for over `length` metres of ray: one ray's
/// own share, or with the keyframe's total length its whole `W_k`. Under the average, a
/// keyframe sends the same message whatever the length.
fn message_of(mode: Aggregation, stored: f32, length: f32) -> f32 {
    match mode {
        Aggregation::Average => stored,
        Aggregation::Sum => stored * length,
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

/// Per-ray buffers, reused across rays of a block.
#[derive(Default)]
struct RayScratch {
    keys: Vec<VoxelKey>,
    length: Vec<f64>,
    mu: Vec<f64>,
    nu: Vec<f64>,
    out: Vec<f64>,
}

impl RayScratch {
    fn clear(&mut self) {
        self.keys.clear();
        self.length.clear();
        self.mu.clear();
        self.nu.clear();
    }

    fn push(&mut self, key: VoxelKey, length: f64, mu: f64, nu: f64) {
        self.keys.push(key);
        self.length.push(length);
        self.mu.push(mu);
        self.nu.push(nu);
    }
}

impl Engine for MrfEngine {
    fn name(&self) -> &'static str {
        "mrf"
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
        match self.params.tolerance {
            Some(t) => {
                let r = self.run_until(t, self.params.iterations);
                tracing::info!(
                    "MRF: {} sweeps, {} keyframe updates, {} rays traced, {}",
                    r.sweeps,
                    r.keyframe_updates,
                    r.rays,
                    if r.converged { "converged" } else { "not converged (sweep cap)" }
                );
            }
            None => {
                self.run_with_progress(self.params.iterations, progress);
                let rays: usize = self.keyframes.iter().map(|k| k.frame.depth.valid_count()).sum();
                tracing::info!(
                    "MRF: {} sweeps over {} of {} keyframes, {} rays traced per sweep of all keyframes",
                    self.params.iterations,
                    self.last_run,
                    self.keyframes.len(),
                    rays
                );
            }
        }
        Ok(())
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.map_voxel(*self.sums.get(key)?)
    }

    fn map(&self) -> Map {
        let mut map = Map::new(self.name(), self.resolution()).expect("valid resolution");
        for (key, s) in self.sums.iter() {
            if let Some(v) = self.map_voxel(*s) {
                map.voxels.insert(key, v);
            }
        }
        let p = self.params;
        map.params.insert("prior".into(), p.prior.to_string());
        map.params.insert("iterations".into(), p.iterations.to_string());
        map.params.insert("allocation".into(), format!("{:?}", p.allocation).to_lowercase());
        map.params.insert("messages".into(), format!("{:?}", p.messages).to_lowercase());
        map.params.insert("damping".into(), p.damping.to_string());
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
