//! Tiled maps: one map stored as a folder of ordinary map files, one per cube of space (a
//! tile), and an index, so that a map larger than one machine's memory can be built tile by
//! tile (on many machines) and read a few tiles at a time.
//!
//! ```text
//! MAP/tiles.toml          the index (TOML): format, version, engine, resolution, tile edge,
//!                         tile height (when tiles are not columns), has_variance, params,
//!                         and per tile its key, file and counts
//! MAP/tile_X_Y_Z.mrfmap   the voxels of tile (X, Y, Z), an ordinary `.mrfmap` file
//! ```
//!
//! Tiles are columns by default: tile `(X, Y, 0)` holds the voxels whose x and y keys divided
//! by the tile's edge in voxels (rounded down) are `X` and `Y`, at every height; with a tile
//! height, `Z` is the z key divided by it likewise. Tiles are whole bricks, so a brick belongs to exactly one tile and
//! tiles stitch by moving bricks ([`TiledMap::load`]). The index is written last, atomically:
//! a folder without one is not a map. [`TileGrid`] is the geometry; [`TiledMap`] reads the
//! index at once and the tiles only when asked ([`TiledMap::load_tile`]).

use super::EngineKind;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Aabb, BRICK_EDGE, BrickKey, Map, VoxelKey, box_keys};
use crate::error::{Error, Result};

/// The index file's name inside a tiled map's folder.
pub const INDEX_FILE: &str = "tiles.toml";

const FORMAT: &str = "mrfmap-tiles";
const VERSION: u32 = 1;

/// Which tile: the tile's position in tile edges from the origin.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TileKey(pub [i32; 3]);

/// How space is cut into tiles: squares of `edge_voxels` voxels (a whole number of bricks)
/// from the origin in x and y, and either columns through every height or layers of
/// `height_voxels` in z.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileGrid {
    resolution: f64,
    edge_voxels: i32,
    height_voxels: Option<i32>,
}

/// Half the height of a column tile's box (m): far beyond any map, finite for box arithmetic.
const COLUMN_HALF_HEIGHT: f64 = 1e6;

/// `length` metres as a whole number of bricks of voxel edge `resolution` (what tile edges must
/// be), or an error naming `what` and the nearest lengths that are.
fn whole_bricks(what: &str, length: f64, resolution: f64) -> Result<i32> {
    let brick = BRICK_EDGE as f64 * resolution;
    let bricks = (length / brick).round();
    let whole = length.is_finite() && bricks >= 1.0 && (bricks * brick - length).abs() <= 1e-6 * length;
    if !whole || bricks * BRICK_EDGE as f64 > (1 << 24) as f64 {
        let below = (length / brick).floor().max(1.0) * brick;
        return Err(Error::Invalid(format!(
            "a tile {what} must be a whole number of bricks (8 voxels = {brick} m at {resolution} m), got {length}; \
             e.g. {} or {}",
            round_metres(below),
            round_metres(below + brick)
        )));
    }
    Ok(bricks as i32 * BRICK_EDGE)
}

impl TileGrid {
    /// Column tiles of edge `edge` metres (through every height) in a grid of voxel edge
    /// `resolution`. The edge must be a whole number of bricks (8 voxels) so that tiles stitch
    /// brick by brick; the error names the nearest edges that are.
    ///
    /// ```
    /// use mrfmap::map::{TileGrid, TileKey, VoxelKey};
    /// let grid = TileGrid::new(10.0, 0.05).unwrap();
    /// assert_eq!(grid.tile_of(VoxelKey([199, -1, -7])), TileKey([0, -1, 0]));
    /// let cubes = grid.with_height(Some(10.0)).unwrap();
    /// assert_eq!(cubes.tile_of(VoxelKey([199, -1, -7])), TileKey([0, -1, -1]));
    /// assert!(TileGrid::new(10.0, 0.03).unwrap_err().to_string().contains("9.84"));
    /// ```
    pub fn new(edge: f64, resolution: f64) -> Result<Self> {
        super::check_resolution(resolution)?;
        Ok(TileGrid { resolution, edge_voxels: whole_bricks("edge", edge, resolution)?, height_voxels: None })
    }

    /// The same tiles cut into layers of `height` metres in z too (`None`: columns).
    pub fn with_height(self, height: Option<f64>) -> Result<Self> {
        let height_voxels = height.map(|h| whole_bricks("height", h, self.resolution)).transpose()?;
        Ok(TileGrid { height_voxels, ..self })
    }

