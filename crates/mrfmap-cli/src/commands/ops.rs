//! Map operations, one subcommand each: `crop`, `clear`, `merge`, `diff`, `project`
//! (the library's `Map::crop`, `clear`, `merge`, `diff`, `project`).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, Result};
use mrfmap::map::Aabb;
use mrfmap::map::{Map, TiledMap, VoxelState};
use mrfmap::outputs::{write_changes_ply, write_map_server};

/// The input map and the box of `crop` and `clear`.
#[derive(clap::Args)]
pub struct BoxArgs {
    /// Map file written by `mrfmap build` (or a tiled map's folder).
    map: PathBuf,
    /// The box `XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`: voxels overlapping it with positive volume.
    #[arg(long = "box", value_name = "XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX", allow_hyphen_values = true)]
    region: String,
    /// Output map file.
    #[arg(long, short)]
    output: PathBuf,
}

impl BoxArgs {
    fn load(&self) -> Result<(Map, Aabb)> {
        let region = Aabb::parse(&self.region).with_context(|| format!("--box {}", self.region))?;
        Ok((Map::load(&self.map)?, region))
    }
}

/// `mrfmap crop`: keep only the voxels in a box.
/// A tiled map's folder is read a tile at a time: only the tiles the box overlaps.
pub fn crop(a: BoxArgs) -> Result<()> {
    let region = Aabb::parse(&a.region).with_context(|| format!("--box {}", a.region))?;
    let (map, total) = if TiledMap::is_tiled(&a.map) {
        let tiled = TiledMap::open(&a.map)?;
        (tiled.load_region(&region)?, tiled.totals().voxels as usize)
    } else {
        let map = Map::load(&a.map)?;
        let total = map.voxels.len();
        (map, total)
    };
    let out = map.crop(&region);
    out.save(&a.output)?;
    println!("{}: {} of {total} voxels", a.output.display(), out.voxels.len());
    Ok(())
}

/// `mrfmap clear`: make the voxels in a box unknown.
pub fn clear(a: BoxArgs) -> Result<()> {
    let (mut map, region) = a.load()?;
    let n = map.clear(&region);
    map.save(&a.output)?;
    println!("{}: cleared {n} voxels, {} left", a.output.display(), map.voxels.len());
    Ok(())
}

#[derive(clap::Args)]
pub struct MergeArgs {
    /// First map.
    a: PathBuf,
    /// Second map (same engine and resolution).
    b: PathBuf,
    /// Output map file.
    #[arg(long, short)]
    output: PathBuf,
}

/// `mrfmap merge`: both maps' evidence in one.
pub fn merge(a: MergeArgs) -> Result<()> {
    let (first, second) = (Map::load(&a.a)?, Map::load(&a.b)?);
    let out = mrfmap::inference::merge(&first, &second)
        .with_context(|| format!("merging {} and {}", a.a.display(), a.b.display()))?;
    out.save(&a.output)?;
    println!("{}: {} voxels, {} occupied", a.output.display(), out.voxels.len(), out.occupied_count());
    Ok(())
}

#[derive(clap::Args)]
pub struct DiffArgs {
    /// The map before.
    before: PathBuf,
    /// The map after (same resolution).
    after: PathBuf,
    /// Occupancy above which a voxel is occupied.
    #[arg(long, default_value_t = 0.5, value_parser = super::threshold)]
    threshold: f32,
    /// Write the changed voxels: `.ply` (centres with `before` and `after` occupancy, -1 for
    /// unknown) or a map file (the changed voxels as the second map has them; voxels that
    /// became unknown are left out).
    #[arg(long, short)]
    output: Option<PathBuf>,
}

/// `mrfmap diff`: voxels whose state changed.
pub fn diff(a: DiffArgs) -> Result<()> {
    let (before, after) = (Map::load(&a.before)?, Map::load(&a.after)?);
    let changes = before.diff(&after, a.threshold)?;
    let mut counts: BTreeMap<(VoxelState, VoxelState), usize> = BTreeMap::new();
    for c in &changes {
        let key = (VoxelState::of(c.before.as_ref(), a.threshold), VoxelState::of(c.after.as_ref(), a.threshold));
        *counts.entry(key).or_default() += 1;
    }
    println!("{} voxels changed state", changes.len());
    for ((from, to), n) in &counts {
        println!("  {:>8} -> {:<8} {n}", from.name(), to.name());
    }
    if let Some(path) = &a.output {
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("ply")) {
            write_changes_ply(&changes, after.resolution(), path)?;
        } else {
            let mut out = Map { voxels: mrfmap::map::Grid::new(after.resolution())?, ..after.clone() };
            for c in &changes {
                if let Some(v) = c.after {
                    out.voxels.insert(c.key, v);
                }
            }
            out.save(path)?;
        }
        println!("{}: {} changed voxels", path.display(), changes.len());
    }
    Ok(())
}

#[derive(clap::Args)]
pub struct ProjectArgs {
    /// Map file written by `mrfmap build`.
    map: PathBuf,
    /// Lowest height (metres) of the slab to project.
    #[arg(long, allow_hyphen_values = true)]
    z_min: f64,
    /// Highest height (metres) of the slab to project.
    #[arg(long, allow_hyphen_values = true)]
    z_max: f64,
    /// Occupancy above which a cell is occupied.
    #[arg(long, default_value_t = 0.5, value_parser = super::threshold)]
    threshold: f32,
    /// Also write `<stem>-sigma.pgm`, the standard deviation per cell.
    #[arg(long)]
    sigma: bool,
    /// Output YAML (`map_server` format); the PGM is written beside it.
    #[arg(long, short)]
    output: PathBuf,
}

/// `mrfmap project`: the 2D occupancy grid of a height slab, for 2D planners.
pub fn project(a: ProjectArgs) -> Result<()> {
    let map = Map::load(&a.map)?;
    let grid = map.project(a.z_min, a.z_max).with_context(|| a.map.display().to_string())?;
    let files = write_map_server(&grid, &a.output, a.threshold, a.sigma)?;
    let [occ, free, unknown] = files.counts;
    println!(
        "{} and {}: {} x {} cells at {} m, {occ} occupied, {free} free, {unknown} unknown",
        a.output.display(),
        files.image.display(),
        grid.width,
        grid.height,
        grid.resolution
    );
    Ok(())
}
