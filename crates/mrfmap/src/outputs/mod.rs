//! Outputs: what leaves the library — exported files for viewers and other tools.
//!
//! [`write_ply`] writes voxel centres with occupancy (and variance); [`read_ply`] reads
//! such files back (ASCII or binary) for checks and round trips.

mod ply;

pub use ply::{PlyOptions, PlyVertices, read_ply, write_ply};