    /// Tile height in metres (`None`: columns through every height).
    pub fn height(&self) -> Option<f64> {
        self.height_voxels.map(|h| h as f64 * self.resolution)
    }

    /// Voxel edge in metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Tile edge in metres.
    pub fn edge(&self) -> f64 {
        self.edge_voxels as f64 * self.resolution
    }

    /// The tile holding voxel `key`.
    #[inline]
    pub fn tile_of(&self, key: VoxelKey) -> TileKey {
        let [x, y, z] = key.0;
        TileKey([
            x.div_euclid(self.edge_voxels),
            y.div_euclid(self.edge_voxels),
            self.height_voxels.map_or(0, |h| z.div_euclid(h)),
        ])
    }

    /// The tile holding brick `key`.
    pub fn tile_of_brick(&self, key: BrickKey) -> TileKey {
        self.tile_of(VoxelKey(key.0.map(|k| k * BRICK_EDGE)))
    }

    /// The tile's box in world coordinates.
    pub fn bounds(&self, tile: TileKey) -> Aabb {
        let edge = self.edge();
        let [x, y, z] = tile.0.map(|t| t as f64);
        let (z0, z1) = match self.height() {
            Some(h) => (z * h, (z + 1.0) * h),
            None => (-COLUMN_HALF_HEIGHT, COLUMN_HALF_HEIGHT),
        };
        Aabb { min: [x * edge, y * edge, z0], max: [(x + 1.0) * edge, (y + 1.0) * edge, z1] }
    }

    /// The tiles holding a voxel that overlaps `region`, in key order (at most `limit` of
    /// them: an error beyond).
    pub fn overlapping(&self, region: &Aabb, limit: usize) -> Result<Vec<TileKey>> {
        let (lo, hi) = box_keys(region, self.resolution);
        let (lo, hi) = (self.tile_of(VoxelKey(lo)).0, self.tile_of(VoxelKey(hi)).0);
        let count: u128 = (0..3).map(|a| (hi[a] as i128 - lo[a] as i128 + 1).max(0) as u128).product();
        if count > limit as u128 {
            return Err(Error::Invalid(format!(
                "the box {region:?} spans {count} tiles of {} m, more than {limit}",
                self.edge()
            )));
        }
        let mut out = Vec::with_capacity(count as usize);
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    out.push(TileKey([x, y, z]));
                }
            }
        }
        Ok(out)
    }
}

/// `x` metres written without floating-point noise (9.840000000000001 -> 9.84).
fn round_metres(x: f64) -> f64 {
    (x * 1e9).round() / 1e9
}

/// One tile in the index.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileEntry {
    /// The tile's key.
    pub key: [i32; 3],
    /// Its map file, a name inside the map's folder.
    pub file: String,
    /// Voxels it holds.
    pub voxels: u64,
    /// Voxels above [`super::OCCUPIED_THRESHOLD`].
    pub occupied: u64,
    /// Bricks it holds.
    pub bricks: u64,
    /// Memory the loaded tile takes (bytes, [`super::Grid::memory_bytes`]).
    pub memory_bytes: u64,
    /// Readings (frames) it was built from.
    pub frames: u64,
    /// World bounds `[min, max]` of its voxels (none when empty).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bounds: Option<[[f64; 3]; 2]>,
}

/// The index of a tiled map (`tiles.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileIndex {
    /// `"mrfmap-tiles"`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// Engine that built every tile.
    pub engine: EngineKind,
    /// Voxel edge in metres.
    pub resolution: f64,
    /// Tile edge in x and y (metres).
    pub tile_edge: f64,
    /// Tile height in z (metres); none: tiles are columns through every height.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tile_height: Option<f64>,
    /// True when the tiles' variances are meaningful.
    pub has_variance: bool,
    /// Parameters of the build, as a map file's.
    #[serde(default)]
    pub params: BTreeMap<String, String>,
    /// The tiles, in key order.
    #[serde(rename = "tile", default)]
    pub tiles: Vec<TileEntry>,
}

