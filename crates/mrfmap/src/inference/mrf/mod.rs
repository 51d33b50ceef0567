//! The MRFMap engine: every depth pixel of every keyframe is a ray factor in a Markov random
//! field over binary voxel occupancies; loopy sum-product belief propagation over all
//! keyframes gives each voxel's marginal (MRFMap secs. III-IV, docs/ALGORITHMS.md 5.3).
//!
//! How the pieces fit:
//! - [`ray_messages`] computes one ray factor's outgoing messages in linear time.
//! - Every ray is a factor, as in the model. Each voxel keeps `S = logit(prior) + sum of the
//!   messages (log-odds) of every ray that reaches it`; the marginal is `sigmoid(S)`. A ray's
//!   message counts with its length in the voxel over the voxel edge: a full crossing counts
//!   once, a corner clip a little. (The paper's text averages a keyframe's rays into one
//!   message per voxel; a voxel crossed by 100 rays then gets the evidence of one, walls stay
//!   at 0.2-0.5 and the marginals are under-confident by construction: RESULTS.md.)
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
//!   cross it (the brick projected into their images, nearer than their rays reach); a freed
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

use std::ops::ControlFlow;
use std::sync::Arc;

use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

pub use messages::{MU_EPS, ray_messages};
pub use online::{Budget, MAX_BATCH, StepReport};

use super::{Engine, logit, sigmoid};
use crate::error::{Error, Result};
use crate::frames::{Frame, NoiseModel, Pose, default_noise_model};
use crate::map::{
    BRICK_EDGE, BRICK_VOXELS, Brick, BrickKey, Grid, Map, MapVoxel, SlotMask, VoxelKey, mask_set, mask_slots,
};
use crate::rays::{FrameRays, RayLimits, for_each_crossing, pose_parts};

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
    /// Sweeps run by [`Engine::finish`]: all of them with `tolerance: None` (the default:
    /// [`DEFAULT_SWEEPS`], the paper's 3), at most this many otherwise.
    pub iterations: usize,
    /// Brick allocation mode.
    pub allocation: Allocation,
    /// Which frames [`Engine::integrate`] turns into keyframes.
    pub keyframes: KeyframeSelection,
    /// Share of a tile's old message (log-odds) kept when it is replaced, in `[0, 1)`, on
    /// top of the halving of messages whose change reverses (which is what stops the
    /// sequential schedule's cycles). 0 (the default) converges in fewer traces: every
    /// change goes in whole, where 0.3 let a message approach its new value by 70% a trace
    /// (a 60-view map converges with 2.5x fewer tile traces, and the held-out scores match
    /// within 0.002; RESULTS.md).
    pub damping: f64,
    /// Rays traced per keyframe, as their spacing in voxel edges: where pixels are much
    /// smaller than voxels, a tile traces one ray per `s x s` pixel block (`s` a power of two
    /// up to 8), the largest `s` whose rays lie at most this far apart at the tile's nearest
    /// depth, and the ray counts for the block's valid pixels. Their rays through a voxel are
    /// nearly alike. 0 (the default) traces every pixel; RESULTS.md measures what 0.5 and 1
    /// save and cost.
    pub ray_spacing: f64,
    /// With `Some(t)`, [`Engine::finish`] runs [`MrfEngine::run_until`] with tolerance `t`
    /// and at most `iterations` sweeps; with `None` (the default), `iterations` full sweeps
    /// ([`MrfEngine::run`]). The online schedule ([`MrfEngine::refine`]) follows moves above
    /// `t`, [`DEFAULT_TOLERANCE`] when `None`.
    pub tolerance: Option<f64>,
    /// With `Some(w)`, [`Engine::finish`] runs the online schedule's order instead
    /// ([`MrfEngine::refine`]): every tile traced once, then the largest moves first, for at
    /// most `w` times as many tile traces as the keyframes have tiles in all (the first trace
    /// included), stopping early when nothing moves by more than the tolerance. Takes
    /// precedence over `tolerance` and `iterations`.
    pub work: Option<f64>,
    /// A voxel whose `S` lies within this many log-odds of the prior's is unknown:
    /// [`Engine::map`] leaves it out. The default, `ln 3` ([`DEFAULT_MIN_EVIDENCE`]), is
    /// where Kass and Raftery's scale of evidence (JASA 1995) ends "not worth more than a
    /// bare mention": a Bayes factor below 3. Such voxels are mostly inside walls, just
    /// behind surfaces: every ray occluded there sends a message a hair above 1/2, and
    /// hundreds of them sum to a marginal of 0.1-0.3 where the truth is 1 (RESULTS.md). 0
    /// keeps every voxel a ray reached.
    pub min_evidence: f64,
}

/// Default of [`MrfParams::min_evidence`]: `ln 3`.
pub const DEFAULT_MIN_EVIDENCE: f64 = 1.0986122886681098;

impl Default for MrfParams {
    fn default() -> Self {
        MrfParams {
            prior: 0.1,
            iterations: DEFAULT_SWEEPS,
            allocation: Allocation::Band,
            keyframes: KeyframeSelection::All,
            damping: 0.0,
            ray_spacing: 0.0,
            tolerance: None,
            work: None,
            min_evidence: DEFAULT_MIN_EVIDENCE,
        }
    }
}

/// Identifies a keyframe of an [`MrfEngine`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyframeId(pub u64);

/// Pixels per side of a tile, the unit of bookkeeping and re-tracing (see the module docs).
pub const TILE: u32 = 16;

/// One voxel that a tile's rays reach (10 bytes; its brick is the tile's run's). The tiles
/// are most of the engine's memory (22 million entries for coffin-world at 0.01 m), so the
/// fields are 16 bits wide: the message is an `f32` kept as two halves, so that the entry
/// needs no 4-byte alignment (12 bytes otherwise).
#[derive(Clone, Copy, Debug, Default)]
struct Entry {
    /// The tile's message to the voxel (log-odds), the bits of an `f32`: its rays' messages,
    /// each weighted by its length over the voxel edge, summed and damped. Kept exactly:
    /// removal subtracts it.
    message: [u16; 2],
    /// Summed length of the tile's rays in the voxel, in 1/[`LENGTH_STEPS`] voxel edges (a
    /// tile's 256 rays reach at most 443 edges; saturates at 512). It only apportions the
    /// message among the rays for their cavities.
    length: u16,
    /// The voxel's `S` that the tile's rays saw when it last traced, in 1/[`SEEN_STEPS`]
    /// log-odds, saturating at +-32 (where marginals differ from 0 or 1 by 1e-14): the
    /// rounding moves a marginal by at most 1.2e-4, a tenth of the default tolerance.
    seen: i16,
    /// Bits 0-8: the voxel's slot in its brick. Bits 9-15: `9 level + 3 calm + sign`, where
    /// `level` (0-8) is the extra damping (the share of a change that goes in is halved this
    /// many times), `calm` (0-2) counts the traces in a row whose change did not reverse, and
    /// `sign` is the last change's: 0 none, 1 positive, 2 negative.
    packed: u16,
}

// The tiles' memory is 10 bytes per entry, and the damping state fits its 7 bits.
const _: () = assert!(std::mem::size_of::<Entry>() == 10);
const _: () = assert!(9 * MAX_DAMPING_LEVEL as u16 + 3 * (CALM_TRACES as u16 - 1) + 2 < 1 << 7);

