//! Maps: the sparse bricked voxel store ([`Grid`]) and the finished, engine-independent
//! [`Map`] that every output (files, export, queries, evaluation) reads.
//!
//! Engines keep whatever per-voxel state they need in their own `Grid`; when asked they
//! produce a `Map` of occupancy probabilities (and variances where the engine has them).
//! Maps can be cropped, cleared, compared and projected to 2D (`ops`); merging needs the
//! engine's rule and lives with the engines ([`crate::inference::merge`]).

mod file;
mod grid;
mod kind;
mod ops;
mod region;
mod tiled;

pub(crate) use grid::floor_i32_lanes;
pub use grid::{
    BRICK_EDGE, BRICK_VOXELS, Brick, BrickKey, BrickList, Grid, SlotMask, VoxelKey, box_slots, check_resolution,
    floor_i32, mask_has, mask_set, mask_slots,
};

pub use kind::EngineKind;
pub use ops::{Change, Grid2d, MAX_GRID2D_CELLS, VoxelState};
pub use region::{Aabb, box_keys, key_in_box};
pub use tiled::{INDEX_FILE, TileEntry, TileGrid, TileIndex, TileKey, TileTotals, TiledMap};

use std::collections::BTreeMap;
use std::path::Path;

/// The state of one voxel in a finished map.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MapVoxel {
    /// Probability that the voxel is occupied.
    pub occupancy: f32,
    /// Variance of the occupancy estimate (0 when the engine has none).
    pub variance: f32,
}

impl MapVoxel {
    /// Mean occupancy and its standard deviation: the engine's variance where it has one
    /// (CRM), otherwise the Bernoulli variance `p (1 - p)` of the occupancy probability.
    #[inline]
    pub fn mean_sigma(&self, has_variance: bool) -> (f64, f64) {
        let m = self.occupancy as f64;
        let var = if has_variance { self.variance as f64 } else { m * (1.0 - m) };
        (m, var.max(0.0).sqrt())
    }

    /// True when the occupancy is above [`OCCUPIED_THRESHOLD`].
    #[inline]
    pub fn is_occupied(&self) -> bool {
        self.occupancy > OCCUPIED_THRESHOLD
    }
}

/// Probability above which a voxel counts as occupied (OctoMap's default).
pub const OCCUPIED_THRESHOLD: f32 = 0.5;

/// A finished occupancy map: what engines produce and outputs consume.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// let mut map = Map::new(EngineKind::LogOdds, 0.05).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// map.voxels.insert(VoxelKey([1, 0, 0]), MapVoxel { occupancy: 0.2, variance: 0.0 });
/// assert_eq!(map.occupied_count(), 1);
/// assert_eq!(map.occupancy_at([0.01, 0.01, 0.01]), Some(0.9));
/// ```
#[derive(Clone, Debug)]
pub struct Map {
    /// Engine that built the map.
    pub engine: EngineKind,
    /// Engine parameters, for the record (`p_hit = 0.7`, ...).
    pub params: BTreeMap<String, String>,
    /// True when `variance` is meaningful.
    pub has_variance: bool,
    /// The voxels.
    pub voxels: Grid<MapVoxel>,
}

impl Map {
    /// An empty map.
    pub fn new(engine: EngineKind, resolution: f64) -> crate::Result<Self> {
        Ok(Map { engine, params: BTreeMap::new(), has_variance: false, voxels: Grid::new(resolution)? })
    }

    /// Voxel edge in metres.
    pub fn resolution(&self) -> f64 {
        self.voxels.resolution()
    }

    /// Occupancy probability at a world point; `None` where the map has no information.
    pub fn occupancy_at(&self, p: [f64; 3]) -> Option<f32> {
        self.voxels.get(VoxelKey::from_point(p, self.resolution())).map(|v| v.occupancy)
    }

    /// Number of voxels with occupancy above [`OCCUPIED_THRESHOLD`].
    pub fn occupied_count(&self) -> usize {
        self.voxels.iter().filter(|(_, v)| v.is_occupied()).count()
    }

    /// World-space bounds `(min corner, max corner)` of the allocated voxels.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let r = self.resolution();
        self.voxels.key_bounds().map(|(lo, hi)| (lo.0.map(|i| i as f64 * r), hi.0.map(|i| (i + 1) as f64 * r)))
    }

    /// Saves in the binary map format (atomically: temp file + rename).
    pub fn save(&self, path: &Path) -> crate::Result<()> {
        file::save(self, path)
    }

    /// Saves, as [`Map::save`] would, this map's engine, parameters and `has_variance` with
    /// `grid`'s voxels made map voxels by `convert` (this map's own voxels are not read), each
    /// brick converted as it is written: an engine's state saved without its finished map
    /// ever in memory. Returns how many voxels are occupied.
    ///
    /// ```
    /// use mrfmap::map::{EngineKind, Grid, Map, MapVoxel, VoxelKey};
    /// let mut grid: Grid<f32> = Grid::new(0.05).unwrap();
    /// *grid.get_or_insert(VoxelKey([1, 2, 3]), 0.0) = 0.9;
    /// let path = std::env::temp_dir().join("mrfmap-doc-save-converted.mrfmap");
    /// let meta = Map::new(EngineKind::LogOdds, 0.05).unwrap();
    /// let occupied = meta.save_converted(&grid, |&p| MapVoxel { occupancy: p, variance: 0.0 }, &path).unwrap();
    /// assert_eq!(occupied, 1);
    /// assert_eq!(Map::load(&path).unwrap().occupancy_at([0.06, 0.11, 0.16]), Some(0.9));
    /// # std::fs::remove_file(&path).unwrap();
    /// ```
    pub fn save_converted<V: Copy + Default>(
        &self,
        grid: &Grid<V>,
        convert: impl Fn(&V) -> MapVoxel,
        path: &Path,
    ) -> crate::Result<usize> {
        file::save_converted(self, grid, convert, path)
    }

    /// Loads a map saved by [`Map::save`]; corrupt, truncated or foreign files give a clear error.
    /// A tiled map's folder ([`TiledMap`]) is read whole, every tile stitched into one map.
    pub fn load(path: &Path) -> crate::Result<Self> {
        if TiledMap::is_tiled(path) {
            return TiledMap::open(path)?.load_all();
        }
        file::load(path)
    }

    /// A map from the bytes of a map file (what [`Map::load`] reads).
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Self> {
        file::decode(bytes).map_err(crate::Error::Invalid)
    }
}
