//! Queries a planner asks of a map: how likely is this point occupied, is this path free,
//! what is in this box — each with how sure the map is.
//!
//! Every engine answers through [`VoxelSource`]: a finished [`Map`] (fast, brick-cached) or a
//! running engine ([`LiveEngine`], read voxel by voxel without building a map). A voxel's
//! belief is its occupancy `p` and standard deviation `sigma` ([`MapVoxel::mean_sigma`]: CRM's
//! own variance, the Bernoulli `p (1 - p)` for log-odds and the MRF). Space the map knows
//! nothing about is answered with the settable prior [`QueryOptions::unknown`] `P` and
//! `sigma = sqrt(P (1 - P))`.
//!
//! - points ([`query_point`]): occupancy, sigma, known;
//! - segments ([`query_segment`]): over the voxels the segment crosses with positive length
//!   (the exact traversal of [`for_each_crossing`]), the probability that all are free
//!   `prod (1 - p_i)` (voxels independent, as every engine here assumes), the expected number
//!   of occupied voxels `sum p_i`, the same probability with each `p_i` raised to the
//!   confidence bound `min(1, p_i + k sigma_i)` (the CRM paper's planner, sec. 6), and the
//!   first voxel above the occupancy threshold;
//! - polylines ([`query_polyline`]): the same over the union of the legs' voxels;
//! - boxes ([`query_box`]): over the voxels that overlap the box with positive volume, the
//!   largest occupancy, the probability that all are free, and counts of occupied, free and
//!   unknown voxels (unknown ones counted, not visited).
//!
//! The batch forms ([`query_points`], [`query_segments`]) run in parallel and allocate
//! nothing per voxel.

use std::ops::ControlFlow;
use std::sync::{Arc, Mutex};

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use crate::error::{Error, Result};
use crate::inference::Engine;
use crate::map::{Aabb, TileKey, TiledMap, box_keys};
use crate::map::{BRICK_EDGE, Brick, BrickKey, Map, MapVoxel, OCCUPIED_THRESHOLD, VoxelKey};
use crate::rays::for_each_crossing;

/// Something voxels can be read from: a [`Map`] or a running engine ([`LiveEngine`]).
pub trait VoxelSource: Sync {
    /// Voxel edge in metres.
    fn resolution(&self) -> f64;
    /// True when [`MapVoxel::variance`] is meaningful (CRM).
    fn has_variance(&self) -> bool;
    /// One voxel; `None` where the source knows nothing.
    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel>;
    /// A lookup for one thread's run of nearby keys (a segment's voxels). The default looks
    /// every key up; a map remembers the last brick, since consecutive voxels of a segment
    /// mostly share one.
    fn lookup(&self) -> impl FnMut(VoxelKey) -> Option<MapVoxel> + '_ {
        move |key| self.voxel(key)
    }
}

impl VoxelSource for Map {
    fn resolution(&self) -> f64 {
        Map::resolution(self)
    }

    fn has_variance(&self) -> bool {
        self.has_variance
    }

    #[inline]
    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.voxels.get(key).copied()
    }

    fn lookup(&self) -> impl FnMut(VoxelKey) -> Option<MapVoxel> + '_ {
        // No real brick has this key (voxel keys are i32, bricks are keys >> 3).
        let mut last_key = BrickKey([i32::MIN; 3]);
        let mut last: Option<&Brick<MapVoxel>> = None;
        #[inline(always)]
        move |key: VoxelKey| {
            let bk = key.brick();
            if bk != last_key {
                last_key = bk;
                last = self.voxels.brick(bk);
            }
            last?.get(key.slot()).copied()
        }
    }
}

/// A tiled map as a [`VoxelSource`] that reads each tile the first time a query reads one of
/// its voxels: a query over a few metres of a large map opens the few tiles it crosses. A
/// tile that fails to load (or would take the memory over the limit) reads as unknown and
/// the error is kept for [`LazyTiles::finish`], which the caller must check.
pub struct LazyTiles<'a> {
    map: &'a TiledMap,
    tiles: Mutex<FxHashMap<TileKey, Option<Arc<Map>>>>,
    state: Mutex<(u64, Option<Error>)>,
}

