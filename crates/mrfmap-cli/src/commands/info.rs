//! `mrfmap info`: what is in a map file, as text or as one JSON object for scripts.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::map::{Map, TiledMap};

#[derive(clap::Args)]
pub struct Args {
    /// Map file, or a tiled map's folder (described from its index, no tile read).
    map: PathBuf,
    /// Print one JSON object (`file`, `engine`, `resolution`, `voxels`, `occupied`, `bricks`,
    /// `bounds` as `[[min], [max]]` or null, `variance`, `memory_bytes`, `bytes_per_voxel`,
    /// `params`).
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    if TiledMap::is_tiled(&a.map) {
        return tiled(&a);
    }
    let map = Map::load(&a.map)?;
    let memory = map.voxels.memory_bytes();
    let per_voxel = memory as f64 / map.voxels.len().max(1) as f64;
    if a.json {
        let json = serde_json::json!({
            "file": a.map.display().to_string(),
            "engine": map.engine,
            "resolution": map.resolution(),
            "voxels": map.voxels.len(),
            "occupied": map.occupied_count(),
            "bricks": map.voxels.brick_count(),
            "bounds": map.bounds().map(|(lo, hi)| [lo, hi]),
            "variance": map.has_variance,
            "memory_bytes": memory,
            "bytes_per_voxel": per_voxel,
            "params": map.params,
        });
        println!("{json}");
        return Ok(());
    }
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
    println!("memory:      {:.1} MiB in memory ({per_voxel:.1} bytes per voxel)", memory as f64 / (1 << 20) as f64);
    for (k, v) in &map.params {
        println!("param:       {k} = {v}");
    }
    Ok(())
}

/// A tiled map, from its index alone: the same fields, and `tiles` and `tile_edge`.
fn tiled(a: &Args) -> Result<()> {
    let map = TiledMap::open(&a.map)?;
    let index = map.index();
    let t = map.totals();
    let (voxels, occupied, bricks, memory) = (t.voxels, t.occupied, t.bricks, t.memory_bytes);
    let per_voxel = memory as f64 / voxels.max(1) as f64;
    if a.json {
        let json = serde_json::json!({
            "file": a.map.display().to_string(),
            "engine": index.engine,
            "resolution": index.resolution,
            "voxels": voxels,
            "occupied": occupied,
            "bricks": bricks,
            "bounds": t.bounds,
            "variance": index.has_variance,
            "memory_bytes": memory,
            "bytes_per_voxel": per_voxel,
            "params": index.params,
            "tiles": index.tiles.len(),
            "tile_edge": index.tile_edge,
        });
        println!("{json}");
        return Ok(());
    }
    println!("file:        {} (tiled)", a.map.display());
    println!("engine:      {}", index.engine);
    println!("resolution:  {} m", index.resolution);
    println!("tiles:       {} of {} m", index.tiles.len(), index.tile_edge);
    println!("voxels:      {voxels} ({occupied} occupied)");
    println!("bricks:      {bricks} of 8x8x8");
    match t.bounds {
        Some([lo, hi]) => println!(
            "bounds:      [{:.3}, {:.3}, {:.3}] to [{:.3}, {:.3}, {:.3}] m",
            lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
        ),
        None => println!("bounds:      (empty map)"),
    }
    println!("variance:    {}", if index.has_variance { "yes" } else { "no" });
    println!(
        "memory:      {:.1} MiB all tiles loaded ({per_voxel:.1} bytes per voxel)",
        memory as f64 / (1 << 20) as f64
    );
    for (k, v) in &index.params {
        println!("param:       {k} = {v}");
    }
    Ok(())
}
