//! The log-odds occupancy grid (docs/ALGORITHMS.md 5.1), with two inverse sensor models.
//!
//! [`SensorModel::HitMiss`] is OctoMap's `insertPointCloud`: per scan, every voxel a ray
//! crosses before its endpoint is marked *free*, the endpoint voxel *occupied*; a voxel that
//! is both in one scan counts as occupied; then each marked voxel is updated exactly once.
//! Rays are traced in parallel (rayon, by image row) into per-task brick bitmasks that are
//! OR-ed together, so the result is a set and identical for any thread count.
//!
//! [`SensorModel::Ramp`] is the parametric model of the CRM paper's Fig. 1, used in its
//! comparisons and parameter sweeps. Per scan each voxel is updated once, by the ray that
//! passes closest to its centre (the classic occupancy-grid rule of Thrun et al., which
//! picks the beam nearest in bearing), ties broken by pixel index, so it too is identical
//! for any thread count. It is meant for the papers' experiments, not for speed.

use crate::map::EngineKind;
use std::cell::Cell;
use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::path::Path;

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::{Engine, SavedMap, logit, sigmoid};
use crate::error::{Error, Result};
use crate::frames::{Camera, Frame, RangeScan};
use crate::map::{Aabb, BrickKey, BrickList, Grid, Map, MapVoxel, SlotMask, VoxelKey, box_keys, box_slots, key_in_box};
use crate::rays::{CrossedVoxels, PixelRay, Projector, RayLimits, Rays, for_each_crossing};

/// How one ray changes the voxels it crosses (occupancy probabilities, turned into log-odds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SensorModel {
    /// OctoMap: `p_miss` for crossed voxels, `p_hit` for the endpoint voxel (defaults 0.7 / 0.4).
    HitMiss {
        /// Probability for the endpoint voxel.
        p_hit: f64,
        /// Probability for crossed voxels.
        p_miss: f64,
    },
    /// CRM Fig. 1: `q_low` up to `z - r_ramp/2`, a linear ramp to `q_high` at `z + r_ramp/2`,
    /// `q_high` up to `z + r_ramp/2 + r_top`, no update beyond (`z` = measured range). The
    /// CRM paper's best setting: `r_ramp = r_top = 0.1`, `q_low = 0.45`, `q_high = 0.55`.
    Ramp {
        /// Probability in front of the surface.
        q_low: f64,
        /// Probability at and just behind the surface.
        q_high: f64,
        /// Width of the ramp (m).
        r_ramp: f64,
        /// Depth of the occupied plateau behind the ramp (m).
        r_top: f64,
    },
}

impl SensorModel {
    /// OctoMap's defaults.
    pub const OCTOMAP: SensorModel = SensorModel::HitMiss { p_hit: 0.7, p_miss: 0.4 };

    /// The CRM paper's best ramp setting.
    pub const CRM_PAPER: SensorModel = SensorModel::Ramp { q_low: 0.45, q_high: 0.55, r_ramp: 0.1, r_top: 0.1 };

    /// Occupancy probability of the ramp model at range `s` for a surface at `z` (`None` beyond
    /// the plateau, and for [`SensorModel::HitMiss`], which has no range profile).
    ///
    /// ```
    /// use mrfmap::inference::SensorModel;
    /// let m = SensorModel::CRM_PAPER;
    /// assert_eq!(m.ramp_probability(1.0, 2.0), Some(0.45));
    /// assert!((m.ramp_probability(2.0, 2.0).unwrap() - 0.5).abs() < 1e-12);
    /// assert_eq!(m.ramp_probability(2.1, 2.0), Some(0.55));
    /// assert_eq!(m.ramp_probability(2.2, 2.0), None);
    /// ```
    pub fn ramp_probability(&self, s: f64, z: f64) -> Option<f64> {
        let SensorModel::Ramp { q_low, q_high, r_ramp, r_top } = *self else { return None };
        let (a, b) = (z - 0.5 * r_ramp, z + 0.5 * r_ramp);
        if s < a {
            Some(q_low)
        } else if s < b {
            Some(q_low + (q_high - q_low) * (s - a) / r_ramp)
        } else {
            (s <= b + r_top).then_some(q_high)
        }
    }

