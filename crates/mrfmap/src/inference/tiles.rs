//! Building a map in tiles ([`crate::map::TiledMap`]): each tile is built from the frames that
//! can reach it, alone, with the map's bounds at the tile (plus a margin), and cut to the tile.
//! Tiles are independent, so they can be built one after another in a small process, or on
//! many machines at once (the Python package's `mrfmap.distributed`).
//!
//! - [`Tiling::plan`] reads each frame once and lists, per tile, the frames some ray of which
//!   crosses it ([`Tiling::tiles_reached`]).
//! - [`Tiling::build`] builds one tile: the tile's frames in order into an engine that keeps
//!   only the tile's box grown by the margin, then only the tile's bricks kept.
//!
//! **Log-odds tiles are exact** (the union of the tiles is the map built in one process,
//! voxel for voxel, tested): a voxel's log-odds is the sum, in frame order, of the updates of
//! the rays that cross it or end in it; every such ray belongs to a frame the tile gets, and a
//! tile's engine traces every ray exactly as the whole build does and only stores fewer voxels
//! ([`super::LogOddsParams::keep`]). (Cutting the rays at the tile instead changed 26 of 25
//! million voxels on the simulated floor: a cut ray starts its traversal at the cut, and
//! rounding then decides a few edge-grazing voxels differently.) MRF and CRM tiles are
//! approximations at their borders: their engines are bounded to the tile's box grown by the
//! margin, so a ray loses the voxels outside it (CRM's update along a ray reads them) and
//! joint inference across the border (the MRF) is cut; the margin moves that error away from
//! the tile's voxels.

use std::borrow::Borrow;
use std::collections::BTreeMap;
use std::path::Path;

use super::{EngineConfig, EngineKind, new_engine};
use crate::error::{Error, Result};
use crate::frames::Frame;
use crate::map::{Aabb, Map, TileEntry, TileGrid, TileIndex, TileKey};
use crate::rays::{frame_crosses, frame_reach};

/// Frames decoded for a tile's memory estimate, at most.
const ESTIMATE_SAMPLES: usize = 8;

/// Most tiles one frame may reach (a frame reaching more is an error: the tiles are far too
/// small for the sensor's range).
const MAX_TILES_PER_FRAME: usize = 1 << 16;

/// The margin a tile is built with by default: none for log-odds (its tiles are exact
/// without one), a metre for MRF and CRM, whose rays carry information along their length
/// (with it their tiled maps score within 0.00001 of the whole map on the simulated floor,
/// RESULTS.md "Tiled maps"; smaller margins are not measured).
pub fn default_margin(kind: EngineKind) -> f64 {
    match kind {
        EngineKind::LogOdds => 0.0,
        EngineKind::Mrf | EngineKind::Crm => 1.0,
    }
}

/// How a map is cut into tiles and how much space around each tile its build sees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tiling {
    /// The tiles.
    pub grid: TileGrid,
    /// Metres around a tile that its build maps too (then cut away).
    pub margin: f64,
}

/// One tile, built.
#[derive(Debug)]
pub struct TileBuild {
    /// The tile's voxels.
    pub map: Map,
    /// Frames integrated.
    pub frames: usize,
}