impl<'a> LazyTiles<'a> {
    /// No tile read yet.
    pub fn new(map: &'a TiledMap) -> Self {
        LazyTiles { map, tiles: Mutex::new(FxHashMap::default()), state: Mutex::new((0, None)) }
    }

    fn tile(&self, key: TileKey) -> Option<Arc<Map>> {
        let mut tiles = self.tiles.lock().expect("no panics under the lock");
        if let Some(t) = tiles.get(&key) {
            return t.clone();
        }
        let loaded = self.map.entry(key).and_then(|entry| {
            let mut state = self.state.lock().expect("no panics under the lock");
            state.0 += entry.memory_bytes;
            let checked = crate::limits::check_memory(
                &format!("the tiles of {} a query reads", self.map.dir().display()),
                state.0 as f64,
                "query a smaller region",
            );
            match checked.and_then(|_| self.map.load_tile(key)) {
                Ok(tile) => tile.map(Arc::new),
                Err(e) => {
                    state.1.get_or_insert(e);
                    None
                }
            }
        });
        tiles.insert(key, loaded.clone());
        loaded
    }

    /// The tiles read (those the map has).
    pub fn opened(&self) -> usize {
        self.tiles.lock().expect("no panics under the lock").values().filter(|t| t.is_some()).count()
    }

    /// The tiles read, or the first error reading one.
    pub fn finish(self) -> Result<usize> {
        let opened = self.opened();
        match self.state.into_inner().expect("no panics under the lock").1 {
            Some(e) => Err(e),
            None => Ok(opened),
        }
    }
}

impl VoxelSource for LazyTiles<'_> {
    fn resolution(&self) -> f64 {
        self.map.index().resolution
    }

    fn has_variance(&self) -> bool {
        self.map.index().has_variance
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.tile(self.map.grid().tile_of(key))?.voxels.get(key).copied()
    }

    fn lookup(&self) -> impl FnMut(VoxelKey) -> Option<MapVoxel> + '_ {
        // A segment's voxels stay in one tile for long runs: the tile is looked up (under the
        // lock) only when it changes.
        let mut last: Option<(TileKey, Option<Arc<Map>>)> = None;
        move |key: VoxelKey| {
            let tile = self.map.grid().tile_of(key);
            if last.as_ref().is_none_or(|(k, _)| *k != tile) {
                last = Some((tile, self.tile(tile)));
            }
            last.as_ref()?.1.as_ref()?.voxels.get(key).copied()
        }
    }
}

/// A running engine as a [`VoxelSource`]: queries read its live state voxel by voxel.
pub struct LiveEngine<'a>(pub &'a dyn Engine);

impl VoxelSource for LiveEngine<'_> {
    fn resolution(&self) -> f64 {
        self.0.resolution()
    }

    fn has_variance(&self) -> bool {
        self.0.has_variance()
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.0.voxel(key)
    }
}

/// How queries treat unknown space and confidence.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QueryOptions {
    /// Occupancy assumed where the map knows nothing (default 0.5).
    pub unknown: f64,
    /// Standard deviations added to each voxel's occupancy for the confidence bound (default 2).
    pub k: f64,
    /// Occupancy above which a voxel is occupied (default [`OCCUPIED_THRESHOLD`]).
    pub threshold: f64,
}

impl Default for QueryOptions {
    fn default() -> Self {
        QueryOptions { unknown: 0.5, k: 2.0, threshold: OCCUPIED_THRESHOLD as f64 }
    }
}

impl QueryOptions {
    /// Checks the options: probabilities in `[0, 1]`, `k >= 0`, all finite.
    pub fn validate(&self) -> Result<()> {
        if !((0.0..=1.0).contains(&self.unknown) && (0.0..=1.0).contains(&self.threshold)) {
            return Err(Error::Invalid(format!(
                "unknown occupancy and threshold are probabilities in [0, 1], got {} and {}",
                self.unknown, self.threshold
            )));
        }
        if !(self.k >= 0.0 && self.k.is_finite()) {
            return Err(Error::Invalid(format!("k must be a finite number >= 0, got {}", self.k)));
        }
        Ok(())
    }

