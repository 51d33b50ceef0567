//! The log-odds occupancy grid with OctoMap's update semantics (ALGORITHMS.md 5.1).
//!
//! Per scan, as `OcTree::insertPointCloud`: every voxel a ray crosses before its endpoint is
//! marked *free*, the endpoint voxel *occupied*; a voxel that is both in one scan counts as
//! occupied; then each marked voxel is updated exactly once. Rays are traced in parallel
//! (rayon, by image row) into per-task brick bitmasks that are OR-ed together, so the
//! result is a set and identical for any thread count.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::Engine;
use crate::error::{Error, Result};
use crate::frames::Frame;
use crate::map::{BrickKey, Grid, Map, MapVoxel, SlotMask, mask_slots};
use crate::rays::{FrameRays, PixelRay, RayLimits, for_each_crossing};

/// OctoMap's sensor model parameters (probabilities).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogOddsParams {
    /// Probability added for an endpoint (OctoMap: 0.7).
    pub p_hit: f64,
    /// Probability added for a traversed voxel (OctoMap: 0.4).
    pub p_miss: f64,
    /// Lower clamp (OctoMap: 0.1192).
    pub clamp_min: f64,
    /// Upper clamp (OctoMap: 0.971).
    pub clamp_max: f64,
}

impl Default for LogOddsParams {
    fn default() -> Self {
        LogOddsParams { p_hit: 0.7, p_miss: 0.4, clamp_min: 0.1192, clamp_max: 0.971 }
    }
}

fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

fn sigmoid(l: f32) -> f32 {
    1.0 / (1.0 + (-l).exp())
}

/// OctoMap-style log-odds mapping.
///
/// ```
/// use mrfmap::inference::{Engine, LogOddsEngine, LogOddsParams};
/// let engine = LogOddsEngine::new(0.05, Default::default(), LogOddsParams::default()).unwrap();
/// assert!(engine.map().voxels.is_empty());
/// ```
#[derive(Clone, Debug)]
pub struct LogOddsEngine {
    grid: Grid<f32>,
    limits: RayLimits,
    params: LogOddsParams,
    hit: f32,
    miss: f32,
    min: f32,
    max: f32,
}

impl LogOddsEngine {
    /// An empty map; fails on a bad resolution or probabilities outside (0, 1).
    pub fn new(resolution: f64, limits: RayLimits, params: LogOddsParams) -> Result<Self> {
        let p = params;
        let ok = [p.p_hit, p.p_miss, p.clamp_min, p.clamp_max].iter().all(|v| *v > 0.0 && *v < 1.0);
        if !ok || p.clamp_min >= p.clamp_max {
            return Err(Error::Invalid(format!(
                "log-odds parameters must be in (0, 1) with clamp_min < clamp_max: {p:?}"
            )));
        }
        Ok(LogOddsEngine {
            grid: Grid::new(resolution)?,
            limits,
            params,
            hit: logit(p.p_hit) as f32,
            miss: logit(p.p_miss) as f32,
            min: logit(p.clamp_min) as f32,
            max: logit(p.clamp_max) as f32,
        })
    }

    /// The log-odds per voxel.
    pub fn log_odds(&self) -> &Grid<f32> {
        &self.grid
    }
}