    fn validate(&self) -> std::result::Result<(), String> {
        let probs_ok = |ps: &[f64]| ps.iter().all(|p| *p > 0.0 && *p < 1.0);
        match *self {
            SensorModel::HitMiss { p_hit, p_miss } if probs_ok(&[p_hit, p_miss]) => Ok(()),
            SensorModel::Ramp { q_low, q_high, r_ramp, r_top }
                if probs_ok(&[q_low, q_high]) && r_ramp > 0.0 && r_top >= 0.0 =>
            {
                Ok(())
            }
            m => Err(format!("sensor model needs probabilities in (0, 1) and r_ramp > 0, r_top >= 0: {m:?}")),
        }
    }
}

/// Parameters of the log-odds engine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogOddsParams {
    /// The inverse sensor model (default: OctoMap's hit/miss).
    pub model: SensorModel,
    /// Lower clamp as a probability (OctoMap: 0.1192).
    pub clamp_min: f64,
    /// Upper clamp as a probability (OctoMap: 0.971).
    pub clamp_max: f64,
    /// How the hit/miss model finds the voxels a depth image's rays cross.
    pub marking: Marking,
    /// Store only the voxels inside this box; rays are traced exactly as without it, so those
    /// voxels are exactly the map built without it (unlike [`RayLimits::bounds`], which cuts
    /// the rays). A tile of a tiled map is built with its box here.
    pub keep: Option<Aabb>,
}

impl Default for LogOddsParams {
    fn default() -> Self {
        LogOddsParams {
            model: SensorModel::OCTOMAP,
            clamp_min: 0.1192,
            clamp_max: 0.971,
            marking: Marking::Project,
            keep: None,
        }
    }
}

/// How [`SensorModel::HitMiss`] finds the voxels the rays of a depth image cross. `Walk` and
/// `Project` give the same voxels (up to rays that graze a voxel's edge or corner), OctoMap's;
/// `Centres` is a faster approximation of them. Range scans are always walked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Marking {
    /// Walk every ray ([`for_each_crossing`]): work grows with the number of rays times
    /// their length.
    Walk,
    /// Project boxes of voxels into the image ([`crossed_voxels`]): work grows with the
    /// number of voxels in view; several times faster on 640x480 images. Frames whose depths
    /// lie mostly where voxels are smaller than a pixel are walked instead
    /// ([`Projector::pays_off`]).
    ///
    /// [`crossed_voxels`]: crate::rays::Projector::crossed_voxels
    #[default]
    Project,
    /// Not OctoMap's voxels: a voxel is free when its centre lies in front of the depth at
    /// the pixel it projects to, occupied when that pixel's surface lies on the voxel's chord
    /// through its centre ([`centre_voxels`]), as voxblox's and wavemap's projective
    /// integrators decide. Voxels that rays only clip are left out, and far voxels smaller
    /// than a pixel are all cleared, not only those a ray hits. 2-4x as fast as `Project`
    /// (BENCHMARKS.md, session 28); RESULTS.md compares the maps' held-out accuracy.
    ///
    /// [`centre_voxels`]: crate::rays::Projector::centre_voxels
    Centres,
}

crate::choice::choice!(Marking, "marking", Project => "project", Walk => "walk", Centres => "centres");

/// Merging log-odds maps ([`super::merge`]): the sum of the log-odds, clamped to the maps'
/// clamping bounds (probabilities).
pub(super) fn merge_rule(clamp_min: f64, clamp_max: f64) -> impl Fn(MapVoxel, MapVoxel) -> MapVoxel {
    let (lo, hi) = (logit(clamp_min), logit(clamp_max));
    move |a, b| MapVoxel {
        occupancy: sigmoid((logit(a.occupancy as f64) + logit(b.occupancy as f64)).clamp(lo, hi)) as f32,
        variance: 0.0,
    }
}

/// Log-odds occupancy mapping.
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
    min: f32,
    max: f32,
    /// Buffers for [`Marking::Project`], kept between frames.
    projector: Projector,
    /// The voxels at the lower clamp, per brick of the grid that has any, as
    /// [`crate::map::Brick::slots_where`] finds them: kept by [`LogOddsEngine::apply_marks`]
    /// from the bricks it has just updated (the grid's only writer under the hit/miss model,
    /// the only model that reads this). The projection's `settled` voxels: read from the grid
    /// instead, a brick's 2 KiB of values, which had left the cache, were 3% of a coffin-world
    /// frame at 0.05 m.
    at_min: FxHashMap<BrickKey, SlotMask>,
}

