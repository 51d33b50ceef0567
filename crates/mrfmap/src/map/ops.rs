//! Operations on finished maps: crop and clear a box, what changed between two maps, and the
//! 2D occupancy grid between two heights. (Merging two maps combines their engine's evidence,
//! so it lives with the engines: [`crate::inference::merge`].)
//!
//! A box selects the voxels that overlap it with positive volume (the same rule as
//! [`crate::outputs::query_box`]).

use super::{Aabb, box_keys, key_in_box};
use super::{Grid, Map, MapVoxel, VoxelKey};
use crate::error::{Error, Result};

/// What the map knows of a voxel, as a planner reads it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum VoxelState {
    /// Not in the map.
    Unknown,
    /// Occupancy at or below the threshold.
    Free,
    /// Occupancy above the threshold.
    Occupied,
}

impl VoxelState {
    /// The state of a voxel (or of none) at `threshold`.
    pub fn of(voxel: Option<&MapVoxel>, threshold: f32) -> Self {
        match voxel {
            None => VoxelState::Unknown,
            Some(v) if v.occupancy > threshold => VoxelState::Occupied,
            Some(_) => VoxelState::Free,
        }
    }

    /// Lower-case name (`unknown`, `free`, `occupied`).
    pub fn name(self) -> &'static str {
        match self {
            VoxelState::Unknown => "unknown",
            VoxelState::Free => "free",
            VoxelState::Occupied => "occupied",
        }
    }
}

/// A voxel whose state differs between two maps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Change {
    /// The voxel.
    pub key: VoxelKey,
    /// Its value in the first map, if known there.
    pub before: Option<MapVoxel>,
    /// Its value in the second map, if known there.
    pub after: Option<MapVoxel>,
}

impl Map {
    /// The voxels of this map that overlap `region`.
    pub fn crop(&self, region: &Aabb) -> Map {
        let (lo, hi) = box_keys(region, self.resolution());
        let mut out = Map { voxels: Grid::new(self.resolution()).expect("valid resolution"), ..self.clone_header() };
        for (key, v) in self.voxels.iter() {
            if key_in_box(key.0, (lo, hi)) {
                out.voxels.insert(key, *v);
            }
        }
        out
    }

    /// Makes the voxels overlapping `region` unknown; returns how many were known.
    pub fn clear(&mut self, region: &Aabb) -> usize {
        let (lo, hi) = box_keys(region, self.resolution());
        let doomed: Vec<VoxelKey> = self.voxels.iter().map(|(k, _)| k).filter(|k| key_in_box(k.0, (lo, hi))).collect();
        for k in &doomed {
            self.voxels.remove(*k);
        }
        doomed.len()
    }

    /// The map without its voxels.
    fn clone_header(&self) -> Map {
        Map {
            engine: self.engine,
            params: self.params.clone(),
            has_variance: self.has_variance,
            voxels: Grid::new(self.resolution()).expect("valid resolution"),
        }
    }

    /// Voxels whose state (unknown, free, occupied at `threshold`) differs from `after`'s,
    /// in key order.
    pub fn diff(&self, after: &Map, threshold: f32) -> Result<Vec<Change>> {
        if self.resolution() != after.resolution() {
            return Err(Error::Invalid(format!(
                "maps at different resolutions ({} m and {} m) cannot be compared voxel by voxel",
                self.resolution(),
                after.resolution()
            )));
        }
        let mut changes = Vec::new();
        let mut visit = |key: VoxelKey| {
            let (b, a) = (self.voxels.get(key), after.voxels.get(key));
            if VoxelState::of(b, threshold) != VoxelState::of(a, threshold) {
                changes.push(Change { key, before: b.copied(), after: a.copied() });
            }
        };
        for (key, _) in self.voxels.iter() {
            visit(key);
        }
        for (key, _) in after.voxels.iter() {
            if self.voxels.get(key).is_none() {
                visit(key);
            }
        }
        changes.sort_by_key(|c| c.key);
        Ok(changes)
    }

    /// The 2D occupancy grid of the voxels overlapping heights `z_min` to `z_max`: each cell
    /// holds its column's most occupied known voxel (occupancy and sigma), or nothing when the
    /// column is unknown. At any threshold a column is then occupied if one of its voxels is,
    /// free if it has known voxels and none occupied (octomap_server's projection). Covers the
    /// map's extent in x and y.
    pub fn project(&self, z_min: f64, z_max: f64) -> Result<Grid2d> {
        let r = self.resolution();
        let (lo, hi) = self.bounds().ok_or_else(|| Error::Invalid("the map is empty: nothing to project".into()))?;
        let region = Aabb::new([lo[0], lo[1], z_min], [hi[0], hi[1], z_max])
            .map_err(|_| Error::Invalid(format!("need z_min < z_max, got {z_min} and {z_max}")))?;
        let (klo, khi) = box_keys(&region, r);
        let (w, h) = ((khi[0] - klo[0] + 1) as usize, (khi[1] - klo[1] + 1) as usize);
        let cells = w as u128 * h as u128;
        if cells > MAX_GRID2D_CELLS {
            return Err(Error::Invalid(format!(
                "the map spans {w} x {h} cells at {r} m, more than {MAX_GRID2D_CELLS}: crop it first"
            )));
        }
        let origin = [klo[0] as f64 * r, klo[1] as f64 * r];
        let mut grid = Grid2d { resolution: r, origin, width: w, height: h, cells: vec![None; w * h] };
        for (key, v) in self.voxels.iter() {
            if !key_in_box(key.0, (klo, khi)) {
                continue;
            }
            let i = (key.0[1] - klo[1]) as usize * w + (key.0[0] - klo[0]) as usize;
            let cell = &mut grid.cells[i];
            let (p, sigma) = v.mean_sigma(self.has_variance);
            // The column's answer is its most occupied voxel.
            if cell.is_none_or(|(q, _)| p as f32 > q) {
                *cell = Some((p as f32, sigma as f32));
            }
        }
        Ok(grid)
    }
}

/// Most cells a 2D projection may have (1 GiB of cells).
pub const MAX_GRID2D_CELLS: u128 = 1 << 27;

/// A 2D occupancy grid: row `j` is `y = origin[1] + (j + 0.5) resolution`, column `i` likewise
/// in `x`; a cell holds occupancy and sigma, or `None` when unknown.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid2d {
    /// Cell edge in metres.
    pub resolution: f64,
    /// World `(x, y)` of the lower-left corner of cell `(0, 0)`.
    pub origin: [f64; 2],
    /// Cells per row (along x).
    pub width: usize,
    /// Rows (along y).
    pub height: usize,
    /// Row-major from the lowest y.
    pub cells: Vec<Option<(f32, f32)>>,
}

impl Grid2d {
    /// The cell at column `i`, row `j` (from the lowest y).
    pub fn cell(&self, i: usize, j: usize) -> Option<(f32, f32)> {
        self.cells[j * self.width + i]
    }
}
