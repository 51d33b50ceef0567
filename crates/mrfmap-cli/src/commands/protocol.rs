//! Experiment protocols (`loo --protocol`, `compare --protocol`): the models a leave-one-out
//! experiment builds its maps with and the depth it scores them against. MRFMap's Table I
//! is reported under both (RESULTS.md): ours, and the reference implementation's as its
//! public configuration for coffin-world sets it up.

use std::borrow::Cow;
use std::sync::Arc;

use mrfmap::frames::{Frame, NoiseModel, Poly};

use super::options::MapOptions;
use super::views::Target;

/// An experiment protocol.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Protocol {
    /// Ours: the engines use the dataset's noise model (the learnt per-patch bias and std);
    /// held-out views are scored against their true depth (`gt_depth/`).
    Truth,
    /// The MRFMap reference implementation's coffin-world runs (mrfmap_ros,
    /// `config/coffin_world_640.yaml`): no bias, a constant std of 0.05 m whose likelihood is
    /// three times as wide; log-odds clamped to [0.0001, 0.9999]; held-out views scored
    /// against `gt_depth/` plus the dataset model's bias (noise-free but biased).
    Reference,
}

/// The reference protocol's constant std (m).
const REFERENCE_STD: f64 = 0.05;
/// How much wider than [`REFERENCE_STD`] the reference protocol's likelihood is.
const REFERENCE_LIKELIHOOD_SCALE: f64 = 3.0;
/// The reference protocol's log-odds clamping thresholds.
const REFERENCE_CLAMP: (f64, f64) = (1e-4, 0.9999);

impl Protocol {
    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Truth => "truth",
            Protocol::Reference => "reference",
        }
    }

    /// What held-out views are scored against.
    pub fn target(self) -> Target {
        match self {
            Protocol::Truth => Target::Truth,
            Protocol::Reference => Target::Biased,
        }
    }

    /// The noise model the engines use under this protocol (`None`: each frame's own).
    pub fn noise(self) -> Option<NoiseModel> {
        match self {
            Protocol::Truth => None,
            Protocol::Reference => Some(NoiseModel {
                likelihood_scale: REFERENCE_LIKELIHOOD_SCALE,
                ..NoiseModel::aggregate(Poly([0.0; 3]), Poly([REFERENCE_STD, 0.0, 0.0]))
            }),
        }
    }

    /// `frames` with this protocol's noise model (the frames themselves when it keeps theirs).
    pub fn frames(self, frames: &[Frame]) -> Cow<'_, [Frame]> {
        match self.noise().map(Arc::new) {
            None => Cow::Borrowed(frames),
            Some(noise) => {
                Cow::Owned(frames.iter().map(|f| Frame { noise: Some(noise.clone()), ..f.clone() }).collect())
            }
        }
    }

    /// `options` with this protocol's log-odds clamp (where the user gave none).
    pub fn options(self, options: &MapOptions) -> MapOptions {
        let mut o = options.clone();
        if self == Protocol::Reference {
            o.clamp = o.clamp.or(Some(REFERENCE_CLAMP));
        }
        o
    }
}
