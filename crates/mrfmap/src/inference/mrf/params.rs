//! The engine's parameters ([`MrfParams`]) and their defaults.

#[cfg(doc)]
use super::MrfEngine;
use crate::Choice;
use crate::frames::{Pose, moved_beyond};
#[cfg(doc)]
use crate::inference::Engine;

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

crate::choice::choice!(Allocation, "allocation", Band => "band", Full => "full");

/// `all`, or `auto` with the default thresholds ([`KeyframeSelection::AUTO`]).
impl Choice for KeyframeSelection {
    const WHAT: &'static str = "keyframe selection";
    const ALL: &'static [Self] = &[KeyframeSelection::All, KeyframeSelection::AUTO];

    fn name(self) -> &'static str {
        match self {
            KeyframeSelection::All => "all",
            KeyframeSelection::Auto { .. } => "auto",
        }
    }
}

impl KeyframeSelection {
    /// `Auto` with the default thresholds.
    pub const AUTO: KeyframeSelection = KeyframeSelection::Auto { translation: 0.2, rotation: 0.2 };

    /// Which of `poses`, integrated in order, become keyframes (their indices).
    ///
    /// ```
    /// use mrfmap::frames::Pose;
    /// use mrfmap::inference::KeyframeSelection;
    /// let poses: Vec<Pose> = (0..10).map(|i| Pose::translation(0.1 * i as f64, 0.0, 0.0)).collect();
    /// assert_eq!(KeyframeSelection::AUTO.keep(&poses), vec![0, 3, 6, 9]);
    /// assert_eq!(KeyframeSelection::All.keep(&poses).len(), 10);
    /// ```
    pub fn keep(&self, poses: &[Pose]) -> Vec<usize> {
        let mut kept: Vec<usize> = Vec::new();
        for (i, pose) in poses.iter().enumerate() {
            let new = match *self {
                KeyframeSelection::All => true,
                KeyframeSelection::Auto { translation, rotation } => {
                    kept.iter().all(|&k| moved_beyond(&poses[k], pose, translation, rotation))
                }
            };
            if new {
                kept.push(i);
            }
        }
        kept
    }
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
    /// hundreds of them sum to a marginal of 0.1-0.3 where the truth is 1 (docs/history/RESULTS.md,
    /// "Weak evidence is unknown"). 0
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

/// Default tolerance of [`MrfEngine::run_until`] on a marginal's change.
pub const DEFAULT_TOLERANCE: f64 = 1e-3;

/// Default sweeps of a batch build ([`MrfParams::default`]): the MRFMap paper's fixed three
/// passes. On coffin-world (views 2, 6 and 9 held out) they score within 0.002 of the
/// change-driven schedule at 0.01 m and 0.005-0.008 above it at 0.02 m, in a third of the time
/// (RESULTS.md, "The online MRF").
pub const DEFAULT_SWEEPS: usize = 3;

/// Default cap on the sweeps of [`MrfEngine::run_until`] (`--tolerance` alone). Adding a
/// keyframe to a converged 60-view map of the demo room mostly reaches it with a few dozen
/// tiles still moving (about 1,900 tiles traced in all, 1,200 of them the new keyframe's); its
/// map is then within 0.02 of the converged one for 99.97% of voxels (docs/history/BENCHMARKS.md,
/// session 7). A whole
/// build may stop further away: a few hundred voxels of coffin-world at 0.02 m kept
/// oscillating for more than 100 sweeps (docs/history/RESULTS.md, "Why the MRF converges slowly").
pub const DEFAULT_MAX_SWEEPS: usize = 10;
