//! Sources: where frames come from — datasets on disk and the analytic scene simulator.
//!
//! [`Dataset`] reads the TUM / ICL-NUIM layout; [`Scene`] describes an analytic world and
//! [`simulate`] renders it into that same layout, so simulated and real data take one path.
//! [`GridWorld`] is a planar world of cells with a simulated range scanner, for 2D
//! experiments (it produces [`crate::frames::RangeScan`]s, not depth images). [`CarmenLog`]
//! reads real planar-laser logs (CARMEN format, plain or gzip) into range scans.
//! [`DepthNoise`] makes clean depth noisy the way a real depth camera would (`mrfmap add-noise`).

#[cfg(feature = "bags")]
pub mod bag;
mod carmen;
mod dataset;
mod depth_noise;
mod depth_png;
mod grid_world;
mod scene;
mod simulate;

pub use carmen::{BeamSpacing, CarmenLog, CarmenOptions, LaserReading, Misses, parse_carmen};
pub use dataset::{Dataset, DatasetOptions, FrameCache, FrameInfo};
pub use depth_noise::{DepthNoise, NoiseStatistics, StructuredLight, noise_statistics};
pub use depth_png::{decode_depth_png, quantise_depth, read_depth_png, write_depth_png};
pub use grid_world::GridWorld;
pub use scene::{Scene, Shape};
pub use simulate::{DatasetWriter, NoisySummary, SimulationSummary, add_noise, simulate};