impl TileIndex {
    /// Parses and checks an index (`origin` names the file in errors): its format and version,
    /// a tile grid that is whole bricks, file names inside the folder, each key once.
    pub fn from_toml(text: &str, origin: &Path) -> Result<Self> {
        let index: TileIndex = crate::error::parse_toml(text, origin)?;
        let bad = |m: String| Error::file(origin, m);
        if index.format != FORMAT || index.version != VERSION {
            return Err(bad(format!(
                "not a tile index of this version (format {:?} version {}; this build reads {FORMAT:?} version \
                 {VERSION})",
                index.format, index.version
            )));
        }
        TileGrid::new(index.tile_edge, index.resolution)
            .and_then(|g| g.with_height(index.tile_height))
            .map_err(|e| bad(e.to_string()))?;
        let mut keys = std::collections::BTreeSet::new();
        for t in &index.tiles {
            let plain = Path::new(&t.file).file_name().is_some_and(|n| n == t.file.as_str()) && t.file != "..";
            if !plain {
                return Err(bad(format!("tile {:?}: file {:?} is not a name inside the map's folder", t.key, t.file)));
            }
            if !keys.insert(t.key) {
                return Err(bad(format!("tile {:?} is listed twice", t.key)));
            }
        }
        Ok(index)
    }

    /// An index of no tiles yet for maps of `engine` cut by `grid`.
    pub fn new(engine: EngineKind, grid: &TileGrid, has_variance: bool, params: BTreeMap<String, String>) -> Self {
        TileIndex {
            format: FORMAT.into(),
            version: VERSION,
            engine,
            resolution: grid.resolution(),
            tile_edge: grid.edge(),
            tile_height: grid.height(),
            has_variance,
            params,
            tiles: Vec::new(),
        }
    }

    /// The file name of tile `key`.
    pub fn file_name(key: TileKey) -> String {
        let [x, y, z] = key.0;
        format!("tile_{x}_{y}_{z}.mrfmap")
    }

    /// Writes tile `key` of `map` (the voxels of that tile only) into the folder `dir`
    /// (atomically) and returns its index entry; `frames` is recorded. An empty tile is
    /// written too: it says the tile was built and saw nothing.
    pub fn save_tile(dir: &Path, grid: &TileGrid, key: TileKey, map: &Map, frames: u64) -> Result<TileEntry> {
        if let Some((brick, _)) = map.voxels.bricks().find(|(b, _)| grid.tile_of_brick(**b) != key) {
            return Err(Error::Invalid(format!("tile {:?}: brick {:?} lies outside the tile", key.0, brick.0)));
        }
        let file = Self::file_name(key);
        map.save(&dir.join(&file))?;
        Ok(TileEntry {
            key: key.0,
            file,
            voxels: map.voxels.len() as u64,
            occupied: map.occupied_count() as u64,
            bricks: map.voxels.brick_count() as u64,
            memory_bytes: map.voxels.memory_bytes() as u64,
            frames,
            bounds: map.bounds().map(|(lo, hi)| [lo, hi]),
        })
    }

    /// Writes the index into `dir` (atomically), tiles sorted by key: what makes the folder a
    /// map, so it goes last.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let mut index = self.clone();
        index.tiles.sort_by_key(|t| t.key);
        let text = toml::to_string(&index).map_err(|e| Error::Invalid(format!("tile index: {e}")))?;
        crate::atomic_file::write_atomic(&dir.join(INDEX_FILE), |w| std::io::Write::write_all(w, text.as_bytes()))
    }
}

/// Sums over a tiled map's index ([`TiledMap::totals`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileTotals {
    /// Voxels.
    pub voxels: u64,
    /// Voxels above [`super::OCCUPIED_THRESHOLD`].
    pub occupied: u64,
    /// Bricks.
    pub bricks: u64,
    /// Memory every tile loaded would take (bytes).
    pub memory_bytes: u64,
    /// World bounds `[min, max]` of every tile's voxels (none when all are empty).
    pub bounds: Option<[[f64; 3]; 2]>,
}

/// A tiled map opened for reading: the index in memory, each tile read when asked.
#[derive(Clone, Debug)]
pub struct TiledMap {
    dir: PathBuf,
    index: TileIndex,
    grid: TileGrid,
    by_key: BTreeMap<TileKey, usize>,
}

impl TiledMap {
    /// Is `path` a tiled map (a folder with an index)?
    pub fn is_tiled(path: &Path) -> bool {
        path.is_dir() && path.join(INDEX_FILE).is_file()
    }

