//! Posed depth views to build maps from and score them on: a dataset folder's, or a ROS bag's
//! (what `eval`, `loo` and `compare` take). A dataset scores against its `gt_depth/` when it
//! has one; a bag, like a dataset without one, against its own depth images.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use mrfmap::frames::{Camera, DepthImage, Frame, NoiseModel, Pose};
use mrfmap::source::Dataset;

use super::options::BagArgs;

/// A dataset, or a bag's frames read once.
pub enum Views {
    /// A dataset folder (frames read when asked).
    Dataset(Dataset),
    /// A bag's posed depth frames.
    Bag(Vec<Frame>),
}

impl Views {
    /// Opens `path` as a bag (`BagArgs::is_bag`) or a dataset, with `noise` replacing the
    /// dataset's model when given.
    pub fn open(path: &Path, noise: Option<&Path>, bag: &BagArgs) -> Result<Self> {
        if BagArgs::is_bag(path) {
            return Ok(Views::Bag(bag.frames(path, noise)?));
        }
        let mut dataset = Dataset::open(path)?;
        if let Some(n) = noise {
            dataset.set_noise_file(n)?;
        }
        Ok(Views::Dataset(dataset))
    }

    /// Number of views.
    pub fn len(&self) -> usize {
        match self {
            Views::Dataset(d) => d.len(),
            Views::Bag(f) => f.len(),
        }
    }

    /// The camera.
    pub fn camera(&self) -> Camera {
        match self {
            Views::Dataset(d) => *d.camera(),
            Views::Bag(f) => f[0].camera,
        }
    }

    /// The dataset's noise model (a bag's: its frames').
    pub fn noise(&self) -> Option<Arc<NoiseModel>> {
        match self {
            Views::Dataset(d) => d.noise().cloned(),
            Views::Bag(f) => f.first().and_then(|f| f.noise.clone()),
        }
    }

    /// Pose of view `i`.
    pub fn pose(&self, i: usize) -> Pose {
        match self {
            Views::Dataset(d) => d.frames()[i].pose,
            Views::Bag(f) => f[i].pose,
        }
    }

    /// Frame `i`.
    pub fn frame(&self, i: usize) -> mrfmap::Result<Frame> {
        match self {
            Views::Dataset(d) => d.frame(i),
            Views::Bag(f) => Ok(f[i].clone()),
        }
    }

    /// Every frame (leave-one-out builds reuse them N times).
    pub fn frames(&self) -> Result<Vec<Frame>> {
        match self {
            Views::Dataset(_) => Ok((0..self.len()).map(|i| self.frame(i)).collect::<mrfmap::Result<Vec<_>>>()?),
            Views::Bag(f) => Ok(f.clone()),
        }
    }

    /// The depth view `i` is scored against. [`Target::Truth`]: `gt_depth/` when the dataset
    /// has it, else the view's own (noisy) depth. [`Target::Biased`]: `gt_depth/` plus the
    /// noise model's bias, what the sensor reads without noise.
    pub fn held_out_depth(&self, i: usize, target: Target) -> Result<DepthImage> {
        let d = match self {
            Views::Dataset(d) => d,
            Views::Bag(f) if target == Target::Truth => return Ok(f[i].depth.clone()),
            Views::Bag(_) => bail!("the biased target needs a dataset with gt_depth/"),
        };
        match (target, d.truth_depth(i)?) {
            (Target::Truth, Some(truth)) => Ok(truth),
            (Target::Biased, Some(truth)) => {
                let noise = d.noise().with_context(|| {
                    format!("{}: no noise.toml (or --noise) to take the biased target's bias from", d.root().display())
                })?;
                Ok(noise.biased(&truth))
            }
            (Target::Biased, None) => bail!("{}: the biased target needs gt_depth/", d.root().display()),
            (Target::Truth, None) => {
                tracing::warn!("{}: no gt_depth/, scoring against the noisy depth/ images", d.root().display());
                Ok(d.frame(i)?.depth)
            }
        }
    }
}

/// What a held-out view is scored against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    /// The true depth (`gt_depth/`; datasets without one: their own depth).
    Truth,
    /// The true depth plus the noise model's bias: what the sensor reads without noise (the
    /// MRFMap reference implementation's coffin-world target).
    Biased,
}