impl Tiling {
    /// Tiles of `edge` metres in x and y (columns, or layers of `height` metres) for maps at
    /// `config`'s resolution, built with `margin` metres around them (default
    /// [`default_margin`]).
    pub fn new(config: &EngineConfig, edge: f64, height: Option<f64>, margin: Option<f64>) -> Result<Self> {
        let grid = TileGrid::new(edge, config.resolution)?.with_height(height)?;
        let margin = margin.unwrap_or_else(|| default_margin(config.kind));
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(Error::Invalid(format!("the tile margin must be 0 or more metres, got {margin}")));
        }
        Ok(Tiling { grid, margin })
    }

    /// The box tile `key` is built in: its own grown by the margin, within the map's bounds
    /// (`None` when the bounds leave nothing of the tile).
    pub fn build_box(&self, config: &EngineConfig, key: TileKey) -> Option<Aabb> {
        let tile = self.grid.bounds(key);
        if let Some(b) = &config.limits.bounds
            && (0..3).any(|a| b.max[a] <= tile.min[a] || b.min[a] >= tile.max[a])
        {
            return None;
        }
        let mut grown = Aabb { min: tile.min.map(|x| x - self.margin), max: tile.max.map(|x| x + self.margin) };
        if let Some(b) = &config.limits.bounds {
            grown.min = [0, 1, 2].map(|a| grown.min[a].max(b.min[a]));
            grown.max = [0, 1, 2].map(|a| grown.max[a].min(b.max[a]));
        }
        Some(grown)
    }

    /// The configuration tile `key` is built with: `config` keeping its build box (log-odds:
    /// rays traced whole, voxels outside not stored) or bounded to it (MRF, CRM: rays cut).
    pub fn tile_config(&self, config: &EngineConfig, key: TileKey) -> Option<EngineConfig> {
        let bounds = self.build_box(config, key)?;
        let mut tile = *config;
        match config.kind {
            EngineKind::LogOdds => tile.logodds.keep = Some(bounds),
            EngineKind::Mrf | EngineKind::Crm => tile.limits.bounds = Some(bounds),
        }
        Some(tile)
    }

    /// The configuration whose memory estimate ([`super::frames_extent`],
    /// [`super::estimate_memory`]) is tile `key`'s: bounded to its build box for every engine
    /// (log-odds traces rays beyond it, but stores nothing there).
    pub fn estimate_config(&self, config: &EngineConfig, key: TileKey) -> Option<EngineConfig> {
        let mut tile = self.tile_config(config, key)?;
        tile.limits.bounds = self.build_box(config, key);
        Some(tile)
    }

    /// The memory estimate (bytes) of building tile `key` from the frames `indices`: from
    /// every frame's pose (`pose`) and at most 8 frames spread over them (`frame` decodes
    /// one). 0 when the tile lies outside the bounds or sees nothing.
    pub fn estimate<F: Borrow<Frame>>(
        &self,
        config: &EngineConfig,
        key: TileKey,
        indices: &[usize],
        pose: impl Fn(usize) -> crate::frames::Pose,
        mut frame: impl FnMut(usize) -> Result<F>,
    ) -> Result<f64> {
        let Some(config) = self.estimate_config(config, key) else { return Ok(0.0) };
        let step = indices.len().div_ceil(ESTIMATE_SAMPLES).max(1);
        let sampled =
            indices.iter().step_by(step).map(|&i| Ok(frame(i)?.borrow().clone())).collect::<Result<Vec<_>>>()?;
        let extent = super::frames_extent(indices.iter().map(|&i| pose(i)), &sampled, &config);
        Ok(extent.map_or(0.0, |e| super::estimate_memory(&config, &e, super::MapOutput::InMemory)))
    }

    /// The tiles whose build box (grown by a voxel, so that a ray along a face counts) some
    /// ray of `frame` crosses: the tiles the box of its rays ([`frame_reach`]) overlaps, then
    /// each tested against every ray ([`frame_crosses`]).
    pub fn tiles_reached(&self, config: &EngineConfig, frame: &Frame) -> Result<Vec<TileKey>> {
        let forward_model = config.kind != EngineKind::LogOdds;
        let Some(reach) = frame_reach(frame, &config.limits, forward_model) else { return Ok(Vec::new()) };
        let pad = self.margin + self.grid.resolution();
        let grown = Aabb { min: reach.min.map(|x| x - pad), max: reach.max.map(|x| x + pad) };
        let keys = self.grid.overlapping(&grown, MAX_TILES_PER_FRAME).map_err(|e| {
            Error::Invalid(format!("{e}: one frame reaches that many tiles; use larger tiles or a --max-range"))
        })?;
        let r = self.grid.resolution();
        let (keys, boxes): (Vec<TileKey>, Vec<Aabb>) = keys
            .into_iter()
            .filter_map(|k| {
                let b = self.build_box(config, k)?;
                Some((k, Aabb { min: b.min.map(|x| x - r), max: b.max.map(|x| x + r) }))
            })
            .unzip();
        let crossed = frame_crosses(frame, &config.limits, forward_model, &boxes);
        Ok(keys.into_iter().zip(crossed).filter_map(|(k, c)| c.then_some(k)).collect())
    }

    /// Which frames reach which tile, each frame list in index order: every frame of
    /// `indices` read once (`frame` reads one; frames are read in parallel, as many at once
    /// as there are threads). Frames without a valid pixel reach nothing.
    pub fn plan(
        &self,
        config: &EngineConfig,
        indices: &[usize],
        frame: impl Fn(usize) -> Result<Frame> + Sync,
    ) -> Result<BTreeMap<TileKey, Vec<usize>>> {
        use rayon::prelude::*;
        let reached: Vec<(usize, Vec<TileKey>)> =
            indices.par_iter().map(|&i| Ok((i, self.tiles_reached(config, &frame(i)?)?))).collect::<Result<_>>()?;
        let mut plan: BTreeMap<TileKey, Vec<usize>> = BTreeMap::new();
        for (index, keys) in reached {
            for key in keys {
                plan.entry(key).or_default().push(index);
            }
        }
        Ok(plan)
    }

    /// Builds tile `key` from `frames` (its frames, in order): the engine bounded to the
    /// tile's build box, then cut to the tile.
    pub fn build<F: Borrow<Frame>>(
        &self,
        config: &EngineConfig,
        key: TileKey,
        frames: impl Iterator<Item = Result<F>>,
    ) -> Result<TileBuild> {
        let tile_config = self.tile_config(config, key).ok_or_else(|| {
            Error::Invalid(format!("tile {:?} lies outside the map's bounds: nothing to build", key.0))
        })?;
        let mut engine = new_engine(&tile_config)?;
        let mut count = 0;
        for frame in frames {
            engine.integrate(frame?.borrow())?;
            count += 1;
        }
        engine.finish()?;
        let mut map = engine.into_map();
        map.voxels.retain_bricks(|b| self.grid.tile_of_brick(b) == key);
        // Where the user's bounds cut the tile, voxels beyond them go too (the engine's box
        // was grown by the margin).
        if let Some(b) = &config.limits.bounds {
            map = map.crop(b);
        }
        Ok(TileBuild { map, frames: count })
    }
}