    /// Occupancy, sigma and whether it is known, for a voxel or unknown space.
    #[inline]
    fn belief(&self, voxel: Option<MapVoxel>, has_variance: bool) -> (f64, f64, bool) {
        match voxel {
            Some(v) => {
                let (p, sigma) = v.mean_sigma(has_variance);
                (p, sigma, true)
            }
            None => (self.unknown, (self.unknown * (1.0 - self.unknown)).sqrt(), false),
        }
    }
}

/// What the map says at a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointAnswer {
    /// Occupancy probability (the unknown prior where not known).
    pub occupancy: f64,
    /// Its standard deviation.
    pub sigma: f64,
    /// False where the map knows nothing.
    pub known: bool,
}

/// What the map says about a straight path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentAnswer {
    /// Probability that every crossed voxel is free: `prod (1 - p_i)`.
    pub p_free: f64,
    /// Expected number of occupied voxels: `sum p_i`.
    pub expected_occupied: f64,
    /// `prod (1 - min(1, p_i + k sigma_i))`: a lower confidence bound on `p_free`.
    pub p_free_lcb: f64,
    /// Centre of the first voxel above the threshold, if any.
    pub first_hit: Option<[f64; 3]>,
    /// Voxels crossed with positive length.
    pub voxels: u32,
    /// How many of them are unknown.
    pub unknown: u32,
}

impl SegmentAnswer {
    /// A path through no voxel: certainly free.
    pub const EMPTY: SegmentAnswer =
        SegmentAnswer { p_free: 1.0, expected_occupied: 0.0, p_free_lcb: 1.0, first_hit: None, voxels: 0, unknown: 0 };
}

/// What the map says about an axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxAnswer {
    /// Largest occupancy of any voxel in the box (unknown voxels at the prior).
    pub max_occupancy: f64,
    /// Probability that every voxel of the box is free.
    pub p_free: f64,
    /// Known voxels above the threshold.
    pub occupied: u64,
    /// Known voxels at or below the threshold.
    pub free: u64,
    /// Voxels the map knows nothing about.
    pub unknown: u64,
}

/// The map's belief at a point.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{QueryOptions, query_point};
/// let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// let a = query_point(&map, [0.05, 0.05, 0.05], &QueryOptions::default());
/// assert!(a.known && a.occupancy == 0.8999999761581421 && (a.sigma - 0.3).abs() < 1e-6);
/// assert!(!query_point(&map, [1.0, 0.0, 0.0], &QueryOptions::default()).known);
/// ```
pub fn query_point(source: &impl VoxelSource, p: [f64; 3], options: &QueryOptions) -> PointAnswer {
    let key = VoxelKey::from_point(p, source.resolution());
    let (occupancy, sigma, known) = options.belief(source.voxel(key), source.has_variance());
    PointAnswer { occupancy, sigma, known }
}

/// [`query_point`] for many points, in parallel.
pub fn query_points(source: &impl VoxelSource, points: &[[f64; 3]], options: &QueryOptions) -> Vec<PointAnswer> {
    points.par_iter().with_min_len(4096).map(|p| query_point(source, *p, options)).collect()
}

/// Longest path, in voxels walked, that [`check_path`] lets through: a second or two of
/// walking; anything longer is far outside every map this library can hold.
pub const MAX_PATH_VOXELS: f64 = 1e7;

