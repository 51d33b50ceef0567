//! `mrfmap export`: map file to PLY, OctoMap, Foxglove (MCAP) and ROS map_server files.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use mrfmap::map::Map;
use mrfmap::outputs::{
    OctomapFormat, PlyOptions, SCENE_TOPIC, SceneOptions, write_map_server, write_octomap, write_ply, write_scene_mcap,
};

#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("outputs").required(true).multiple(true).args(["ply", "bt", "ot", "mcap", "grid2d"]))]
pub struct Args {
    /// Map file written by `mrfmap build`.
    map: PathBuf,
    /// Write a binary PLY of voxel centres with occupancy (and variance).
    #[arg(long)]
    ply: Option<PathBuf>,
    /// PLY: only voxels with occupancy above 0.5.
    #[arg(long)]
    occupied_only: bool,
    /// Write an OctoMap `.bt` (occupied / free, pruned; octovis, RViz).
    #[arg(long)]
    bt: Option<PathBuf>,
    /// Write an OctoMap `.ot` (log-odds per node).
    #[arg(long)]
    ot: Option<PathBuf>,
    /// Write an MCAP file with a `foxglove.SceneUpdate` of cubes (one entity per brick) that
    /// Foxglove opens.
    #[arg(long)]
    mcap: Option<PathBuf>,
    /// Write a 2D occupancy grid in the ROS map_server format (YAML + PGM beside it) of all
    /// the map's layers (for a 3D map's slab use `mrfmap project`).
    #[arg(long, value_name = "OUT.yaml")]
    grid2d: Option<PathBuf>,
    /// grid2d: also write `<stem>-sigma.pgm`, the standard deviation per cell.
    #[arg(long)]
    sigma: bool,
    /// MCAP and grid2d: voxels above this occupancy are occupied.
    #[arg(long, default_value_t = 0.5, value_parser = super::threshold)]
    threshold: f32,
    /// MCAP: colour cubes by height, sigma or occupancy.
    #[arg(long, default_value = "occupancy", value_parser = ["height", "sigma", "variance", "occupancy"])]
    color: String,
    /// MCAP: the frame id of the scene's entities.
    #[arg(long, default_value = "map")]
    frame_id: String,
}

pub fn run(a: Args) -> Result<()> {
    // A wrong extension is most often a swapped flag: found before any work.
    let outputs = [
        ("--ply", &a.ply, "ply"),
        ("--bt", &a.bt, "bt"),
        ("--ot", &a.ot, "ot"),
        ("--mcap", &a.mcap, "mcap"),
        ("--grid2d", &a.grid2d, "yaml"),
    ];
    for (flag, path, ext) in outputs {
        if let Some(path) = path {
            let got = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
            if got != ext && !(ext == "yaml" && got == "yml") {
                bail!("{flag} {}: expected a .{ext} file", path.display());
            }
            super::options::check_output_folder(path)?;
        }
    }
    let map = Map::load(&a.map)?;
    if let Some(ply) = &a.ply {
        let options = if a.occupied_only { PlyOptions::occupied_only() } else { PlyOptions { min_occupancy: None } };
        let n = write_ply(&map, ply, options)?;
        if n == 0 {
            tracing::warn!("{}: no voxels to export; wrote an empty PLY", a.map.display());
        }
        println!("{}: {n} voxels", ply.display());
    }
    for (path, format) in [(&a.bt, OctomapFormat::Binary), (&a.ot, OctomapFormat::Full)] {
        if let Some(path) = path {
            let s = write_octomap(&map, path, format)?;
            println!("{}: {} nodes, {} leaves", path.display(), s.nodes, s.leaves);
        }
    }
    if let Some(path) = &a.grid2d {
        let (lo, hi) =
            map.bounds().with_context(|| format!("{}: the map is empty: no grid to write", a.map.display()))?;
        let grid = map.project(lo[2], hi[2])?;
        let f = write_map_server(&grid, path, a.threshold, a.sigma)?;
        let [occ, free, unknown] = f.counts;
        println!(
            "{} and {}: {} x {} cells, {occ} occupied, {free} free, {unknown} unknown",
            path.display(),
            f.image.display(),
            grid.width,
            grid.height
        );
    }
    if let Some(path) = &a.mcap {
        let options =
            SceneOptions { threshold: a.threshold, colouring: a.color.parse()?, frame_id: a.frame_id.clone() };
        let s = write_scene_mcap(&map, path, &options)?;
        println!("{}: {} cubes in {} entities on {SCENE_TOPIC}", path.display(), s.cubes, s.entities);
    }
    Ok(())
}