impl Engine for LogOddsEngine {
    fn name(&self) -> &'static str {
        "logodds"
    }

    fn resolution(&self) -> f64 {
        self.grid.resolution()
    }

    fn integrate(&mut self, frame: &Frame) -> Result<()> {
        let marks = ScanMarks::of_frame(frame, self.grid.resolution(), &self.limits);
        for (key, m) in marks.bricks {
            let brick = self.grid.brick_or_insert(key);
            for slot in mask_slots(&m.hit) {
                let l = brick.get_or_insert(slot, 0.0);
                *l = (*l + self.hit).clamp(self.min, self.max);
            }
            let free_only: SlotMask = std::array::from_fn(|w| m.free[w] & !m.hit[w]);
            for slot in mask_slots(&free_only) {
                let l = brick.get_or_insert(slot, 0.0);
                *l = (*l + self.miss).clamp(self.min, self.max);
            }
        }
        Ok(())
    }

    fn map(&self) -> Map {
        let mut map = Map::new(self.name(), self.grid.resolution()).expect("valid resolution");
        map.voxels = self.grid.map(|l| MapVoxel { occupancy: sigmoid(*l), variance: 0.0 });
        let p = self.params;
        for (k, v) in [("p_hit", p.p_hit), ("p_miss", p.p_miss), ("clamp_min", p.clamp_min), ("clamp_max", p.clamp_max)]
        {
            map.params.insert(k.into(), v.to_string());
        }
        if let Some(m) = self.limits.max_range {
            map.params.insert("max_range".into(), m.to_string());
        }
        map
    }
}

/// Free and occupied voxels of one brick in one scan.
#[derive(Clone, Copy, Default)]
struct BrickMarks {
    free: SlotMask,
    hit: SlotMask,
}

/// The voxel sets of one scan, as bitmasks per brick.
#[derive(Default)]
struct ScanMarks {
    bricks: FxHashMap<BrickKey, BrickMarks>,
}

impl ScanMarks {
    fn of_frame(frame: &Frame, resolution: f64, limits: &RayLimits) -> Self {
        let rays = FrameRays::new(frame);
        (0..rays.rows())
            .into_par_iter()
            .fold(RowMarker::default, |mut m, v| {
                for ray in rays.row(v) {
                    m.mark_ray(&ray, resolution, limits);
                }
                m
            })
            .map(RowMarker::finish)
            .reduce(ScanMarks::default, ScanMarks::merge)
    }

    fn merge(mut self, mut other: ScanMarks) -> ScanMarks {
        if self.bricks.len() < other.bricks.len() {
            std::mem::swap(&mut self, &mut other);
        }
        for (k, m) in other.bricks {
            let e = self.bricks.entry(k).or_default();
            for w in 0..8 {
                e.free[w] |= m.free[w];
                e.hit[w] |= m.hit[w];
            }
        }
        self
    }
}

/// Marks voxels for a run of rays, caching the current brick: consecutive voxels of a ray
/// are usually in the same brick, so most marks skip the hash lookup.
#[derive(Default)]
struct RowMarker {
    index: FxHashMap<BrickKey, u32>,
    marks: Vec<(BrickKey, BrickMarks)>,
}

impl RowMarker {
    /// Index of `key`'s marks, adding an empty entry for a new brick.
    #[inline(never)]
    fn lookup(&mut self, key: BrickKey) -> usize {
        let next = self.marks.len() as u32;
        let i = *self.index.entry(key).or_insert(next);
        if i == next {
            self.marks.push((key, BrickMarks::default()));
        }
        i as usize
    }