/// Steps per voxel edge of [`Entry::length`].
const LENGTH_STEPS: f64 = 128.0;
/// Steps per unit of log-odds of [`Entry::seen`].
const SEEN_STEPS: f32 = 1024.0;

impl Entry {
    /// The entry of the voxel in `slot`, with no damping and no change yet.
    fn new(slot: usize) -> Entry {
        Entry { packed: slot as u16, ..Entry::default() }
    }

    /// The message (log-odds).
    fn message(&self) -> f32 {
        f32::from_bits(self.message[0] as u32 | (self.message[1] as u32) << 16)
    }

    fn set_message(&mut self, m: f32) {
        let bits = m.to_bits();
        self.message = [bits as u16, (bits >> 16) as u16];
    }

    /// The voxel's slot in its brick.
    fn slot(&self) -> usize {
        (self.packed & 0x1ff) as usize
    }

    /// The summed length in voxel edges.
    fn edges(&self) -> f32 {
        self.length as f32 / LENGTH_STEPS as f32
    }

    fn set_edges(&mut self, edges: f64) {
        self.length = (edges * LENGTH_STEPS).round().min(u16::MAX as f64) as u16;
    }

    /// The `S` the tile saw.
    fn seen(&self) -> f32 {
        self.seen as f32 / SEEN_STEPS
    }

    fn set_seen(&mut self, s: f32) {
        self.seen = (s * SEEN_STEPS).round().clamp(-(i16::MAX as f32), i16::MAX as f32) as i16;
    }

    /// `9 level + 3 calm + sign` (see [`Entry::packed`]).
    fn damping(&self) -> u8 {
        (self.packed >> 9) as u8
    }

    /// Extra damping level.
    fn level(&self) -> u8 {
        self.damping() / 9
    }

    /// Traces in a row without a reversal.
    fn calm(&self) -> u8 {
        self.damping() / 3 % 3
    }

    /// The sign of the message's last change (0 for none).
    fn step_sign(&self) -> f64 {
        match self.damping() % 3 {
            1 => 1.0,
            2 => -1.0,
            _ => 0.0,
        }
    }

    /// Records the damping level (at most [`MAX_DAMPING_LEVEL`]), the calm count (below
    /// [`CALM_TRACES`]) and the sign of the last change, `step`.
    fn set_damping(&mut self, level: u8, calm: u8, step: f64) {
        let sign = if step > 0.0 {
            1
        } else if step < 0.0 {
            2
        } else {
            0
        };
        let code = 9 * level.min(MAX_DAMPING_LEVEL) as u16 + 3 * calm.min(CALM_TRACES - 1) as u16 + sign;
        self.packed = (self.packed & 0x1ff) | code << 9;
    }
}

#[derive(Clone, Debug, Default)]
struct Tile {
    /// Sorted by brick, then slot, so that consecutive entries share a brick lookup.
    entries: Vec<Entry>,
    /// Each brick of the entries with the index of its first entry.
    runs: Vec<(BrickKey, u32)>,
    /// The `MrfEngine::epoch` of its last trace.
    traced_at: u64,
    /// Must be re-traced: new, moved, or a brick its rays may cross came or went.
    stale: bool,
    /// A brick its rays may cross changed since the keyframe's last check.
    suspect: bool,
    /// The largest camera z its rays reach (m); new bricks beyond it cannot affect it.
    z_max: f32,
    /// How far (in marginal) its last update fell short of what its rays computed, where
    /// damping held a message back: the largest move the rest of the step would make.
    held_back: f32,
    /// The online schedule's backlog priority ([`MrfEngine::refine`]): the largest marginal
    /// move of a voxel its rays reach since it traced, as far as the checks so far found
    /// (0 until a check finds one; a trace resets it).
    priority: f32,
}

impl Tile {
    /// The entries of run `n` (brick `runs[n].0`).
    fn run(&self, n: usize) -> &[Entry] {
        let end = self.runs.get(n + 1).map_or(self.entries.len(), |r| r.1 as usize);
        &self.entries[self.runs[n].1 as usize..end]
    }

    /// Every entry with its voxel.
    fn iter(&self) -> impl Iterator<Item = (VoxelKey, &Entry)> + '_ {
        (0..self.runs.len()).flat_map(move |n| self.run(n).iter().map(move |e| (self.runs[n].0.voxel(e.slot()), e)))
    }

    /// Appends the entry of voxel `key` (entries come sorted by brick and slot).
    fn push(&mut self, key: VoxelKey, entry: Entry) {
        if self.runs.last().is_none_or(|&(b, _)| b != key.brick()) {
            self.runs.push((key.brick(), self.entries.len() as u32));
        }
        self.entries.push(entry);
    }

    /// Drops the entries in bricks `freed`; true if there were any.
    fn drop_bricks(&mut self, freed: &FxHashSet<BrickKey>) -> bool {
        if !self.runs.iter().any(|(b, _)| freed.contains(b)) {
            return false;
        }
        let mut kept = Tile { stale: true, traced_at: self.traced_at, z_max: self.z_max, ..Tile::default() };
        kept.entries.reserve_exact(self.entries.len());
        for (k, e) in self.iter().filter(|(k, _)| !freed.contains(&k.brick())) {
            kept.push(k, *e);
        }
        kept.entries.shrink_to_fit();
        kept.runs.shrink_to_fit();
        *self = kept;
        true
    }
}

struct Keyframe {
    id: KeyframeId,
    frame: Frame,
    noise: Arc<NoiseModel>,
    /// Bricks this keyframe allocated (counted in `MrfEngine::brick_refs`).
    bricks: Vec<BrickKey>,
    /// Row-major, `tiles_x` per row.
    tiles: Vec<Tile>,
    tiles_x: u32,
    /// The `MrfEngine::epoch` when `run_until` last checked its tiles.
    checked_at: u64,
}

impl Keyframe {
    /// The pixel columns and rows of tile `t`.
    fn tile_pixels(&self, t: usize) -> (std::ops::Range<u32>, std::ops::Range<u32>) {
        let (tx, ty) = (t as u32 % self.tiles_x, t as u32 / self.tiles_x);
        let (w, h) = (self.frame.depth.width(), self.frame.depth.height());
        (tx * TILE..((tx + 1) * TILE).min(w), ty * TILE..((ty + 1) * TILE).min(h))
    }

    /// The world-to-camera rotation and the camera's origin.
    fn to_camera(&self) -> (nalgebra::Matrix3<f64>, [f64; 3]) {
        let (rotation, origin) = pose_parts(&self.frame.pose);
        (rotation.transpose(), origin)
    }

