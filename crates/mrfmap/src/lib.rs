//! # mrfmap
//!
//! Probabilistic 3D occupancy mapping from depth cameras with forward sensor models.
//!
//! The modules follow the data's path:
//!
//! - [`source`]: where frames come from — TUM / ICL-NUIM datasets, the scene simulator and
//!   planar cell worlds with a simulated range scanner;
//! - [`frames`]: one reading — depth image or range scan, camera, pose, noise model (and its
//!   calibration from image pairs);
//! - [`rays`]: pixel and beam rays, exact voxel traversal, and the crossed voxels of a whole
//!   depth image found by projection;
//! - [`inference`]: the engines (log-odds, MRF, CRM) behind one [`inference::Engine`] trait;
//! - [`map`]: the sparse bricked voxel grid and the finished [`map::Map`] with its file format;
//! - [`outputs`]: exports (PLY, OctoMap), the accuracy metric, ground-truth metrics and
//!   pictures;
//! - [`pipeline`]: the loop that runs a source's readings through an engine into a map, which
//!   the command line and Python share.
//!
//! ```no_run
//! use mrfmap::inference::{EngineConfig, EngineKind, new_engine};
//! use mrfmap::source::Dataset;
//!
//! let dataset = Dataset::open("../shared/data/icl-livingroom-5".as_ref())?;
//! let mut engine = new_engine(&EngineConfig::new(EngineKind::LogOdds, 0.05))?;
//! for i in 0..dataset.len() {
//!     engine.integrate(&dataset.frame(i)?)?;
//! }
//! let map = engine.map();
//! println!("{} occupied voxels", map.occupied_count());
//! map.save("room.mrfmap".as_ref())?;
//! # Ok::<(), mrfmap::Error>(())
//! ```
#![warn(missing_docs)]
// `!(x > 0.0)` also rejects NaN, which is the point wherever it is used to validate input.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod atomic_file;

mod choice;
mod error;
pub mod frames;
pub mod inference;
pub mod limits;
pub mod map;
pub mod outputs;
pub mod pipeline;
pub mod placement;
pub mod random;
pub mod rays;
pub mod source;
mod vecmath;

pub use choice::Choice;
pub use error::{Error, Result};