impl LogOddsEngine {
    /// An empty map; fails on a bad resolution or parameters outside their ranges.
    pub fn new(resolution: f64, limits: RayLimits, params: LogOddsParams) -> Result<Self> {
        let p = params;
        p.model.validate().map_err(Error::Invalid)?;
        if !(p.clamp_min > 0.0 && p.clamp_min < p.clamp_max && p.clamp_max < 1.0) {
            return Err(Error::Invalid(format!("need 0 < clamp_min < clamp_max < 1: {p:?}")));
        }
        Ok(LogOddsEngine {
            grid: Grid::new(resolution)?,
            limits,
            params,
            min: logit(p.clamp_min) as f32,
            max: logit(p.clamp_max) as f32,
            projector: Projector::default(),
            at_min: FxHashMap::default(),
        })
    }

    /// The log-odds per voxel.
    pub fn log_odds(&self) -> &Grid<f32> {
        &self.grid
    }

    /// Is a brick (by key) one [`LogOddsParams::keep`] keeps? `None` without a box: every
    /// brick. A brick counts when it overlaps the box.
    fn keep_bricks(&self) -> Option<impl Fn([i32; 3]) -> bool + use<>> {
        let (lo, hi) = box_keys(&self.params.keep?, self.grid.resolution());
        let (lo, hi) = (VoxelKey(lo).brick().0, VoxelKey(hi).brick().0);
        Some(move |b: [i32; 3]| (0..3).all(|a| b[a] >= lo[a] && b[a] <= hi[a]))
    }

    /// Adds `delta` to a voxel's log-odds (allocating it at 0 = prior 0.5), then clamps.
    #[inline]
    fn update(l: &mut f32, delta: f32, min: f32, max: f32) {
        *l = (*l + delta).clamp(min, max);
    }

    /// [`Engine::integrate`]'s work: the frame's voxels by projection (or its rays walked,
    /// where projecting does not pay), marked and applied.
    fn integrate_frame(&mut self, frame: &Frame) {
        match (self.params.model, self.params.marking) {
            (SensorModel::HitMiss { .. }, Marking::Project) if Projector::pays_off(frame, self.grid.resolution()) => {
                let crossed = self.project(frame, true);
                self.apply_marks(ScanMarks::of_crossed(crossed));
            }
            (SensorModel::HitMiss { .. }, Marking::Centres) => {
                let r = self.grid.resolution();
                let crossed = self.projector.centre_voxels(frame, &self.limits, r, self.params.keep.as_ref());
                self.apply_marks(ScanMarks::of_crossed(crossed));
            }
            _ => self.integrate_rays(&Rays::of_frame(frame)),
        }
    }

    /// The voxels `frame`'s rays cross, by projection; with `leave_open`, whether the voxels
    /// at the lower clamp are crossed is left open where a miss lowers the log-odds.
    ///
    /// A voxel at the lower clamp stays there after such a miss (OctoMap clamps the sum back
    /// to the bound), so whether a ray crosses it changes nothing. The map is the same bit for
    /// bit; long sequences, whose free space reaches the clamp after five misses with
    /// OctoMap's defaults, skip most of their tests.
    fn project(&mut self, frame: &Frame, leave_open: bool) -> CrossedVoxels {
        let (grid, at_min) = (&self.grid, &self.at_min);
        let settled = move |key: BrickKey| at_min.get(&key).copied().unwrap_or_default();
        let lowers = matches!(self.params.model, SensorModel::HitMiss { p_miss, .. } if p_miss < 0.5);
        let keep = self.params.keep.as_ref();
        let settled = (leave_open && lowers).then_some(&settled as _);
        self.projector.crossed_voxels(frame, &self.limits, grid.resolution(), keep, settled)
    }

    fn integrate_rays(&mut self, rays: &Rays) {
        match self.params.model {
            SensorModel::HitMiss { .. } => {
                self.apply_marks(ScanMarks::of_rays(rays, self.grid.resolution(), &self.limits))
            }
            SensorModel::Ramp { .. } => self.integrate_ramp(rays),
        }
    }