    /// Calls `visit` on every tile whose rays may cross brick `b` (of edge `edge` m): the
    /// brick's projection (the box around its projected corners, a pixel wider) overlaps
    /// the tile, and its nearest point is no farther than the tile's rays reach. A ray that
    /// crosses the brick passes through its projection, at a depth at least the brick's
    /// smallest, so no such tile is missed.
    fn for_tiles_reaching(
        &mut self,
        to_camera: &(nalgebra::Matrix3<f64>, [f64; 3]),
        b: BrickKey,
        edge: f64,
        mut visit: impl FnMut(&mut Tile),
    ) {
        let (rotation, origin) = to_camera;
        let camera = &self.frame.camera;
        let (w, h) = (camera.width as f64, camera.height as f64);
        let (mut z_min, mut z_max) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        let mut behind = false;
        for c in 0..8 {
            let p = nalgebra::Vector3::from_fn(|a, _| (b.0[a] as f64 + (c >> a & 1) as f64) * edge - origin[a]);
            let q = rotation * p;
            z_min = z_min.min(q.z);
            z_max = z_max.max(q.z);
            match camera.project(&q) {
                Some((u, v)) if q.z > 1e-9 => {
                    lo = [lo[0].min(u - 1.0), lo[1].min(v - 1.0)];
                    hi = [hi[0].max(u + 1.0), hi[1].max(v + 1.0)];
                }
                _ => behind = true,
            }
        }
        if z_max <= 0.0 {
            // Wholly behind the camera: rays only go forward. (Before this check, every tile
            // of a keyframe facing away from a new brick was marked stale: an add re-traced
            // whole keyframes that could not see it.)
            return;
        }
        if behind {
            // A corner at or behind the camera plane: the projection is unbounded.
            (lo, hi) = ([0.0, 0.0], [w, h]);
        }
        if hi[0] < 0.0 || hi[1] < 0.0 || lo[0] >= w || lo[1] >= h {
            return;
        }
        let cols = (lo[0].max(0.0) as u32 / TILE)..=((hi[0].min(w - 1.0)) as u32 / TILE);
        let rows = (lo[1].max(0.0) as u32 / TILE)..=((hi[1].min(h - 1.0)) as u32 / TILE);
        for ty in rows {
            for tx in cols.clone() {
                let tile = &mut self.tiles[(ty * self.tiles_x + tx) as usize];
                if z_min <= tile.z_max as f64 {
                    visit(tile);
                }
            }
        }
    }

    /// Forgets every message and marks every tile for tracing.
    fn reset_tiles(&mut self) {
        let (w, h) = (self.frame.depth.width(), self.frame.depth.height());
        self.tiles_x = w.div_ceil(TILE);
        let n = (self.tiles_x * h.div_ceil(TILE)) as usize;
        self.tiles = vec![Tile { stale: true, ..Tile::default() }; n];
    }
}

/// Messages are kept away from 0 and 1 so that their log-odds stay finite.
const MSG_EPS: f64 = 1e-6;

/// A voxel whose `S` is within this many log-odds of the prior's was reached by no ray (or
/// only by occluded ones, whose messages are 1/2): unknown whatever
/// [`MrfParams::min_evidence`] says.
const UNOBSERVED: f64 = 0.01;

/// Cap on an entry's extra damping level (its changes go in at 2^-8 of the plain share).
const MAX_DAMPING_LEVEL: u8 = 8;

/// Largest pixel stride of [`MrfParams::ray_spacing`] (a divisor of [`TILE`]).
const MAX_STRIDE: u32 = 8;

/// Traces in a row without a reversal after which an entry's extra damping level drops by one.
const CALM_TRACES: u8 = 3;

/// Default tolerance of [`MrfEngine::run_until`] on a marginal's change.
pub const DEFAULT_TOLERANCE: f64 = 1e-3;

/// Default sweeps of a batch build ([`MrfParams::default`]): the MRFMap paper's fixed three
/// passes. On coffin-world (views 2, 6 and 9 held out) they score within 0.002 of the
/// change-driven schedule at 0.01 m and 0.005-0.008 above it at 0.02 m, in a third of the time
/// (RESULTS.md, "Session 16").
pub const DEFAULT_SWEEPS: usize = 3;

/// Default cap on the sweeps of [`MrfEngine::run_until`] (`--tolerance` alone). Adding a
/// keyframe to a converged 60-view map of the demo room mostly reaches it with a few dozen
/// tiles still moving (about 1,900 tiles traced in all, 1,200 of them the new keyframe's); its
/// map is then within 0.02 of the converged one for 99.97% of voxels (BENCHMARKS.md). A whole
/// build may stop further away: a few hundred voxels of coffin-world at 0.02 m kept
/// oscillating for more than 100 sweeps (RESULTS.md).
pub const DEFAULT_MAX_SWEEPS: usize = 10;

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

/// What a schedule ([`MrfEngine::run`], [`MrfEngine::run_until`]) did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RunReport {
    /// Sweeps over the keyframes.
    pub sweeps: usize,
    /// Keyframe updates (a keyframe with at least one tile traced) in all.
    pub keyframe_updates: usize,
    /// Tiles traced in all.
    pub tiles: usize,
    /// Rays traced in all.
    pub rays: usize,
    /// Whether the last sweep had nothing left to trace (always false for [`MrfEngine::run`]).
    pub converged: bool,
}

impl RunReport {
    fn add(&mut self, other: RunReport) {
        self.keyframe_updates += other.keyframe_updates;
        self.tiles += other.tiles;
        self.rays += other.rays;
    }

    /// The debug line of sweep `sweep`: what was traced since the report was `start`.
    fn log_sweep(&self, sweep: usize, start: &RunReport) {
        tracing::debug!("sweep {sweep}: {} tiles, {} rays traced", self.tiles - start.tiles, self.rays - start.rays);
    }
}