    /// Opens the tiled map in folder `dir`: reads and checks its index (not its tiles).
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join(INDEX_FILE);
        let index = TileIndex::from_toml(&crate::error::read_text(&path)?, &path)?;
        let grid = TileGrid::new(index.tile_edge, index.resolution)
            .and_then(|g| g.with_height(index.tile_height))
            .expect("checked by from_toml");
        let by_key = index.tiles.iter().enumerate().map(|(i, t)| (TileKey(t.key), i)).collect();
        Ok(TiledMap { dir: dir.to_path_buf(), index, grid, by_key })
    }

    /// The index.
    pub fn index(&self) -> &TileIndex {
        &self.index
    }

    /// How space is cut.
    pub fn grid(&self) -> &TileGrid {
        &self.grid
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The index entry of tile `key`, if the map has it.
    pub fn entry(&self, key: TileKey) -> Option<&TileEntry> {
        self.by_key.get(&key).map(|&i| &self.index.tiles[i])
    }

    /// Sums over the index (what `mrfmap info` says without reading a tile).
    pub fn totals(&self) -> TileTotals {
        let t = &self.index.tiles;
        let bounds = t.iter().filter_map(|e| e.bounds).fold(None, |acc: Option<[[f64; 3]; 2]>, [lo, hi]| {
            Some(match acc {
                None => [lo, hi],
                Some([a, b]) => [[0, 1, 2].map(|k| a[k].min(lo[k])), [0, 1, 2].map(|k| b[k].max(hi[k]))],
            })
        });
        TileTotals {
            voxels: t.iter().map(|e| e.voxels).sum(),
            occupied: t.iter().map(|e| e.occupied).sum(),
            bricks: t.iter().map(|e| e.bricks).sum(),
            memory_bytes: t.iter().map(|e| e.memory_bytes).sum(),
            bounds,
        }
    }

    /// A map with the index's header and no voxels.
    pub fn empty_map(&self) -> Map {
        let mut map = Map::new(self.index.engine, self.index.resolution).expect("resolution checked at open");
        map.has_variance = self.index.has_variance;
        map.params = self.index.params.clone();
        map
    }

    /// Reads tile `key` (`None` when the map has no such tile), checking that the file
    /// belongs to this map: same engine and resolution, voxels inside the tile.
    pub fn load_tile(&self, key: TileKey) -> Result<Option<Map>> {
        let Some(entry) = self.entry(key) else { return Ok(None) };
        let path = self.dir.join(&entry.file);
        let map = Map::load(&path)?;
        let bad = |m: String| Error::file(&path, m);
        if map.engine != self.index.engine || map.resolution() != self.index.resolution {
            return Err(bad(format!(
                "tile of engine {} at {} m in a map of engine {} at {} m",
                map.engine,
                map.resolution(),
                self.index.engine,
                self.index.resolution
            )));
        }
        if let Some((brick, _)) = map.voxels.bricks().find(|(b, _)| self.grid.tile_of_brick(**b) != key) {
            return Err(bad(format!("brick {:?} lies outside tile {:?}", brick.0, key.0)));
        }
        Ok(Some(map))
    }

    /// The tiles `keys` (those the map has) stitched into one map, after checking that their
    /// memory (as the index records it) is within the limit.
    pub fn load(&self, keys: &[TileKey]) -> Result<Map> {
        let entries: Vec<&TileEntry> = keys.iter().filter_map(|k| self.entry(*k)).collect();
        let memory: f64 = entries.iter().map(|e| e.memory_bytes as f64).sum();
        crate::limits::check_memory(
            &format!("loading {} tiles of {}", entries.len(), self.dir.display()),
            memory,
            "load a region: `mrfmap crop` or `mrfmap query` read only the tiles they touch",
        )?;
        let mut map = self.empty_map();
        for key in keys {
            if let Some(tile) = self.load_tile(*key)? {
                map.voxels.absorb(tile.voxels);
                // The index's sizes may be wrong (or forged): what the tiles hold is checked
                // too, so loading stops within a tile of the limit.
                crate::limits::check_memory(
                    &format!("loading the tiles of {}", self.dir.display()),
                    map.voxels.memory_bytes() as f64,
                    "load a region: `mrfmap crop` or `mrfmap query` read only the tiles they touch",
                )?;
            }
        }
        Ok(map)
    }

    /// Every tile stitched into one map.
    pub fn load_all(&self) -> Result<Map> {
        self.load(&self.by_key.keys().copied().collect::<Vec<_>>())
    }

    /// The tiles holding a voxel that overlaps `region`, stitched into one map.
    pub fn load_region(&self, region: &Aabb) -> Result<Map> {
        let keys: Vec<TileKey> = match self.grid.overlapping(region, self.by_key.len().max(1) * 8) {
            Ok(keys) => keys.into_iter().filter(|k| self.by_key.contains_key(k)).collect(),
            // A box over more tiles than the map has: pick the map's tiles inside it.
            Err(_) => {
                let (lo, hi) = box_keys(region, self.index.resolution);
                let (lo, hi) = (self.grid.tile_of(VoxelKey(lo)).0, self.grid.tile_of(VoxelKey(hi)).0);
                self.by_key.keys().copied().filter(|k| (0..3).all(|a| k.0[a] >= lo[a] && k.0[a] <= hi[a])).collect()
            }
        };
        self.load(&keys)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::MapVoxel;

    fn map_with(keys: &[[i32; 3]]) -> Map {
        let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        for (i, k) in keys.iter().enumerate() {
            map.voxels.insert(VoxelKey(*k), MapVoxel { occupancy: 0.1 * (i % 10) as f32, variance: 0.0 });
        }
        map
    }

    #[test]
    fn tiles_round_trip_and_stitch() {
        let tmp = tempfile::tempdir().unwrap();
        let grid = TileGrid::new(1.6, 0.1).unwrap();
        let keys = [[0, 0, 0], [15, 15, 15], [16, 0, 0], [-1, -17, 3], [40, 2, -30]];
        let whole = map_with(&keys);
        let mut index = TileIndex::new(EngineKind::LogOdds, &grid, false, BTreeMap::new());
        let mut tiles: BTreeMap<TileKey, Map> = BTreeMap::new();
        for (k, v) in whole.voxels.iter() {
            let t = grid.tile_of(k);
            tiles.entry(t).or_insert_with(|| Map::new(EngineKind::LogOdds, 0.1).unwrap()).voxels.insert(k, *v);
        }
        assert_eq!(tiles.len(), 4, "two voxels share tile 0");
        for (t, m) in &tiles {
            index.tiles.push(TileIndex::save_tile(tmp.path(), &grid, *t, m, 1).unwrap());
        }
        // A tile written into the wrong key is refused.
        let wrong = TileIndex::save_tile(tmp.path(), &grid, TileKey([9, 9, 9]), &tiles[&TileKey([0, 0, 0])], 1);
        assert!(wrong.unwrap_err().to_string().contains("outside"));
        index.save(tmp.path()).unwrap();
        assert!(TiledMap::is_tiled(tmp.path()));
        let tiled = TiledMap::open(tmp.path()).unwrap();
        let all = tiled.load_all().unwrap();
        assert_eq!(all.voxels.len(), whole.voxels.len());
        for (k, v) in whole.voxels.iter() {
            assert_eq!(all.voxels.get(k), Some(v));
        }
        // A region opens only its tiles.
        let part = tiled.load_region(&Aabb::new([0.0; 3], [1.0; 3]).unwrap()).unwrap();
        assert_eq!(part.voxels.len(), 2);
        // Map::load reads a tiled folder whole.
        assert_eq!(Map::load(tmp.path()).unwrap().voxels.len(), 5);
    }

    #[test]
    fn bad_indexes_are_named() {
        let tmp = tempfile::tempdir().unwrap();
        let grid = TileGrid::new(0.8, 0.1).unwrap();
        let mut index = TileIndex::new(EngineKind::LogOdds, &grid, false, BTreeMap::new());
        index.tiles.push(TileEntry {
            key: [0, 0, 0],
            file: "../elsewhere.mrfmap".into(),
            voxels: 0,
            occupied: 0,
            bricks: 0,
            memory_bytes: 0,
            frames: 0,
            bounds: None,
        });
        index.save(tmp.path()).unwrap();
        let e = TiledMap::open(tmp.path()).unwrap_err().to_string();
        assert!(e.contains("tiles.toml") && e.contains("not a name inside"), "{e}");
        index.tiles[0].file = "tile_0_0_0.mrfmap".into();
        index.save(tmp.path()).unwrap();
        let e = TiledMap::open(tmp.path()).unwrap().load_all().unwrap_err().to_string();
        assert!(e.contains("tile_0_0_0.mrfmap"), "{e}");
        index.tile_edge = 0.85;
        index.save(tmp.path()).unwrap();
        let e = TiledMap::open(tmp.path()).unwrap_err().to_string();
        assert!(e.contains("whole number of bricks"), "{e}");
        // A broken index names its file; a folder without one is not a map.
        std::fs::write(tmp.path().join(INDEX_FILE), "format = \"mrfmap-tiles\"\nversion = [").unwrap();
        let e = TiledMap::open(tmp.path()).unwrap_err().to_string();
        assert!(e.contains("tiles.toml"), "{e}");
        std::fs::remove_file(tmp.path().join(INDEX_FILE)).unwrap();
        assert!(!TiledMap::is_tiled(tmp.path()));
        assert!(Map::load(tmp.path()).is_err());
    }
}
