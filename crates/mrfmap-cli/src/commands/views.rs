//! Posed depth views to build maps from and score them on: a dataset folder's, or a ROS bag's
//! (what `eval`, `loo` and `compare` take). A dataset scores against its `gt_depth/` when it
//! has one; a bag, like a dataset without one, against its own depth images.

use std::path::Path;

use anyhow::Result;
use mrfmap::frames::{Camera, DepthImage, Frame, Pose};
use mrfmap::source::Dataset;

use super::build::BagArgs;

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

    /// The depth view `i` is scored against: `gt_depth/` when the dataset has it, else the
    /// view's own (noisy) depth.
    pub fn held_out_depth(&self, i: usize) -> Result<DepthImage> {
        match self {
            Views::Dataset(d) => match d.truth_depth(i)? {
                Some(truth) => Ok(truth),
                None => {
                    tracing::warn!("{}: no gt_depth/, scoring against the noisy depth/ images", d.root().display());
                    Ok(d.frame(i)?.depth)
                }
            },
            Views::Bag(f) => Ok(f[i].depth.clone()),
        }
    }
}