/// One tile's trace, before it is applied.
struct Traced {
    /// Which tile, and what it becomes (without its epoch).
    index: usize,
    tile: Tile,
    /// Per entry of `tile`, the change it makes to `S`: its new message minus its old one.
    changes: Vec<f32>,
    /// The changes to voxels the tile's rays no longer reach (minus their old messages).
    gone: Vec<(VoxelKey, f32)>,
    rays: usize,
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
        self.changed.extend(old.iter().chain(&bricks).copied());
        self.keyframes[i].bricks = bricks;
        self.release_bricks(&old);
        Ok(())
    }

    /// Belief propagation until nothing moves (change-driven). Each sweep visits the
    /// keyframes in turn and re-traces only their tiles for which, since the tile last traced,
    /// some voxel its rays reach moved by more than `tolerance` in marginal (by any tile,
    /// the tile's own last update included), whose last update damping held back by more than
    /// `tolerance` (a voxel whose marginal sits at 0 or 1 hardly moves while a damped message
    /// crawls towards the other side), or which are stale (new, moved, or near a brick that
    /// came or went). Stops when a sweep traces nothing, or after `max_sweeps` sweeps.
    /// Changes below the tolerance are not followed, so the result is within a small multiple
    /// of it of a fixed point, not at it.
    pub fn run_until(&mut self, tolerance: f64, max_sweeps: usize) -> RunReport {
        self.run_until_with_progress(tolerance, max_sweeps, &mut |_, _| {})
    }

    /// [`MrfEngine::run_until`], calling `progress(sweep, max_sweeps)` after each sweep.
    pub fn run_until_with_progress(
        &mut self,
        tolerance: f64,
        max_sweeps: usize,
        progress: &mut dyn FnMut(usize, usize),
    ) -> RunReport {
        let mut report = RunReport::default();
        self.use_tolerance(tolerance);
        for sweep in 0..max_sweeps {
            let start = report;
            for i in 0..self.keyframes.len() {
                let dirty = self.dirty_tiles(i, tolerance);
                report.add(self.update_tiles(i, &dirty));
            }
            // Changes every keyframe has checked are not needed any more.
            self.trim_log();
            report.sweeps += 1;
            report.log_sweep(sweep + 1, &start);
            progress(sweep + 1, max_sweeps);
            if report.tiles == start.tiles {
                report.converged = true;
                break;
            }
        }
        self.changed.clear();
        report
    }

    /// Runs `iterations` sweeps of belief propagation, re-tracing every tile of each keyframe
    /// in a sweep. After keyframes were added, moved or removed, only the keyframes that share
    /// a brick with them or have stale tiles are swept: the others' voxels did not change,
    /// so their messages would come out the same. (Effects two or more overlaps away are left
    /// to later runs.) With no such edits pending it sweeps every keyframe, so repeated calls
    /// keep converging.
    pub fn run(&mut self, iterations: usize) -> RunReport {
        self.run_with_progress(iterations, &mut |_, _| {})
    }

    /// [`MrfEngine::run`], calling `progress(done, total)` after each keyframe update.
    pub fn run_with_progress(&mut self, iterations: usize, progress: &mut dyn FnMut(usize, usize)) -> RunReport {
        let active: Vec<usize> = if self.changed.is_empty() {
            (0..self.keyframes.len()).collect()
        } else {
            let changed = &self.changed;
            (0..self.keyframes.len())
                .filter(|&i| {
                    let kf = &self.keyframes[i];
                    kf.bricks.iter().any(|b| changed.contains(b)) || kf.tiles.iter().any(|t| t.stale)
                })
                .collect()
        };
        let total = iterations * active.len();
        let mut report = RunReport { sweeps: iterations, ..Default::default() };
        for round in 0..iterations {
            let start = report;
            for (n, &i) in active.iter().enumerate() {
                let all: Vec<usize> = (0..self.keyframes[i].tiles.len()).collect();
                report.add(self.update_tiles(i, &all));
                progress(round * active.len() + n + 1, total);
            }
            report.log_sweep(round + 1, &start);
        }
        self.changed.clear();
        self.last_run = active.len();
        report
    }

    /// Runs `iterations` sweeps over every keyframe, whatever changed.
    pub fn run_all(&mut self, iterations: usize) -> RunReport {
        self.changed.clear();
        self.run(iterations)
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

    /// Bytes held by the keyframes' tiles (their per-voxel bookkeeping).
    pub fn tile_bytes(&self) -> usize {
        let (per, run) = (std::mem::size_of::<Entry>(), std::mem::size_of::<(BrickKey, u32)>());
        self.keyframes.iter().flat_map(|k| &k.tiles).map(|t| t.entries.capacity() * per + t.runs.capacity() * run).sum()
    }

    fn index_of(&self, id: KeyframeId) -> Result<usize> {
        self.keyframes.iter().position(|k| k.id == id).ok_or_else(|| Error::Invalid(format!("no keyframe {id:?}")))
    }

    /// Takes keyframe `i`'s messages out of the sums and forgets them (exactly: each tile
    /// knows its messages).
    fn withdraw_messages(&mut self, i: usize) {
        self.epoch += 1;
        let tiles = std::mem::take(&mut self.keyframes[i].tiles);
        for tile in &tiles {
            let out: Vec<(VoxelKey, f32)> = tile.iter().map(|(k, e)| (k, -e.message())).collect();
            self.apply(&out);
        }
        self.keyframes[i].reset_tiles();
    }

    /// Adds `(voxel, change)` pairs, in runs by brick, to the sums (changes to voxels no longer
    /// allocated are dropped). A brick is stamped and logged when a marginal in it moved by
    /// more than `log_threshold` since it was last logged. A voxel that no log entry names
    /// has moved by at most two thresholds since the last check of any tile that reaches it,
    /// which found it within the tolerance: so changes that go unseen stay below 1.5
    /// tolerances.
    fn apply(&mut self, deltas: &[(VoxelKey, f32)]) {
        for run in deltas.chunk_by(|a, b| a.0.brick() == b.0.brick()) {
            self.apply_run(run[0].0.brick(), run.iter().map(|(k, d)| (k.slot(), *d)));
        }
    }

    /// [`MrfEngine::apply`] of `(slot, change)` pairs of brick `bk`.
    fn apply_run(&mut self, bk: BrickKey, run: impl Iterator<Item = (usize, f32)>) {
        let theta = self.log_threshold;
        let (Some(sums), Some(logged)) = (self.sums.brick_mut(bk), self.logged.brick_mut(bk)) else { return };
        let mut moved = false;
        for (slot, d) in run {
            if let (Some(s), Some(l)) = (sums.get_mut(slot), logged.get_mut(slot)) {
                *s += d;
                // |d sigmoid| <= |dS| / 4: the exponentials only for changes that may matter.
                if (*s - *l).abs() as f64 > 4.0 * theta && (sigmoid(*s as f64) - sigmoid(*l as f64)).abs() > theta {
                    *l = *s;
                    moved = true;
                }
            }
        }
        if moved {
            self.stamp(bk);
        }
    }

    /// Records that a sum in brick `b` changed in the current epoch. The log is bounded: past
    /// a few entries per brick it is dropped, and keyframes check all their tiles once.
    fn stamp(&mut self, b: BrickKey) {
        self.stamps.insert(b, self.epoch);
        if self.log.len() > 4 * self.brick_refs.len() + 4096 {
            self.log.clear();
            self.log_floor = self.epoch;
        }
        self.log.push((self.epoch, b));
    }

    /// References `bricks`; returns those that were not allocated before (they start at the
    /// prior; a brick already allocated keeps its sums).
    fn reference_bricks(&mut self, bricks: &[BrickKey]) -> Vec<BrickKey> {
        let prior = logit(self.params.prior) as f32;
        let mut new = Vec::new();
        for &b in bricks {
            let refs = self.brick_refs.entry(b).or_insert(0);
            *refs += 1;
            if *refs == 1 {
                for grid in [&mut self.sums, &mut self.logged] {
                    let brick = grid.brick_or_insert(b);
                    for slot in 0..BRICK_VOXELS {
                        brick.get_or_insert(slot, prior);
                    }
                }
                new.push(b);
            }
        }
        new
    }

    /// Marks stale every tile whose rays may cross one of the new `bricks`: the brick's
    /// corners projected into the keyframe's image overlap the tile, and the brick's nearest
    /// corner is no farther than the tile's rays reach. Tiles never traced are stale already.
    fn mark_tiles_reaching(&mut self, bricks: &[BrickKey]) {
        if bricks.is_empty() {
            return;
        }
        let edge = self.resolution() * BRICK_EDGE as f64;
        self.keyframes.par_iter_mut().for_each(|kf| {
            let to_camera = kf.to_camera();
            for b in bricks {
                kf.for_tiles_reaching(&to_camera, *b, edge, |tile| tile.stale = true);
            }
        });
    }

    /// Drops a reference to each brick; bricks nobody references leave the map, and every
    /// tile's messages in them go too (as if they had never been allocated; those tiles are
    /// marked stale).
    fn release_bricks(&mut self, bricks: &[BrickKey]) {
        let mut freed = FxHashSet::default();
        for b in bricks {
            if let Some(refs) = self.brick_refs.get_mut(b) {
                *refs -= 1;
                if *refs == 0 {
                    self.brick_refs.remove(b);
                    freed.insert(*b);
                }
            }
        }
        if freed.is_empty() {
            return;
        }
        let list: Vec<BrickKey> = freed.iter().copied().collect();
        self.sums.remove_bricks(&list);
        self.logged.remove_bricks(&list);
        self.stamps.retain(|b, _| !freed.contains(b));
        self.keyframes.par_iter_mut().flat_map(|k| &mut k.tiles).for_each(|tile| {
            tile.drop_bricks(&freed);
        });
    }

    /// The bricks keyframe `kf` allocates.
    fn allocation_of(&self, kf: &Keyframe) -> Vec<BrickKey> {
        let r = self.resolution();
        let rays = FrameRays::new(&kf.frame);
        let full = self.params.allocation == Allocation::Full;
        let limits = self.limits;
        let mut bricks: Vec<BrickKey> = (0..rays.rows())
            .into_par_iter()
            .fold(FxHashSet::default, |mut out: FxHashSet<BrickKey>, v| {
                // Neighbouring pixels' depth points often share a voxel: its bricks once.
                let mut last = None;
                for ray in rays.row(v) {
                    let Some(seg) = limits.forward_model_segment(&ray, &kf.noise) else { continue };
                    if seg.hits_surface {
                        // Bricks of the voxels within one voxel of the depth point: one to
                        // eight (the same brick unless the voxel is on a brick's face).
                        let k = VoxelKey::from_point(FrameRays::endpoint(&ray), r);
                        if last != Some(k) {
                            last = Some(k);
                            let lo = VoxelKey(k.0.map(|i| i - 1)).brick().0;
                            let hi = VoxelKey(k.0.map(|i| i + 1)).brick().0;
                            for z in lo[2]..=hi[2] {
                                for y in lo[1]..=hi[1] {
                                    for x in lo[0]..=hi[0] {
                                        out.insert(BrickKey([x, y, z]));
                                    }
                                }
                            }
                        }
                    }
                    if full {
                        let edge = r * BRICK_EDGE as f64;
                        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, edge, |c| {
                            out.insert(BrickKey(c.key.0));
                            ControlFlow::Continue(())
                        });
                    }
                }
                out
            })
            .reduce(FxHashSet::default, |mut a, b| {
                a.extend(b);
                a
            })
            .into_iter()
            .collect();
        bricks.sort_unstable();
        bricks
    }

    /// The pixel stride of tile `cols` x `rows` of `kf`: the largest power of two up to
    /// [`MAX_STRIDE`] whose rays, at the tile's nearest depth, lie at most
    /// [`MrfParams::ray_spacing`] voxel edges apart (1 with `ray_spacing` 0).
    fn tile_stride(&self, kf: &Keyframe, cols: &std::ops::Range<u32>, rows: &std::ops::Range<u32>) -> u32 {
        let spacing = self.params.ray_spacing * self.resolution();
        if spacing <= 0.0 {
            return 1;
        }
        let mut z_min = f32::INFINITY;
        for v in rows.clone() {
            for u in cols.clone() {
                if let Some(z) = kf.frame.depth.get(u, v) {
                    z_min = z_min.min(z);
                }
            }
        }
        // Pixel pitch at depth z: z / f (the camera's larger focal length, its finer pitch).
        let f = kf.frame.camera.fx.abs().max(kf.frame.camera.fy.abs());
        let mut stride = 1;
        while stride < MAX_STRIDE && (2 * stride) as f64 * z_min as f64 / f <= spacing {
            stride *= 2;
        }
        stride
    }

    /// The tiles of keyframe `i` that [`MrfEngine::run_until`] re-traces: stale ones, those
    /// whose last update damping held back by more than `tolerance`, and those a voxel of
    /// which moved by more than `tolerance` (marginal) since the tile saw it, or left the map.
    fn dirty_tiles(&mut self, i: usize, tolerance: f64) -> Vec<usize> {
        let recent = self.mark_suspects(i);
        let (kf, sums, stamps) = (&self.keyframes[i], &self.sums, &self.stamps);
        let dirty = (0..kf.tiles.len())
            .into_par_iter()
            .filter(|&t| {
                let tile = &kf.tiles[t];
                tile.stale
                    || tile.held_back as f64 > tolerance
                    || (tile.suspect
                        && largest_move(sums, stamps, tile, recent.as_ref(), tolerance, tolerance) > tolerance)
            })
            .collect();
        self.keyframes[i].tiles.iter_mut().for_each(|t| t.suspect = false);
        dirty
    }

    /// Logs changes finely enough for `tolerance`: if they were logged more coarsely, every
    /// tile is checked once.
    fn use_tolerance(&mut self, tolerance: f64) {
        if tolerance / 4.0 < self.log_threshold {
            self.log_threshold = tolerance / 4.0;
            self.log.clear();
            self.log_floor = self.epoch + 1;
        }
    }

    /// Marks `suspect` the tiles of keyframe `i` that a brick logged since the keyframe's last
    /// check may reach, and records the check. Returns those bricks, or `None` when the log
    /// was dropped since (then every tile is suspect and the brick stamps tell what changed).
    fn mark_suspects(&mut self, i: usize) -> Option<FxHashSet<BrickKey>> {
        let edge = self.resolution() * BRICK_EDGE as f64;
        let since = self.keyframes[i].checked_at;
        let kf = &mut self.keyframes[i];
        kf.checked_at = self.epoch;
        if since < self.log_floor {
            kf.tiles.iter_mut().for_each(|t| t.suspect = true);
            return None;
        }
        // The bricks logged since the keyframe's last check: a small table, where the stamps
        // of every brick are a large one.
        let start = self.log.partition_point(|&(e, _)| e <= since);
        let bricks: FxHashSet<BrickKey> = self.log[start..].iter().map(|x| x.1).collect();
        let to_camera = kf.to_camera();
        for &b in &bricks {
            kf.for_tiles_reaching(&to_camera, b, edge, |t| t.suspect = true);
        }
        Some(bricks)
    }

    /// Drops the log entries that every keyframe has checked.
    fn trim_log(&mut self) {
        let checked = self.keyframes.iter().map(|k| k.checked_at).min().unwrap_or(self.epoch);
        let seen = self.log.partition_point(|&(e, _)| e <= checked);
        self.log.drain(..seen);
    }

    /// Traces tiles `tiles` (ascending) of keyframe `i` against the current sums, then
    /// replaces their messages in the sums in tile order.
    fn update_tiles(&mut self, i: usize, tiles: &[usize]) -> RunReport {
        let mut report = RunReport::default();
        if tiles.is_empty() {
            return report;
        }
        report.keyframe_updates = 1;
        report.tiles = tiles.len();
        // All traced against the same sums, then applied in tile order: the same sums
        // whatever the number of threads. (Held at once: a keyframe's new tiles with a change
        // per entry, 14 bytes per entry on top of what its tiles already hold.)
        let kf = &self.keyframes[i];
        let rays = FrameRays::new(&kf.frame);
        let pending: Vec<Traced> = tiles
            .par_iter()
            .map_init(TileScratch::default, |scratch, &t| self.trace_tile(kf, &rays, t, scratch))
            .collect();
        self.epoch += 1;
        for mut tr in pending {
            report.rays += tr.rays;
            for n in 0..tr.tile.runs.len() {
                let start = tr.tile.runs[n].1 as usize;
                let run = tr.tile.run(n).iter().zip(&tr.changes[start..]);
                self.apply_run(tr.tile.runs[n].0, run.map(|(e, d)| (e.slot(), *d)));
            }
            self.apply(&tr.gone);
            tr.tile.traced_at = self.epoch;
            self.keyframes[i].tiles[tr.index] = tr.tile;
        }
        report
    }

    /// Traces tile `t` of keyframe `kf`: every ray with its cavities, and the tile's new
    /// entries (damped against its old ones) and the changes they make to the sums.
    fn trace_tile<'a>(
        &'a self,
        kf: &Keyframe,
        rays: &FrameRays<'_>,
        t: usize,
        scratch: &mut TileScratch<'a>,
    ) -> Traced {
        let tile = &kf.tiles[t];
        let r = self.resolution();
        let inv_r = 1.0 / r;
        // The tile's voxels: old ones first (their message per metre is the rays' own share).
        scratch.clear();
        for (key, e) in tile.iter() {
            scratch.voxel(key, Some(*e), &self.sums);
        }
        let (cols, rows) = kf.tile_pixels(t);
        let (mut z_max, mut traced) = (0.0f64, 0usize);
        let edge = r * BRICK_EDGE as f64;
        let depth = &kf.frame.depth;
        let stride = self.tile_stride(kf, &cols, &rows);
        for v0 in rows.clone().step_by(stride as usize) {
            for u0 in cols.clone().step_by(stride as usize) {
                // One ray, of the first valid pixel, stands for the valid pixels of its
                // stride x stride block.
                let mut valid = (v0..(v0 + stride).min(rows.end))
                    .flat_map(|v| (u0..(u0 + stride).min(cols.end)).map(move |u| (u, v)))
                    .filter(|&(u, v)| depth.get(u, v).is_some());
                let Some((u, v)) = valid.next() else { continue };
                let weight = 1.0 + valid.count() as f64;
                let Some(ray) = rays.ray(u, v) else { continue };
                let Some(seg) = self.limits.forward_model_segment(&ray, &kf.noise) else { continue };
                traced += 1;
                z_max = z_max.max(seg.end * ray.cz);
                let measured = ray.range * ray.cz;
                let mut likelihood = kf.noise.along_ray(ray.u, ray.v, measured);
                scratch.ray.clear();
                // Voxels before the first one with any likelihood (the free stretch, about
                // 40% of a ray's voxels at 0.02 m) get the message 0 whatever anyone's belief:
                // a surface there would make the reading impossible. Nor does their belief
                // reach the other voxels' messages (`ray_messages`'s prefix stays 0 through
                // them). So they need no cavity and no place in the ray's factor.
                let mut window = false;
                for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, edge, |b| {
                    let key = BrickKey(b.key.0);
                    let Some((table, Some(sums))) = scratch.table_of(key, &self.sums) else {
                        return ControlFlow::Continue(()); // unallocated: skipped, as the reference does
                    };
                    for_each_crossing(ray.origin, ray.dir, b.s_in, b.s_out, r, |c| {
                        // (A voxel of another brick: rounding at a brick face.)
                        let inside = c.key.brick() == key;
                        let s = if inside { sums.get(c.key.slot()) } else { self.sums.get(c.key) };
                        if let Some(&s) = s {
                            let length = c.length();
                            let slot = if inside {
                                scratch.voxel_in(table, c.key, None)
                            } else {
                                scratch.voxel(c.key, None, &self.sums)
                            };
                            let voxel = &mut scratch.voxels[slot];
                            voxel.seen = s;
                            let nu = likelihood.over(c.s_in * ray.cz, c.s_out * ray.cz);
                            window |= nu > 0.0;
                            if window {
                                // The cavity: everything the voxel heard except this ray's own
                                // message. (Clamped where `ray_messages` clamps anyway: exp
                                // overflow is slow.)
                                let cavity =
                                    sigmoid(((s - voxel.own * (length * inv_r) as f32) as f64).clamp(-40.0, 40.0));
                                scratch.ray.push(slot, length, cavity, nu);
                            } else {
                                scratch.ray.free.push((slot, length));
                            }
                        }
                        ControlFlow::Continue(())
                    });
                    ControlFlow::Continue(())
                });
                if scratch.ray.slots.is_empty() && scratch.ray.free.is_empty() {
                    continue;
                }
                // The chance the surface lies past the segment (outside the map where the
                // bounds cut the ray short).
                let beyond = seg.beyond(&ray, &kf.noise, &mut likelihood, r);
                let ray_buf = &mut scratch.ray;
                // The free stretch's message: 0 (clamped), unless the ray has no likelihood
                // anywhere, beyond included, and says nothing (1/2).
                let free = if window || beyond > 0.0 { logit(MSG_EPS) } else { 0.0 };
                for &(slot, l) in &ray_buf.free {
                    let voxel = &mut scratch.voxels[slot];
                    voxel.length += weight * l * inv_r;
                    voxel.sum += weight * l * inv_r * free;
                }
                ray_messages(&ray_buf.mu, &ray_buf.nu, beyond, &mut ray_buf.out);
                for j in 0..ray_buf.slots.len() {
                    let l = ray_buf.length[j];
                    let voxel = &mut scratch.voxels[ray_buf.slots[j]];
                    voxel.length += weight * l * inv_r;
                    voxel.sum += weight * l * inv_r * logit(ray_buf.out[j].clamp(MSG_EPS, 1.0 - MSG_EPS));
                }
            }
        }
        // New entries, damped in log-odds: part of the old message stays (a tile's first
        // message to a voxel goes in whole). A message whose change reverses direction from
        // one trace to the next is oscillating (voxels competing for one surface can cycle
        // under any fixed damping): the share of its change that goes in is halved, and
        // doubled back after `CALM_TRACES` traces in a row without a reversal (after one, a
        // period-four cycle, two reversals in four traces, was never damped). Damping changes
        // how a fixed point is approached, not where it is. Voxels its rays no longer reach
        // lose its message.
        let keep = self.params.damping;
        // The new tile by brick and slot, with each entry's change of the sum; voxels no ray
        // reaches any more lose the tile's message (`gone`, rare, in the same order, applied
        // after).
        let mut new = Tile { z_max: z_max as f32, ..Tile::default() };
        new.entries.reserve_exact(scratch.voxels.len());
        let mut changes = Vec::with_capacity(scratch.voxels.len());
        let mut gone = Vec::new();
        for i in scratch.sorted() {
            let voxel = &scratch.voxels[i];
            let old = voxel.old.map_or(0.0, |e| e.message());
            if voxel.length > 0.0 {
                let mut entry = Entry::new(voxel.key.slot());
                entry.set_edges(voxel.length);
                entry.set_seen(voxel.seen);
                match voxel.old {
                    Some(e) => {
                        let change = voxel.sum - e.message() as f64;
                        let (level, calm) = if change * e.step_sign() < 0.0 {
                            ((e.level() + 1).min(MAX_DAMPING_LEVEL), 0)
                        } else if e.calm() + 1 >= CALM_TRACES {
                            (e.level().saturating_sub(1), 0)
                        } else {
                            (e.level(), e.calm() + 1)
                        };
                        let step = (1.0 - keep) * change / (1u32 << level) as f64;
                        entry.set_message((e.message() as f64 + step) as f32);
                        entry.set_damping(level, calm, step);
                        if step != change {
                            // The voxel's `S` after this update, and where the whole step would take it.
                            let after = voxel.seen as f64 + step;
                            let rest = (sigmoid(after + change - step) - sigmoid(after)).abs();
                            new.held_back = new.held_back.max(rest as f32);
                        }
                    }
                    None => entry.set_message(voxel.sum as f32),
                }
                new.push(voxel.key, entry);
                changes.push(entry.message() - old);
            } else if old != 0.0 {
                gone.push((voxel.key, -old));
            }
        }
        new.entries.shrink_to_fit(); // (voxels no longer reached leave room)
        new.runs.shrink_to_fit();
        Traced { index: t, tile: new, changes, gone, rays: traced }
    }
}