impl Tiling {
    /// [`Tiling::build`] tile `key` and write it into the tiled map's folder `dir`
    /// ([`TileIndex::save_tile`]); returns its index entry and its map's parameters (what the
    /// index records once for all tiles).
    pub fn build_into<F: Borrow<Frame>>(
        &self,
        dir: &Path,
        config: &EngineConfig,
        key: TileKey,
        frames: impl Iterator<Item = Result<F>>,
    ) -> Result<(TileEntry, BTreeMap<String, String>)> {
        let built = self.build(config, key, frames)?;
        let entry = TileIndex::save_tile(dir, &self.grid, key, &built.map, built.frames as u64)?;
        Ok((entry, built.map.params))
    }

    /// An index for tiles built with `config`: the engine, the grid, the tiles' parameters
    /// (`params`) and the margin; no tiles yet.
    pub fn index(&self, config: &EngineConfig, mut params: BTreeMap<String, String>) -> TileIndex {
        params.insert("tile_margin".into(), self.margin.to_string());
        TileIndex::new(config.kind, &self.grid, config.kind == EngineKind::Crm, params)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::{Camera, DepthImage, look_at};
    use nalgebra::Vector3;

    fn frame(index: usize, eye: [f64; 3], target: [f64; 3], depth: f32) -> Frame {
        let camera = Camera::new(40.0, 40.0, 19.5, 14.5, 40, 30, 5000.0).unwrap();
        let mut image = DepthImage::new(40, 30);
        for v in 0..30 {
            for u in 0..40 {
                image.set(u, v, depth + 0.01 * ((u * 7 + v * 3) % 11) as f32);
            }
        }
        let pose = look_at(Vector3::from(eye), Vector3::from(target)).unwrap();
        Frame { index, timestamp: index as f64, depth: image, pose, camera, noise: None }
    }

    #[test]
    fn log_odds_tiles_equal_the_whole_map() {
        use crate::inference::Marking;
        for marking in [Marking::Project, Marking::Walk, Marking::Centres] {
            let mut config = EngineConfig::new(EngineKind::LogOdds, 0.1);
            config.logodds.marking = marking;
            tiles_equal_whole(&config);
        }
        let config = EngineConfig::new(EngineKind::LogOdds, 0.1);
        assert!(Tiling::new(&config, 1.6, None, Some(-1.0)).unwrap_err().to_string().contains("margin"));
    }

    fn tiles_equal_whole(config: &EngineConfig) {
        let config = *config;
        let frames: Vec<Frame> = (0..6)
            .map(|i| {
                let a = i as f64 * 1.1;
                frame(i, [0.3 * a.cos() + 0.05, 0.3 * a.sin() - 0.02, 0.4], [3.0 * a.cos(), 3.0 * a.sin(), 0.2], 2.3)
            })
            .collect();
        let mut whole = new_engine(&config).unwrap();
        for f in &frames {
            whole.integrate(f).unwrap();
        }
        let whole = whole.map();
        let tiling = Tiling::new(&config, 1.6, Some(1.6), None).unwrap();
        let indices: Vec<usize> = (0..frames.len()).collect();
        let plan = tiling.plan(&config, &indices, |i| Ok(frames[i].clone())).unwrap();
        assert!(plan.len() >= 4, "{} tiles", plan.len());
        let mut union = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        for (key, indices) in &plan {
            let built = tiling.build(&config, *key, indices.iter().map(|&i| Ok(frames[i].clone()))).unwrap();
            assert!(built.map.voxels.bricks().all(|(b, _)| tiling.grid.tile_of_brick(*b) == *key));
            union.voxels.absorb(built.map.voxels);
        }
        assert_eq!(union.voxels.len(), whole.voxels.len());
        for (k, v) in whole.voxels.iter() {
            assert_eq!(union.voxels.get(k), Some(v), "voxel {k:?}");
        }
    }

    #[test]
    fn bounds_cut_tiles() {
        let mut config = EngineConfig::new(EngineKind::LogOdds, 0.1);
        config.limits.bounds = Some(Aabb::new([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]).unwrap());
        let tiling = Tiling::new(&config, 0.8, Some(0.8), None).unwrap();
        assert!(tiling.build_box(&config, TileKey([5, 0, 0])).is_none());
        let b = tiling.build_box(&config, TileKey([1, 0, 0])).unwrap();
        assert_eq!((b.min[0], b.max[0]), (0.8, 1.0));
    }
}