    /// Applies one scan's hit/miss marks: each marked voxel is updated once.
    fn apply_marks(&mut self, mut marks: ScanMarks) {
        let SensorModel::HitMiss { p_hit, p_miss } = self.params.model else { unreachable!("hit/miss marks") };
        let (hit, miss, min, max) = (logit(p_hit) as f32, logit(p_miss) as f32, self.min, self.max);
        if let Some(keep) = self.keep_bricks() {
            marks.bricks.retain(|b, _| keep(b.0));
        }
        if let Some((lo, hi)) = self.limits.bounds_keys(self.grid.resolution()) {
            // (`RayLimits::bounds_keys`: rounding at the box's faces.)
            marks.bricks.retain(|b, m| {
                let inside = box_slots(*b, lo, hi);
                m.hit.iter_mut().chain(&mut m.free).zip(inside.iter().cycle()).for_each(|(w, i)| *w &= i);
                m.hit != [0; 8] || m.free != [0; 8]
            });
        }
        // Each marked brick is its own work (serially this was a tenth of a projected frame).
        let at_min = self.grid.update_bricks(&marks.bricks, |brick, m| {
            brick.update_slots(&m.hit, 0.0, |l| Self::update(l, hit, min, max));
            let free_only: SlotMask = std::array::from_fn(|w| m.free[w] & !m.hit[w]);
            brick.update_slots(&free_only, 0.0, |l| Self::update(l, miss, min, max));
            // (While its values are in this thread's cache.)
            brick.slots_where(|l| *l == min)
        });
        for (key, m) in at_min {
            if m == [0; 8] {
                self.at_min.remove(&key);
            } else {
                self.at_min.insert(key, m);
            }
        }
    }

    fn integrate_ramp(&mut self, rays: &Rays) {
        let model = self.params.model;
        let SensorModel::Ramp { r_ramp, r_top, .. } = model else { unreachable!("called for the ramp model") };
        let r = self.grid.resolution();
        let limits = self.limits;
        // Per voxel: (squared distance of the ray from the centre, pixel index, log-odds delta).
        type Best = FxHashMap<VoxelKey, (f64, u64, f32)>;
        let keep_closest = |best: &mut Best, key: VoxelKey, cand: (f64, u64, f32)| {
            let e = best.entry(key).or_insert(cand);
            if (cand.0, cand.1) < (e.0, e.1) {
                *e = cand;
            }
        };
        let best: Best = (0..rays.rows())
            .into_par_iter()
            .fold(Best::default, |mut best, v| {
                for ray in rays.row(v) {
                    let z = limits.surface_range(&ray).unwrap_or(f64::INFINITY);
                    let Some(seg) = limits.segment(&ray, 0.5 * r_ramp + r_top) else { continue };
                    let id = rays.ray_id(&ray);
                    for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, r, |c| {
                        let Some(p) = model.ramp_probability(0.5 * (c.s_in + c.s_out), z) else {
                            return ControlFlow::Break(()); // past the plateau: the rest of the ray too
                        };
                        let centre = c.key.center(r);
                        let d = [0, 1, 2].map(|a| centre[a] - ray.origin[a]);
                        let t = d[0] * ray.dir[0] + d[1] * ray.dir[1] + d[2] * ray.dir[2];
                        let dist2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - t * t;
                        keep_closest(&mut best, c.key, (dist2, id, logit(p) as f32));
                        ControlFlow::Continue(())
                    });
                }
                best
            })
            .reduce(Best::default, |mut a, b| {
                for (k, cand) in b {
                    keep_closest(&mut a, k, cand);
                }
                a
            });
        let (keep, bounds) = (self.keep_bricks(), self.limits.bounds_keys(r));
        for (key, (_, _, delta)) in best {
            if keep.as_ref().is_some_and(|keep| !keep(key.brick().0)) || bounds.is_some_and(|b| !key_in_box(key.0, b)) {
                continue;
            }
            Self::update(self.grid.get_or_insert(key, 0.0), delta, self.min, self.max);
        }
    }
}

impl Engine for LogOddsEngine {
    fn kind(&self) -> EngineKind {
        EngineKind::LogOdds
    }