/// The largest marginal move, since `tile` traced, of a voxel its rays reach, or 1 when one
/// left the map. Only bricks that some update changed since the trace are read: those in
/// `recent` (every brick logged since the tile's keyframe was last checked; the tile traced
/// after that check or in the update just before it), else those stamped since. Moves up to
/// `floor` are not measured (0 is returned when there are only such), and it stops early
/// once the move exceeds `enough`.
fn largest_move(
    sums: &Grid<f32>,
    stamps: &FxHashMap<BrickKey, u64>,
    tile: &Tile,
    recent: Option<&FxHashSet<BrickKey>>,
    floor: f64,
    enough: f64,
) -> f64 {
    let mut largest = 0.0f64;
    for (n, &(bk, _)) in tile.runs.iter().enumerate() {
        let changed = match recent {
            Some(r) => r.contains(&bk),
            None => stamps.get(&bk).is_some_and(|&e| e >= tile.traced_at),
        };
        if !changed {
            continue;
        }
        let Some(brick) = sums.brick(bk) else { return 1.0 };
        for e in tile.run(n) {
            let Some(&s) = brick.get(e.slot()) else { return 1.0 };
            // |d sigmoid| <= |dS| / 4: the exponentials only for changes that may matter.
            let seen = e.seen();
            if (s - seen).abs() as f64 > 4.0 * largest.max(floor) {
                largest = largest.max((sigmoid(s as f64) - sigmoid(seen as f64)).abs());
                if largest > enough {
                    return largest;
                }
            }
        }
    }
    largest
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

/// A voxel a tile's rays reach, while the tile is traced.
#[derive(Clone, Copy)]
struct VoxelAcc {
    key: VoxelKey,
    /// The tile's old message per voxel edge of length (a ray's own share per edge of it).
    own: f32,
    /// The tile's old entry, if it had one.
    old: Option<Entry>,
    /// `S` as traced.
    seen: f32,
    /// Summed lengths (voxel edges) and length-weighted log-odds messages of this trace.
    length: f64,
    sum: f64,
}

/// Per-tile buffers, reused across the tiles a thread traces.
struct TileScratch<'a> {
    voxels: Vec<VoxelAcc>,
    /// Per brick the tile's rays cross, its index in `tables` ([`UNALLOCATED`] for none).
    /// A tile's rays cross mostly the same bricks: this small table answers where the map's
    /// large one cost a cache miss per brick of every ray (13% of a trace).
    bricks: FxHashMap<BrickKey, u32>,
    /// A direct-mapped cache in front of `bricks` (key, value), by a hash of the key. At
    /// 0.01 m a ray crosses dozens of bricks and a tile's rays share most of them: probing
    /// `bricks` for each was a fifth of a trace's profile.
    recent: Box<[(BrickKey, u32); RECENT]>,
    /// The first `used` are in use (the rest are kept for reuse).
    tables: Vec<SlotTable<'a>>,
    used: usize,
    ray: RayScratch,
}