    fn mark_ray(&mut self, ray: &PixelRay, resolution: f64, limits: &RayLimits) {
        let Some(seg) = limits.segment(ray, 0.0) else { return };
        // Every crossed voxel is marked free, the last one (holding the endpoint) also
        // occupied when the ray reached its surface: occupied wins when the scan is applied.
        let mut current: Option<(BrickKey, usize)> = None;
        let mut last = None;
        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, resolution, |c| {
            let brick = c.key.brick();
            let i = match current {
                Some((k, i)) if k == brick => i,
                _ => {
                    let i = self.lookup(brick);
                    current = Some((brick, i));
                    i
                }
            };
            let slot = c.key.slot();
            self.marks[i].1.free[slot >> 6] |= 1 << (slot & 63);
            last = Some((i, slot));
        });
        if let (Some((i, slot)), true) = (last, seg.hits_surface) {
            self.marks[i].1.hit[slot >> 6] |= 1 << (slot & 63);
        }
    }

    fn finish(self) -> ScanMarks {
        ScanMarks { bricks: self.marks.into_iter().collect() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::{Camera, DepthImage, look_at};
    use crate::map::VoxelKey;
    use nalgebra::Vector3;

    /// A frame of a small camera at the origin looking along +x at a wall `dist` away.
    fn wall_frame(dist: f32, w: u32, h: u32) -> Frame {
        let camera = Camera::new(20.0, 20.0, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0, w, h, 5000.0).unwrap();
        let mut depth = DepthImage::new(w, h);
        for v in 0..h {
            for u in 0..w {
                depth.set(u, v, dist);
            }
        }
        let pose = look_at(Vector3::new(0.013, 0.021, 0.017), Vector3::new(1.0, 0.021, 0.017)).unwrap();
        Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None }
    }

    #[test]
    fn single_ray_updates_once_per_voxel() {
        let frame = wall_frame(1.0, 1, 1);
        let mut e = LogOddsEngine::new(0.1, RayLimits::default(), LogOddsParams::default()).unwrap();
        e.integrate(&frame).unwrap();
        let hit = logit(0.7) as f32;
        let miss = logit(0.4) as f32;
        let grid = e.log_odds();
        // Origin x = 0.013 to endpoint x = 1.013: voxels 0..=10 along x, endpoint in 10.
        assert_eq!(grid.len(), 11);
        for i in 0..10 {
            assert_eq!(grid.get(VoxelKey([i, 0, 0])), Some(&miss), "voxel {i}");
        }
        assert_eq!(grid.get(VoxelKey([10, 0, 0])), Some(&hit));
        // Clamping after many scans.
        for _ in 0..50 {
            e.integrate(&frame).unwrap();
        }
        let g = e.log_odds();
        assert_eq!(*g.get(VoxelKey([10, 0, 0])).unwrap(), logit(0.971) as f32);
        assert_eq!(*g.get(VoxelKey([3, 0, 0])).unwrap(), logit(0.1192) as f32);
    }

    #[test]
    fn occupied_wins_within_a_scan_and_max_range_cuts() {
        // Two rays in one scan: one ends in voxel 5, the other passes through it.
        let mut frame = wall_frame(2.0, 2, 1);
        frame.camera.fx = 1e6; // both pixels look almost straight ahead
        frame.depth.set(0, 0, 0.55);
        let mut e = LogOddsEngine::new(0.1, RayLimits::default(), LogOddsParams::default()).unwrap();
        e.integrate(&frame).unwrap();
        assert_eq!(e.log_odds().get(VoxelKey([5, 0, 0])), Some(&(logit(0.7) as f32)));
        let limits = RayLimits { max_range: Some(1.0), bounds: None };
        let mut e = LogOddsEngine::new(0.1, limits, LogOddsParams::default()).unwrap();
        e.integrate(&wall_frame(2.0, 1, 1)).unwrap();
        assert!(e.log_odds().iter().all(|(_, l)| *l < 0.0), "max-range rays carry no hit");
        assert_eq!(e.log_odds().len(), 11);
    }

    #[test]
    fn identical_for_any_thread_count() {
        let frame = {
            let mut f = wall_frame(3.0, 64, 48);
            for v in 0..48 {
                for u in 0..64 {
                    f.depth.set(u, v, 1.0 + ((u * 7 + v * 13) % 29) as f32 * 0.1);
                }
            }
            f
        };
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut e = LogOddsEngine::new(0.02, RayLimits::default(), LogOddsParams::default()).unwrap();
            pool.install(|| {
                e.integrate(&frame).unwrap();
                e.integrate(&frame).unwrap();
            });
            let mut v: Vec<(VoxelKey, u32)> = e.log_odds().iter().map(|(k, l)| (k, l.to_bits())).collect();
            v.sort();
            v
        };
        let one = run(1);
        assert!(one.len() > 1000);
        assert_eq!(one, run(2));
        assert_eq!(one, run(3));
    }
}