/// Refuses a path (a segment's two ends, or a polyline's points) that [`query_segment`] or
/// [`query_polyline`] could not answer in reasonable time or at all: a coordinate that is not
/// finite, a leg whose length overflows, or more than [`MAX_PATH_VOXELS`] voxels to walk at
/// `resolution` (a segment between points 10^9 m apart would walk for minutes, voxel by unknown
/// voxel). The front ends call it before they query.
///
/// ```
/// use mrfmap::outputs::check_path;
/// assert!(check_path(&[[0.0; 3], [10.0, 0.0, 0.0]], 0.05).is_ok());
/// assert!(check_path(&[[-1e9, 0.0, 0.0], [1e9, 0.0, 0.0]], 0.05).is_err());
/// assert!(check_path(&[[-1e308, 0.0, 0.0], [1e308, 0.0, 0.0]], 0.05).is_err());
/// ```
pub fn check_path(points: &[[f64; 3]], resolution: f64) -> Result<()> {
    if let Some(p) = points.iter().find(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(Error::Invalid(format!("path point {p:?} is not finite")));
    }
    // A segment crosses at most one voxel per grid plane it passes, plus its first.
    let walked: f64 = points
        .windows(2)
        .map(|leg| 1.0 + (0..3).map(|a| (leg[1][a] - leg[0][a]).abs() / resolution).sum::<f64>())
        .sum();
    if !(walked <= MAX_PATH_VOXELS) {
        let length: f64 =
            points.windows(2).map(|l| (0..3).map(|a| (l[1][a] - l[0][a]).powi(2)).sum::<f64>().sqrt()).sum();
        return Err(Error::Invalid(format!(
            "a path of {length:.3e} m crosses up to {walked:.3e} voxels of {resolution} m; at most {MAX_PATH_VOXELS:.0e} \
             are walked: clip it to the region you plan in"
        )));
    }
    Ok(())
}

/// The map's belief along the segment from `a` to `b`.
///
/// A segment of zero length crosses no voxel: it is free with probability 1.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{QueryOptions, query_segment};
/// let mut map = Map::new(EngineKind::LogOdds, 1.0).unwrap();
/// for (x, p) in [(0, 0.1), (1, 0.2), (2, 0.9)] {
///     map.voxels.insert(VoxelKey([x, 0, 0]), MapVoxel { occupancy: p, variance: 0.0 });
/// }
/// let opts = QueryOptions { k: 0.0, ..Default::default() };
/// let a = query_segment(&map, [0.5, 0.5, 0.5], [2.5, 0.5, 0.5], &opts);
/// assert!((a.p_free - 0.9 * 0.8 * 0.1).abs() < 1e-6 && a.p_free_lcb == a.p_free);
/// assert_eq!((a.voxels, a.unknown, a.first_hit), (3, 0, Some([2.5, 0.5, 0.5])));
/// ```
pub fn query_segment(source: &impl VoxelSource, a: [f64; 3], b: [f64; 3], options: &QueryOptions) -> SegmentAnswer {
    segment_with(&mut source.lookup(), source.resolution(), source.has_variance(), a, b, options)
}

fn segment_with(
    lookup: &mut impl FnMut(VoxelKey) -> Option<MapVoxel>,
    resolution: f64,
    has_variance: bool,
    a: [f64; 3],
    b: [f64; 3],
    options: &QueryOptions,
) -> SegmentAnswer {
    let mut answer = SegmentAnswer::EMPTY;
    accumulate(lookup, resolution, has_variance, a, b, options, &mut answer, |_| true);
    answer
}