/// [`TileScratch::bricks`] value of a brick that is not allocated.
const UNALLOCATED: u32 = u32::MAX;

/// Entries of [`TileScratch::recent`] (a power of two).
const RECENT: usize = 512;

/// A [`TileScratch::recent`] entry holding no brick (a brick coordinate is an `i32` voxel
/// coordinate `>> 3`, never `i32::MIN`).
const NO_BRICK: BrickKey = BrickKey([i32::MIN; 3]);

/// [`TileScratch::recent`]'s slot of brick `key`.
#[inline]
fn recent_slot(key: BrickKey) -> usize {
    let [x, y, z] = key.0.map(|c| c as u32);
    let h = x.wrapping_mul(0x9E37_79B1) ^ y.wrapping_mul(0x85EB_CA77) ^ z.wrapping_mul(0xC2B2_AE3D);
    (h >> (32 - RECENT.trailing_zeros())) as usize
}

/// One brick's voxels among a tile's: its sums, per slot the index in
/// [`TileScratch::voxels`] (`u32::MAX` for none), and which slots are set. A ray is traced
/// brick by brick, so its voxels are found by one brick lookup and array indexing (a hash
/// lookup per voxel was a tenth of a trace, and sorting the voxels afterwards another 7%).
struct SlotTable<'a> {
    key: BrickKey,
    sums: Option<&'a Brick<f32>>,
    index: Box<[u32; BRICK_VOXELS]>,
    set: SlotMask,
}