    fn resolution(&self) -> f64 {
        self.grid.resolution()
    }

    fn prepare(&mut self, camera: &Camera) {
        if let (SensorModel::HitMiss { .. }, Marking::Project) = (self.params.model, self.params.marking) {
            self.projector.prepare(camera, self.limits.bounds.is_some());
        }
    }

    fn integrate(&mut self, frame: &Frame) -> Result<()> {
        // With one thread, on the pool's worker: the frame's dozen parallel steps then run
        // where they start instead of each being handed from a caller outside the pool to the
        // worker and back (0.83x the time of a 211-frame build at 0.05 m). It still pays with
        // the command line's thread in its pool (without it, 1.05x the time of that build's
        // frames under `mrfmap bench`), and a library caller's thread is outside the pool.
        // With more threads, each step wakes the pool either way, and starting them on a
        // worker was slower (BENCHMARKS.md, session 40).
        if rayon::current_num_threads() == 1 {
            rayon::scope(|_| self.integrate_frame(frame));
        } else {
            self.integrate_frame(frame);
        }
        Ok(())
    }

    fn integrate_scan(&mut self, scan: &RangeScan) -> Result<()> {
        self.integrate_rays(&Rays::of_scan(scan));
        Ok(())
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.grid.get(key).map(|l| map_voxel(*l))
    }

    fn map(&self) -> Map {
        let mut map = self.map_params();
        map.voxels = self.grid.map(|l| map_voxel(*l));
        map
    }

    fn into_map(self: Box<Self>) -> Map {
        let mut map = self.map_params();
        map.voxels = self.grid.into_map(|l| map_voxel(*l));
        map
    }

    fn save_map(&self, path: &Path, params: &BTreeMap<String, String>) -> Result<SavedMap> {
        let mut meta = self.map_params();
        meta.params.extend(params.clone());
        let memo = Memo::default();
        let occupied = meta.save_converted(&self.grid, |l| memo.map_voxel(*l), path)?;
        Ok(SavedMap { voxels: self.grid.len(), occupied })
    }
}

impl LogOddsEngine {
    /// An empty map with this engine's name, resolution and parameters.
    fn map_params(&self) -> Map {
        let mut map = Map::new(self.kind(), self.grid.resolution()).expect("valid resolution");
        let p = self.params;
        let mut params = vec![("clamp_min", p.clamp_min), ("clamp_max", p.clamp_max)];
        match p.model {
            SensorModel::HitMiss { p_hit, p_miss } => params.extend([("p_hit", p_hit), ("p_miss", p_miss)]),
            SensorModel::Ramp { q_low, q_high, r_ramp, r_top } => {
                params.extend([("q_low", q_low), ("q_high", q_high), ("r_ramp", r_ramp), ("r_top", r_top)])
            }
        }
        params.extend(self.limits.max_range.map(|m| ("max_range", m)));
        for (k, v) in params {
            map.params.insert(k.into(), v.to_string());
        }
        if p.marking == Marking::Centres {
            // A different model of space: the file says so (OctoMap's markings agree, and say
            // nothing, as before).
            map.params.insert("marking".into(), crate::Choice::name(p.marking).into());
        }
        map
    }
}

/// A map voxel of a stored log-odds value.
fn map_voxel(l: f32) -> MapVoxel {
    MapVoxel { occupancy: sigmoid(l as f64) as f32, variance: 0.0 }
}

/// [`map_voxel`] remembered for the last values seen, by their bits: a map's log-odds are sums
/// of a few increments, clamped, so a handful of values cover most voxels, and the `exp` per
/// voxel was a quarter of saving a map (a tenth of a short build's whole process). The same
/// values bit for bit.
struct Memo {
    slots: [Cell<(u32, f32)>; 256],
}

impl Default for Memo {
    fn default() -> Self {
        // (Every slot starts as the value 0, probability 1/2, exactly.)
        Memo { slots: std::array::from_fn(|_| Cell::new((0f32.to_bits(), map_voxel(0.0).occupancy))) }
    }
}

