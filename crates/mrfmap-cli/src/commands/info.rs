//! `mrfmap info`: what is in a map file.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::map::Map;

#[derive(clap::Args)]
pub struct Args {
    /// Map file.
    map: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let map = Map::load(&a.map)?;
    println!("file:        {}", a.map.display());
    println!("engine:      {}", map.engine);
    println!("resolution:  {} m", map.resolution());
    println!("voxels:      {} ({} occupied)", map.voxels.len(), map.occupied_count());
    println!("bricks:      {} of 8x8x8", map.voxels.brick_count());
    match map.bounds() {
        Some((lo, hi)) => println!(
            "bounds:      [{:.3}, {:.3}, {:.3}] to [{:.3}, {:.3}, {:.3}] m",
            lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
        ),
        None => println!("bounds:      (empty map)"),
    }
    println!("variance:    {}", if map.has_variance { "yes" } else { "no" });
    println!("memory:      {:.1} MiB in memory", map.voxels.memory_bytes() as f64 / (1 << 20) as f64);
    for (k, v) in &map.params {
        println!("param:       {k} = {v}");
    }
    Ok(())
}