impl Default for TileScratch<'_> {
    fn default() -> Self {
        TileScratch {
            voxels: Vec::new(),
            bricks: FxHashMap::default(),
            recent: Box::new([(NO_BRICK, 0); RECENT]),
            tables: Vec::new(),
            used: 0,
            ray: RayScratch::default(),
        }
    }
}

impl<'a> TileScratch<'a> {
    fn clear(&mut self) {
        for table in &mut self.tables[..self.used] {
            for slot in mask_slots(&table.set) {
                table.index[slot] = u32::MAX;
            }
            table.set = [0; 8];
        }
        self.used = 0;
        self.bricks.clear();
        self.recent.fill((NO_BRICK, 0));
        self.voxels.clear();
        self.ray.clear();
    }

    /// The table of brick `key` with its sums in `grid`, `None` if the brick is not allocated
    /// (and has no table).
    #[inline]
    fn table_of(&mut self, key: BrickKey, grid: &'a Grid<f32>) -> Option<(usize, Option<&'a Brick<f32>>)> {
        let slot = recent_slot(key);
        let t = match self.recent[slot] {
            (k, t) if k == key => t,
            _ => match self.bricks.get(&key) {
                Some(&t) => {
                    self.recent[slot] = (key, t);
                    t
                }
                None => {
                    let t = match grid.brick(key) {
                        Some(sums) => self.add_table(key, Some(sums)),
                        None => UNALLOCATED,
                    };
                    self.remember(key, t);
                    t
                }
            },
        };
        (t != UNALLOCATED).then(|| (t as usize, self.tables[t as usize].sums))
    }

    /// Records brick `key`'s table index `t` (or [`UNALLOCATED`]).
    fn remember(&mut self, key: BrickKey, t: u32) {
        self.bricks.insert(key, t);
        self.recent[recent_slot(key)] = (key, t);
    }

    fn add_table(&mut self, key: BrickKey, sums: Option<&'a Brick<f32>>) -> u32 {
        if self.used == self.tables.len() {
            self.tables.push(SlotTable { key, sums, index: Box::new([u32::MAX; BRICK_VOXELS]), set: [0; 8] });
        }
        let table = &mut self.tables[self.used];
        (table.key, table.sums) = (key, sums);
        self.used += 1;
        (self.used - 1) as u32
    }