/// Adds the voxels that `a -> b` crosses and `fresh` accepts to `answer`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn accumulate(
    lookup: &mut impl FnMut(VoxelKey) -> Option<MapVoxel>,
    resolution: f64,
    has_variance: bool,
    a: [f64; 3],
    b: [f64; 3],
    options: &QueryOptions,
    answer: &mut SegmentAnswer,
    mut fresh: impl FnMut(VoxelKey) -> bool,
) {
    let dir = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    // A segment ending on a voxel face can, by rounding, touch the next voxel for ~1e-16 m
    // (`for_each_crossing`'s exactness notes); such slivers are not "positive length".
    let sliver = 1e-9 * resolution / (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    // Products of (1 - p) run as products, not log sums: no log per voxel, and a long path
    // through occupied space underflows to 0, which is the right answer.
    // `inline(always)` here and on the map's lookup: left to the compiler, both closures
    // stayed calls and 1 m segment queries ran at 1.8 M/s instead of 3.5 M/s (cargo bench).
    for_each_crossing(
        a,
        dir,
        0.0,
        1.0,
        resolution,
        #[inline(always)]
        |c| {
            if c.length() < sliver || !fresh(c.key) {
                return ControlFlow::Continue(());
            }
            let (p, sigma, known) = options.belief(lookup(c.key), has_variance);
            answer.p_free *= 1.0 - p;
            answer.p_free_lcb *= 1.0 - (p + options.k * sigma).min(1.0);
            answer.expected_occupied += p;
            answer.voxels += 1;
            answer.unknown += !known as u32;
            if answer.first_hit.is_none() && p > options.threshold {
                answer.first_hit = Some(c.key.center(resolution));
            }
            ControlFlow::Continue(())
        },
    );
}

/// The map's belief along a polyline through `points`: as [`query_segment`] over every voxel
/// the path crosses with positive length, each counted once even where the path crosses it
/// again (at a waypoint, or coming back). Fewer than two points: an empty path.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{QueryOptions, query_polyline};
/// let mut map = Map::new(EngineKind::LogOdds, 1.0).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.5, variance: 0.0 });
/// // Out and back through one voxel, which counts once.
/// let path = [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [0.2, 0.5, 0.5]];
/// let a = query_polyline(&map, &path, &QueryOptions { unknown: 0.0, ..Default::default() });
/// assert_eq!((a.voxels, a.p_free), (2, 0.5));
/// ```
pub fn query_polyline(source: &impl VoxelSource, points: &[[f64; 3]], options: &QueryOptions) -> SegmentAnswer {
    let (r, v) = (source.resolution(), source.has_variance());
    let mut lookup = source.lookup();
    let mut answer = SegmentAnswer::EMPTY;
    // Sized once from the path's length (a segment crosses at most 3 voxels per voxel edge it
    // advances), so the set does not grow voxel by voxel.
    let length: f64 = points.windows(2).map(|l| (0..3).map(|a| (l[1][a] - l[0][a]).abs()).sum::<f64>()).sum();
    let bound = (length / r) as usize + 3 * points.len();
    let mut seen = rustc_hash::FxHashSet::with_capacity_and_hasher(bound.min(1 << 20), Default::default());
    for leg in points.windows(2) {
        accumulate(&mut lookup, r, v, leg[0], leg[1], options, &mut answer, |k| seen.insert(k));
    }
    answer
}

/// [`query_segment`] for many segments `(a, b)`, in parallel.
pub fn query_segments(
    source: &impl VoxelSource,
    segments: &[([f64; 3], [f64; 3])],
    options: &QueryOptions,
) -> Vec<SegmentAnswer> {
    let (r, v) = (source.resolution(), source.has_variance());
    segments
        .par_iter()
        .with_min_len(256)
        .map_init(|| source.lookup(), |lookup, (a, b)| segment_with(lookup, r, v, *a, *b, options))
        .collect()
}

/// Calls `visit(key, voxel)` for every voxel overlapping `region` with positive volume, and
/// returns how many of them are unknown (those are counted, not visited).
pub fn for_each_in_box(source: &impl VoxelSource, region: &Aabb, mut visit: impl FnMut(VoxelKey, MapVoxel)) -> u64 {
    let (lo, hi) = box_keys(region, source.resolution());
    let blo = lo.map(|i| i >> 3);
    let bhi = hi.map(|i| i >> 3);
    let mut unknown = 0u64;
    let mut lookup = source.lookup();
    for bz in blo[2]..=bhi[2] {
        for by in blo[1]..=bhi[1] {
            for bx in blo[0]..=bhi[0] {
                let bk = [bx, by, bz];
                // This brick's part of the box.
                let from = [0, 1, 2].map(|a| lo[a].max(bk[a] * BRICK_EDGE));
                let to = [0, 1, 2].map(|a| hi[a].min(bk[a] * BRICK_EDGE + BRICK_EDGE - 1));
                for z in from[2]..=to[2] {
                    for y in from[1]..=to[1] {
                        for x in from[0]..=to[0] {
                            let key = VoxelKey([x, y, z]);
                            match lookup(key) {
                                Some(v) => visit(key, v),
                                None => unknown += 1,
                            }
                        }
                    }
                }
            }
        }
    }
    unknown
}

/// Number of voxels overlapping `region` with positive volume.
pub fn box_voxel_count(region: &Aabb, resolution: f64) -> u128 {
    let (lo, hi) = box_keys(region, resolution);
    (0..3).map(|a| (hi[a] as i64 - lo[a] as i64 + 1).max(0) as u128).product()
}

/// Most voxels a box query visits (about a second of work): beyond it, use a coarser map or a
/// smaller box.
pub const MAX_BOX_VOXELS: u128 = 200_000_000;

/// The map's belief about the voxels overlapping `region`.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{QueryOptions, query_box};
/// use mrfmap::map::Aabb;
/// let mut map = Map::new(EngineKind::LogOdds, 1.0).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.2, variance: 0.0 });
/// let region = Aabb::new([0.0; 3], [2.0, 1.0, 1.0]).unwrap(); // voxels [0,0,0] and [1,0,0]
/// let a = query_box(&map, &region, &QueryOptions::default()).unwrap();
/// assert_eq!((a.free, a.occupied, a.unknown), (1, 0, 1));
/// assert!((a.p_free - 0.8 * 0.5).abs() < 1e-6 && a.max_occupancy == 0.5);
/// ```
pub fn query_box(source: &impl VoxelSource, region: &Aabb, options: &QueryOptions) -> Result<BoxAnswer> {
    let n = box_voxel_count(region, source.resolution());
    if n > MAX_BOX_VOXELS {
        return Err(Error::Invalid(format!(
            "box {:?} to {:?} spans {n} voxels at {} m, more than {MAX_BOX_VOXELS} a box query may visit: \
             use a smaller box or a coarser map",
            region.min,
            region.max,
            source.resolution()
        )));
    }
    let has_variance = source.has_variance();
    let (mut occupied, mut free, mut max_occupancy, mut log_free) = (0u64, 0u64, f64::NEG_INFINITY, 0.0f64);
    let unknown = for_each_in_box(source, region, |_, v| {
        let (p, _, _) = options.belief(Some(v), has_variance);
        if p > options.threshold {
            occupied += 1;
        } else {
            free += 1;
        }
        max_occupancy = max_occupancy.max(p);
        log_free += (-p).ln_1p();
    });
    if unknown > 0 {
        max_occupancy = max_occupancy.max(options.unknown);
        log_free += unknown as f64 * (-options.unknown).ln_1p();
    }
    Ok(BoxAnswer { max_occupancy, p_free: log_free.exp(), occupied, free, unknown })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::EngineKind;
    use crate::random::Rng;

    /// A random map at `r` over `[-1, 1)^3` with about half the voxels known.
    fn random_map(r: f64, has_variance: bool, seed: u64) -> Map {
        let mut rng = Rng::new(seed);
        let mut map = Map::new(if has_variance { EngineKind::Crm } else { EngineKind::LogOdds }, r).unwrap();
        map.has_variance = has_variance;
        let n = (1.0 / r).round() as i32;
        for z in -n..n {
            for y in -n..n {
                for x in -n..n {
                    if rng.uniform() < 0.5 {
                        let p = rng.uniform() as f32;
                        let variance = if has_variance {
                            (rng.uniform() * 0.25 * p as f64 * (1.0 - p as f64)) as f32
                        } else {
                            0.0
                        };
                        map.voxels.insert(VoxelKey([x, y, z]), MapVoxel { occupancy: p, variance });
                    }
                }
            }
        }
        map
    }

    /// The voxels a segment crosses, found by sampling it finely: a voxel counts when at least
    /// two consecutive samples (so a positive length) lie in it. Samples are offset from
    /// the voxel grid's faces by construction of the random endpoints.
    fn sampled_voxels(a: [f64; 3], b: [f64; 3], r: f64) -> Vec<VoxelKey> {
        let n = 200_000;
        let mut keys: Vec<VoxelKey> = Vec::new();
        let mut run = 0;
        let mut last = None;
        for i in 0..=n {
            let t = i as f64 / n as f64;
            let k = VoxelKey::from_point([0, 1, 2].map(|j| a[j] + t * (b[j] - a[j])), r);
            if Some(k) == last {
                run += 1;
            } else {
                run = 1;
                last = Some(k);
            }
            if run == 2 && keys.last() != Some(&k) {
                keys.push(k);
            }
        }
        keys
    }

    #[test]
    fn segments_match_brute_force() {
        for has_variance in [false, true] {
            let map = random_map(0.1, has_variance, 7 + has_variance as u64);
            let opts = QueryOptions { unknown: 0.3, k: 1.5, threshold: 0.5 };
            let mut rng = Rng::new(11);
            for _ in 0..200 {
                let a = [0; 3].map(|_| rng.uniform() * 2.4 - 1.2);
                let b = [0; 3].map(|_| rng.uniform() * 2.4 - 1.2);
                let got = query_segment(&map, a, b, &opts);
                let keys = sampled_voxels(a, b, 0.1);
                let (mut p_free, mut lcb, mut expected, mut unknown, mut first) = (1.0, 1.0, 0.0, 0, None);
                for k in &keys {
                    let (p, sigma) = match map.voxels.get(*k) {
                        Some(v) => v.mean_sigma(has_variance),
                        None => {
                            unknown += 1;
                            (0.3, (0.3f64 * 0.7).sqrt())
                        }
                    };
                    p_free *= 1.0 - p;
                    lcb *= 1.0 - (p + 1.5 * sigma).min(1.0);
                    expected += p;
                    if first.is_none() && p > 0.5 {
                        first = Some(k.center(0.1));
                    }
                }
                assert_eq!(got.voxels as usize, keys.len(), "{a:?} -> {b:?}");
                assert_eq!(got.unknown, unknown);
                assert!((got.p_free - p_free).abs() < 1e-12 && (got.p_free_lcb - lcb).abs() < 1e-12);
                assert!((got.expected_occupied - expected).abs() < 1e-9);
                assert_eq!(got.first_hit, first);
                assert!(got.p_free_lcb <= got.p_free, "the bound is never above the mean");
            }
        }
    }

    #[test]
    fn polylines_count_each_voxel_once() {
        let map = random_map(0.1, true, 21);
        let opts = QueryOptions { unknown: 0.4, k: 1.0, threshold: 0.5 };
        let mut rng = Rng::new(8);
        for _ in 0..50 {
            let points: Vec<[f64; 3]> = (0..4).map(|_| [0; 3].map(|_| rng.uniform() * 1.6 - 0.8)).collect();
            let got = query_polyline(&map, &points, &opts);
            let mut keys: Vec<VoxelKey> = Vec::new();
            for leg in points.windows(2) {
                for k in sampled_voxels(leg[0], leg[1], 0.1) {
                    if !keys.contains(&k) {
                        keys.push(k);
                    }
                }
            }
            let (mut p_free, mut lcb) = (1.0, 1.0);
            for k in &keys {
                let (p, sigma, _) = opts.belief(map.voxels.get(*k).copied(), true);
                p_free *= 1.0 - p;
                lcb *= 1.0 - (p + sigma).min(1.0);
            }
            assert_eq!(got.voxels as usize, keys.len());
            assert!((got.p_free - p_free).abs() < 1e-12 && (got.p_free_lcb - lcb).abs() < 1e-12);
        }
        assert_eq!(query_polyline(&map, &[[0.0; 3]], &opts), SegmentAnswer::EMPTY);
    }

    #[test]
    fn segments_ending_on_faces_count_no_slivers() {
        let map = random_map(0.05, false, 2);
        let opts = QueryOptions::default();
        // 0.3 and 0.55 are faces at 0.05 m; rounding must not add a voxel at either end.
        let there = query_segment(&map, [0.0, 0.0, 0.55], [0.0, 0.0, 0.3], &opts);
        let back = query_segment(&map, [0.0, 0.0, 0.3], [0.0, 0.0, 0.55], &opts);
        assert_eq!((there.voxels, back.voxels), (5, 5));
        let round_trip = query_polyline(&map, &[[0.0, 0.0, 0.3], [0.0, 0.0, 0.55], [0.0, 0.0, 0.3]], &opts);
        assert_eq!(round_trip.voxels, 5);
    }

    #[test]
    fn segments_along_faces_and_inside_one_voxel() {
        let map = random_map(0.1, false, 3);
        let opts = QueryOptions::default();
        // Inside one voxel: just that voxel.
        let a = query_segment(&map, [0.01, 0.01, 0.01], [0.09, 0.02, 0.03], &opts);
        assert_eq!(a.voxels, 1);
        let (p, _, _) = opts.belief(map.voxels.get(VoxelKey([0, 0, 0])).copied(), false);
        assert!((a.p_free - (1.0 - p)).abs() < 1e-12);
        // Along the face y = 0 (exactly on the grid): the voxels on the y >= 0 side, one per step.
        let a = query_segment(&map, [0.05, 0.0, 0.05], [0.95, 0.0, 0.05], &opts);
        assert_eq!(a.voxels, 10);
        let expected: f64 = (0..10).map(|x| opts.belief(map.voxels.get(VoxelKey([x, 0, 0])).copied(), false).0).sum();
        assert!((a.expected_occupied - expected).abs() < 1e-9);
        // Zero length: nothing crossed.
        let a = query_segment(&map, [0.3; 3], [0.3; 3], &opts);
        assert_eq!((a.voxels, a.p_free), (0, 1.0));
    }

    #[test]
    fn batches_equal_single_queries_and_live_engines_equal_maps() {
        let map = random_map(0.1, true, 5);
        let opts = QueryOptions::default();
        let mut rng = Rng::new(2);
        let segs: Vec<_> = (0..3000)
            .map(|_| ([0; 3].map(|_| rng.uniform() * 2.0 - 1.0), [0; 3].map(|_| rng.uniform() * 2.0 - 1.0)))
            .collect();
        let batch = query_segments(&map, &segs, &opts);
        for (s, got) in segs.iter().zip(&batch) {
            assert_eq!(*got, query_segment(&map, s.0, s.1, &opts));
        }
        let pts: Vec<_> = segs.iter().map(|s| s.0).collect();
        for (p, got) in pts.iter().zip(query_points(&map, &pts, &opts)) {
            assert_eq!(got, query_point(&map, *p, &opts));
        }
    }

    #[test]
    fn boxes_match_enumeration() {
        let map = random_map(0.1, false, 9);
        let opts = QueryOptions { unknown: 0.2, ..Default::default() };
        let mut rng = Rng::new(4);
        for _ in 0..100 {
            let c = [0; 3].map(|_| rng.uniform() * 2.4 - 1.2);
            let e = [0; 3].map(|_| rng.uniform() * 0.9 + 0.001);
            let region = Aabb::new(c, [0, 1, 2].map(|a| c[a] + e[a])).unwrap();
            let got = query_box(&map, &region, &opts).unwrap();
            // Enumerate by voxel intervals: voxel i overlaps [min, max] with positive volume
            // when i r < max and (i + 1) r > min.
            let (mut occ, mut free, mut unk, mut maxp, mut pf) = (0, 0, 0, f64::NEG_INFINITY, 1.0);
            for z in -30..30 {
                for y in -30..30 {
                    for x in -30..30 {
                        let k = [x, y, z];
                        if !(0..3)
                            .all(|a| (k[a] as f64) * 0.1 < region.max[a] && (k[a] as f64 + 1.0) * 0.1 > region.min[a])
                        {
                            continue;
                        }
                        let p = match map.voxels.get(VoxelKey(k)) {
                            Some(v) if v.occupancy as f64 > 0.5 => {
                                occ += 1;
                                v.occupancy as f64
                            }
                            Some(v) => {
                                free += 1;
                                v.occupancy as f64
                            }
                            None => {
                                unk += 1;
                                0.2
                            }
                        };
                        maxp = f64::max(maxp, p);
                        pf *= 1.0 - p;
                    }
                }
            }
            assert_eq!((got.occupied, got.free, got.unknown), (occ, free, unk), "{region:?}");
            assert!((got.p_free - pf).abs() <= 1e-9 * pf.max(1e-300) + 1e-300);
            assert_eq!(got.max_occupancy, maxp);
        }
        let huge = Aabb::new([-1e4; 3], [1e4; 3]).unwrap();
        let err = query_box(&map, &huge, &opts).unwrap_err().to_string();
        assert!(err.contains("smaller box"), "{err}");
    }

    #[test]
    fn options_are_checked() {
        assert!(QueryOptions { unknown: 1.5, ..Default::default() }.validate().is_err());
        assert!(QueryOptions { k: -1.0, ..Default::default() }.validate().is_err());
        assert!(QueryOptions { k: f64::NAN, ..Default::default() }.validate().is_err());
        assert!(QueryOptions::default().validate().is_ok());
    }
}