impl Memo {
    fn map_voxel(&self, l: f32) -> MapVoxel {
        let bits = l.to_bits();
        let slot = &self.slots[(bits.wrapping_mul(0x9E37_79B1) >> 24) as usize];
        match slot.get() {
            (b, p) if b == bits => MapVoxel { occupancy: p, variance: 0.0 },
            _ => {
                let v = map_voxel(l);
                slot.set((bits, v.occupancy));
                v
            }
        }
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
    fn of_rays(rays: &Rays, resolution: f64, limits: &RayLimits) -> Self {
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

    fn of_crossed(c: CrossedVoxels) -> Self {
        let mut bricks: FxHashMap<BrickKey, BrickMarks> =
            c.crossed.into_iter().map(|(k, free)| (k, BrickMarks { free, hit: [0; 8] })).collect();
        for (k, hit) in c.ends {
            // The end voxel is crossed too; it is in `crossed` unless the segment only
            // touches it, and then it is the voxel the walk would have ended in.
            bricks.entry(k).or_default().hit = hit;
        }
        ScanMarks { bricks }
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
    marks: BrickList<BrickMarks>,
}

impl RowMarker {
    /// Index of `key`'s marks, adding an empty entry for a new brick. Kept out of line: the
    /// walk's hot loop stays small (measured faster).
    #[inline(never)]
    fn lookup(&mut self, key: BrickKey) -> usize {
        self.marks.index_or_insert_with(key, BrickMarks::default)
    }

    fn mark_ray(&mut self, ray: &PixelRay, resolution: f64, limits: &RayLimits) {
        let Some(seg) = limits.hit_miss_segment(ray, resolution) else { return };
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
            self.marks.value_mut(i).free[slot >> 6] |= 1 << (slot & 63);
            last = Some((i, slot));
            ControlFlow::Continue(())
        });
        if let (Some((i, slot)), true) = (last, seg.hits_surface) {
            self.marks.value_mut(i).hit[slot >> 6] |= 1 << (slot & 63);
        }
    }

    fn finish(self) -> ScanMarks {
        ScanMarks { bricks: self.marks.into_items().into_iter().collect() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::{Camera, DepthImage, look_at};
    use crate::map::{Aabb, VoxelKey, box_keys};
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

    /// The projective model marks the wall's voxel and clears the voxels before it, once a
    /// frame each, and its maps say which model made them.
    #[test]
    fn centres_marks_the_wall_and_says_so() {
        let frame = wall_frame(1.0, 32, 24);
        let params = LogOddsParams { marking: Marking::Centres, ..Default::default() };
        let mut e = LogOddsEngine::new(0.1, RayLimits::default(), params).unwrap();
        e.integrate(&frame).unwrap();
        let (hit, miss) = (logit(0.7) as f32, logit(0.4) as f32);
        // Camera at x = 0.013, wall at x = 1.013: in voxel 10, whose centre (1.05) is 3.7 cm
        // behind it, on the voxel's chord.
        let grid = e.log_odds();
        assert_eq!(grid.get(VoxelKey([10, 0, 0])), Some(&hit));
        for i in 1..10 {
            assert_eq!(grid.get(VoxelKey([i, 0, 0])), Some(&miss), "voxel {i}");
        }
        assert!(grid.iter().all(|(k, _)| k.0[0] <= 10), "nothing behind the wall");
        assert_eq!(e.map().params.get("marking").map(String::as_str), Some("centres"));
        let exact = LogOddsEngine::new(0.1, RayLimits::default(), LogOddsParams::default()).unwrap();
        assert_eq!(exact.map().params.get("marking"), None);
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
        // Cut at x = 1.013, in voxel 10: OctoMap traces to the cut point without its voxel.
        let keys: Vec<i32> = e.log_odds().iter().map(|(k, _)| k.0[0]).collect();
        assert_eq!((keys.len(), keys.iter().max()), (10, Some(&9)), "{keys:?}");
        // Walking and projecting agree on it.
        let params = LogOddsParams { marking: Marking::Walk, ..Default::default() };
        let mut walked = LogOddsEngine::new(0.1, limits, params).unwrap();
        walked.integrate(&wall_frame(2.0, 1, 1)).unwrap();
        assert_eq!(walked.log_odds().len(), 10);
        // A cut end in the camera's own voxel leaves OctoMap nothing to mark.
        let short = RayLimits { max_range: Some(0.05), bounds: None };
        let mut e = LogOddsEngine::new(0.1, short, LogOddsParams::default()).unwrap();
        e.integrate(&wall_frame(2.0, 1, 1)).unwrap();
        assert!(e.log_odds().is_empty());
    }

    #[test]
    fn ramp_model_follows_the_profile_and_stops_behind_the_surface() {
        let frame = wall_frame(1.0, 1, 1); // surface at x = 1.013
        let params = LogOddsParams { model: SensorModel::CRM_PAPER, ..Default::default() };
        let mut e = LogOddsEngine::new(0.02, RayLimits::default(), params).unwrap();
        e.integrate(&frame).unwrap();
        let g = e.log_odds();
        // Voxel 20 spans x in [0.40, 0.42): well in front, q_low.
        assert!((g.get(VoxelKey([20, 1, 0])).copied().unwrap() - logit(0.45) as f32).abs() < 1e-6);
        // Voxel 50 spans [1.00, 1.02), crossed at ranges [0.987, 1.007]: midpoint 0.997 -> ramp.
        let expected = 0.45 + 0.1 * (0.997 - 0.95) / 0.1;
        assert!((g.get(VoxelKey([50, 1, 0])).copied().unwrap() - logit(expected) as f32).abs() < 1e-4);
        // The plateau runs to range 1.15, which ends inside voxel 58 (x in [1.16, 1.18)):
        // voxels 57 and 58 get q_high, nothing beyond is touched.
        for i in [57, 58] {
            assert!((g.get(VoxelKey([i, 1, 0])).copied().unwrap() - logit(0.55) as f32).abs() < 1e-6, "voxel {i}");
        }
        assert_eq!(g.get(VoxelKey([59, 1, 0])), None);
        assert!(
            LogOddsEngine::new(
                0.02,
                RayLimits::default(),
                LogOddsParams {
                    model: SensorModel::Ramp { q_low: 0.4, q_high: 1.2, r_ramp: 0.1, r_top: 0.1 },
                    ..Default::default()
                }
            )
            .is_err()
        );
    }

    /// Leaving the voxels at the lower clamp open changes nothing: a sequence long enough for
    /// free space to reach the clamp builds, bit for bit, the map of projections that test
    /// every voxel; and some bricks were left open. (A miss that raises the log-odds, p_miss
    /// above 0.5, settles nothing: the same comparison holds for it too.) The engine's record of
    /// the voxels at the clamp is the grid's after every frame. (The engine that leaves voxels
    /// open is also readied for the camera before its first frame, [`Engine::prepare`]; the
    /// other is not.)
    #[test]
    fn voxels_at_the_lower_clamp_left_open_change_nothing() {
        for p_miss in [0.4, 0.6] {
            let params = LogOddsParams { model: SensorModel::HitMiss { p_hit: 0.7, p_miss }, ..Default::default() };
            let limits = RayLimits { max_range: Some(2.5), bounds: None };
            let (mut fast, mut full) =
                (LogOddsEngine::new(0.05, limits, params).unwrap(), LogOddsEngine::new(0.05, limits, params).unwrap());
            fast.prepare(&Camera::new(100.0, 100.0, 31.5, 23.5, 64, 48, 5000.0).unwrap());
            let mut open = 0;
            for i in 0..12 {
                // A slanted, bumpy wall seen from a camera that moves a little, with pixels small
                // enough for 5 cm voxels to be split (not walked) out to 3 m.
                let mut frame = wall_frame(2.0, 64, 48);
                frame.camera = Camera::new(100.0, 100.0, 31.5, 23.5, 64, 48, 5000.0).unwrap();
                for v in 0..48 {
                    for u in 0..64 {
                        let bump = ((u * 5 + v * 3 + i * 7) % 11) as f32 * 0.01;
                        frame.depth.set(u, v, 1.2 + 0.02 * u as f32 + 0.01 * v as f32 + bump);
                    }
                }
                let eye = Vector3::new(0.013 + 0.01 * i as f64, 0.021 - 0.004 * i as f64, 0.017);
                frame.pose = look_at(eye, eye + Vector3::new(1.0, 0.05, -0.02)).unwrap();
                let count =
                    |c: CrossedVoxels| c.crossed.iter().flat_map(|(_, m)| m).map(|w| w.count_ones()).sum::<u32>();
                open += count(fast.project(&frame, false)) - count(fast.project(&frame, true));
                fast.integrate(&frame).unwrap();
                let all = full.project(&frame, false);
                full.apply_marks(ScanMarks::of_crossed(all));
                // The voxels at the clamp the projection reads are the grid's, brick by brick.
                let min = fast.min;
                for (key, brick) in fast.log_odds().bricks() {
                    let want = brick.slots_where(|l| *l == min);
                    assert_eq!(fast.at_min.get(key).copied().unwrap_or_default(), want, "frame {i}, {key:?}");
                }
                assert!(fast.at_min.keys().all(|k| fast.log_odds().brick(*k).is_some()));
            }
            assert_eq!(fast.at_min.is_empty(), p_miss > 0.5, "p_miss {p_miss}");
            let bits = |e: &LogOddsEngine| {
                let mut v: Vec<(VoxelKey, u32)> = e.log_odds().iter().map(|(k, l)| (k, l.to_bits())).collect();
                v.sort();
                v
            };
            assert!(fast.log_odds().len() > 5000);
            assert_eq!(bits(&fast), bits(&full), "p_miss {p_miss}");
            // (Voxels reported crossed only when tested: fewer with voxels left open.)
            assert_eq!(open > 10_000, p_miss < 0.5, "p_miss {p_miss}: {open} voxels left open");
        }
    }

    /// `--bounds` maps only its box: no voxel outside it is touched, however a ray meets its
    /// faces. Faces on voxel faces, crossed by rays going in and coming out (the camera
    /// outside the box, surfaces beyond it), from several poses, every marking; and the box
    /// is mapped.
    #[test]
    fn nothing_outside_the_bounds_is_touched() {
        let bounds = Aabb { min: [1.0, -0.4, -0.3], max: [2.0, 0.5, 0.35] };
        let (lo, hi) = box_keys(&bounds, 0.05);
        let limits = RayLimits { max_range: Some(6.0), bounds: Some(bounds) };
        let octomap = SensorModel::OCTOMAP;
        for (model, marking) in [
            (octomap, Marking::Project),
            (octomap, Marking::Walk),
            (octomap, Marking::Centres),
            (SensorModel::CRM_PAPER, Marking::Project),
        ] {
            let params = LogOddsParams { model, marking, ..Default::default() };
            let mut e = LogOddsEngine::new(0.05, limits, params).unwrap();
            for i in 0..8 {
                let mut frame = wall_frame(3.0, 96, 72);
                frame.camera = Camera::new(60.0, 60.0, 47.5, 35.5, 96, 72, 5000.0).unwrap();
                for v in 0..72 {
                    for u in 0..96 {
                        frame.depth.set(u, v, 2.2 + 0.013 * u as f32 + 0.007 * v as f32 + 0.05 * (i % 3) as f32);
                    }
                }
                let eye = Vector3::new(0.013 + 0.03 * i as f64, 0.021 - 0.017 * i as f64, 0.017 + 0.011 * i as f64);
                frame.pose = look_at(eye, eye + Vector3::new(1.0, 0.04 * i as f64 - 0.1, 0.03)).unwrap();
                e.integrate(&frame).unwrap();
            }
            let grid = e.log_odds();
            let outside = grid.iter().filter(|(k, _)| !key_in_box(k.0, (lo, hi))).count();
            assert_eq!(outside, 0, "{model:?} {marking:?}: {outside} of {} voxels outside the bounds", grid.len());
            assert!(grid.len() > 4_000, "{model:?} {marking:?}: {} voxels", grid.len());
        }
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
        let cases = [
            (SensorModel::OCTOMAP, Marking::Project),
            (SensorModel::CRM_PAPER, Marking::Project),
            (SensorModel::OCTOMAP, Marking::Centres),
        ];
        for (model, marking) in cases {
            let run = |threads| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                let params = LogOddsParams { model, marking, ..Default::default() };
                let mut e = LogOddsEngine::new(0.02, RayLimits::default(), params).unwrap();
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
            assert_eq!(one, run(2), "{model:?} {marking:?}");
            assert_eq!(one, run(3), "{model:?} {marking:?}");
        }
    }
}