    /// The index of voxel `key`, added with the tile's `old` entry if new (with a table for
    /// its brick even if `grid` no longer holds it: the old message must still go).
    #[inline]
    fn voxel(&mut self, key: VoxelKey, old: Option<Entry>, grid: &'a Grid<f32>) -> usize {
        let t = match self.table_of(key.brick(), grid) {
            Some((t, _)) => t,
            None => {
                let t = self.add_table(key.brick(), None);
                self.remember(key.brick(), t);
                t as usize
            }
        };
        self.voxel_in(t, key, old)
    }

    /// [`TileScratch::voxel`] for a voxel of table `t`'s brick.
    #[inline]
    fn voxel_in(&mut self, t: usize, key: VoxelKey, old: Option<Entry>) -> usize {
        let table = &mut self.tables[t];
        let slot = key.slot();
        let i = table.index[slot];
        if i != u32::MAX {
            return i as usize;
        }
        let own = old.map_or(0.0, |e| if e.length > 0 { e.message() / e.edges() } else { 0.0 });
        let i = self.voxels.len();
        table.index[slot] = i as u32;
        mask_set(&mut table.set, slot);
        self.voxels.push(VoxelAcc { key, own, old, seen: 0.0, length: 0.0, sum: 0.0 });
        i
    }

    /// The voxels' indices by brick, then slot.
    fn sorted(&self) -> impl Iterator<Item = usize> + '_ {
        let mut order: Vec<&SlotTable> = self.tables[..self.used].iter().collect();
        order.sort_unstable_by_key(|t| t.key);
        order.into_iter().flat_map(|t| mask_slots(&t.set).map(|slot| t.index[slot] as usize))
    }
}

/// Per-ray buffers.
#[derive(Default)]
struct RayScratch {
    /// The free stretch's voxels (slot, length), before the first with any likelihood.
    free: Vec<(usize, f64)>,
    slots: Vec<usize>,
    length: Vec<f64>,
    mu: Vec<f64>,
    nu: Vec<f64>,
    out: Vec<f64>,
}

impl RayScratch {
    fn clear(&mut self) {
        self.free.clear();
        self.slots.clear();
        self.length.clear();
        self.mu.clear();
        self.nu.clear();
    }

    fn push(&mut self, slot: usize, length: f64, mu: f64, nu: f64) {
        self.slots.push(slot);
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
                Some(_) if r.converged => ", converged",
                Some(_) => ", not converged (sweep cap)",
                None => "",
            }
        );
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

    /// Every field of a packed entry reads back what was written, whatever its neighbours
    /// hold: messages bit for bit (removal subtracts exactly what went in), every damping state.
    #[test]
    fn entries_keep_every_field() {
        let mut rng = crate::random::Rng::new(13);
        for n in 0..2000 {
            let slot = n % BRICK_VOXELS;
            let mut e = Entry::new(slot);
            assert_eq!((e.level(), e.calm(), e.step_sign()), (0, 0, 0.0));
            let m = (rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-8.0, 4.0))) as f32;
            e.set_message(m);
            e.set_edges(rng.range(0.0, 500.0));
            e.set_seen(rng.range(-40.0, 40.0) as f32);
            let (edges, seen) = (e.edges(), e.seen());
            let level = (n % (MAX_DAMPING_LEVEL as usize + 1)) as u8;
            let calm = (n / 9 % CALM_TRACES as usize) as u8;
            let step = [1.5, -0.25, 0.0][n / 27 % 3];
            e.set_damping(level, calm, step);
            assert_eq!(e.message().to_bits(), m.to_bits());
            assert_eq!(e.slot(), slot);
            assert_eq!((e.level(), e.calm(), e.step_sign()), (level, calm, step.signum() * (step != 0.0) as u8 as f64));
            assert_eq!((e.edges(), e.seen()), (edges, seen));
        }
    }

    /// A floor and a box seen by `views` cameras on a circle.
    pub(super) fn test_scene(views: usize) -> Scene {
        let toml = format!(
            "[camera]\nfx = 60.0\nfy = 60.0\ncx = 39.5\ncy = 29.5\nwidth = 80\nheight = 60\ndepth_scale = 5000.0\n\
             [[box]]\nmin = [-2.0, -2.0, -0.1]\nmax = [2.0, 2.0, 0.0]\n[[box]]\nmin = [-0.3, -0.3, 0.0]\nmax = [0.3, 0.3, 0.6]\n\
             [orbit]\ncenter = [0.0, 0.0, 0.3]\nradius = 2.0\nheight = 1.3\nviews = {views}\n"
        );
        Scene::from_toml(&toml, "t.toml".as_ref()).unwrap()
    }

    /// Rays only go forward: a brick wholly behind a camera reaches none of its tiles, one it
    /// looks at reaches some.
    #[test]
    fn bricks_behind_a_camera_reach_no_tile() {
        let scene = test_scene(1);
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        e.add_keyframe(scene.frame(0, &scene.views[0], Some(1))).unwrap();
        e.run(1);
        let edge = 0.05 * BRICK_EDGE as f64;
        let kf = &mut e.keyframes[0];
        let to_camera = kf.to_camera();
        let origin = to_camera.1;
        // The scene's centre, and a point as far behind the camera.
        let ahead = [0.0, 0.0, 0.3];
        let behind: Vec<f64> = (0..3).map(|a| 2.0 * origin[a] - ahead[a]).collect();
        let brick = |p: &[f64]| VoxelKey::from_point([p[0], p[1], p[2]], 0.05).brick();
        let mut reached = |p: &[f64]| {
            let mut n = 0;
            kf.for_tiles_reaching(&to_camera, brick(p), edge, |_| n += 1);
            n
        };
        assert!(reached(&ahead) > 0);
        assert_eq!(reached(&behind), 0);
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

    /// After change-driven inference has converged, checking every tile of every keyframe
    /// against every brick (not only those the change log projects onto it) finds no voxel
    /// moved by more than the 1.5 tolerances that `apply` guarantees: the log and the
    /// projection missed nothing, through adds, removals and re-poses.
    #[test]
    fn change_log_misses_no_dirty_tile() {
        let scene = test_scene(5);
        let frames: Vec<Frame> =
            scene.views.iter().enumerate().map(|(i, p)| scene.frame(i, p, Some(i as u64))).collect();
        let tol = 1e-3;
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        let check = |e: &mut MrfEngine, what: &str| {
            let r = e.run_until(tol, 500);
            assert!(r.converged, "{what}: {r:?}");
            for v in e.stamps.values_mut() {
                *v = u64::MAX; // every brick counts as changed
            }
            for (k, kf) in e.keyframes.iter().enumerate() {
                for (t, tile) in kf.tiles.iter().enumerate() {
                    let moved = largest_move(&e.sums, &e.stamps, tile, None, 0.0, 1.0);
                    assert!(moved <= 1.5 * tol, "{what}: keyframe {k} tile {t} left dirty ({moved})");
                }
            }
        };
        for f in &frames[..4] {
            e.add_keyframe(f.clone()).unwrap();
        }
        check(&mut e, "build");
        let id = e.add_keyframe(frames[4].clone()).unwrap();
        check(&mut e, "add");
        e.remove_keyframe(e.keyframe_ids()[0]).unwrap();
        check(&mut e, "remove");
        let moved = Pose::new([0.0, 0.2, 0.0].into(), [0.0, 0.0, 0.1].into()) * frames[4].pose;
        e.set_pose(id, moved).unwrap();
        check(&mut e, "re-pose");
    }
}
