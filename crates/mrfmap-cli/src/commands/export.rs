//! `mrfmap export`: map file to PLY.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::map::Map;
use mrfmap::outputs::{PlyOptions, write_ply};

#[derive(clap::Args)]
pub struct Args {
    /// Map file written by `mrfmap build`.
    map: PathBuf,
    /// Write a binary PLY of voxel centres with occupancy (and variance).
    #[arg(long, required = true)]
    ply: PathBuf,
    /// Only voxels with occupancy above 0.5.
    #[arg(long)]
    occupied_only: bool,
}

pub fn run(a: Args) -> Result<()> {
    let map = Map::load(&a.map)?;
    let options = if a.occupied_only { PlyOptions::occupied_only() } else { PlyOptions { min_occupancy: None } };
    let n = write_ply(&map, &a.ply, options)?;
    if n == 0 {
        tracing::warn!("{}: no voxels to export; wrote an empty PLY", a.map.display());
    }
    println!("{}: {n} voxels", a.ply.display());
    Ok(())
}
