//! The MRFMap accuracy metric for probabilistic maps (docs/ALGORITHMS.md 6.1, MRFMap sec. III-D).
//!
//! A held-out depth pixel is explained by the map if the most likely generating surface
//! along its ray lies where the held-out depth says. Each voxel with occupancy `p` is a slab
//! of constant occlusion density `alpha = -ln(1 - p) / r` per metre (a full crossing occludes
//! with probability `p`; partial crossings scale with length). Visibility is
//! `vis(s) = exp(-integral alpha)`, the generating-surface density `omega(s) = alpha(s) vis(s)`.
//! Inside a voxel omega only falls, so its maximum is at the entry of some voxel.
//!
//! Classification of a pixel with held-out range `r_D`:
//! - no allocated voxel on the ray: *invalid*;
//! - visibility never below 0.9 (the map does not explain a surface): *inaccurate* if the
//!   mapped part of the ray reached `r_D` (the map claims free space where the surface is),
//!   else *invalid* (the map ended first). The MRFMap paper instead counts the latter as
//!   accurate ("the measurement lies beyond the map boundary"); docs/ALGORITHMS.md rules by
//!   default and [`AccuracyParams::beyond_map_is_accurate`] selects the paper's rule;
//! - otherwise *accurate* iff `|argmax omega - r_D| <= k sigma` (defaults `k = 1`,
//!   `sigma = 0.05 m`: the reference implementation's setting; the paper's text says 1.5 sigma).
//!
//! The reference implementation places the peak differently ([`PeakRule::Exit`],
//! `--metric reference`): per voxel `w = (vis_before - vis_after) / l`, the generating
//! density averaged over the voxel; the peak is the voxel with the largest `w`, located where
//! the ray *leaves* it, and compared with the held-out depth as z-depth,
//! `|z_exit - z_D| <= k sigma`. The reference also adds the sensor bias at the exit to
//! `z_exit` when its held-out target carries that bias; here held-out depths are true depths,
//! so that term is zero. The visibility and no-voxel rules are the same.
//!
//! Unallocated voxels read as empty; for log-odds maps voxels at or below the occupancy
//! threshold read as empty too, as the paper did for OctoMap.

use std::ops::ControlFlow;

use rayon::prelude::*;

use crate::frames::{Camera, DepthImage, NoiseModel, Pose};
use crate::inference::EngineKind;
use crate::map::Aabb;
use crate::map::{BRICK_EDGE, BRICK_VOXELS, BrickKey, Map, MapVoxel, OCCUPIED_THRESHOLD};
use crate::rays::{for_each_crossing, pixel_direction, pose_parts};

/// Occupancies are clamped below 1 by this much so that `alpha` stays finite.
const P_MAX: f64 = 1.0 - 1e-6;

/// Visibility above which a ray counts as not explained by any surface.
pub const VISIBILITY_FLOOR: f64 = 0.9;

/// Settings of the metric.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AccuracyParams {
    /// Tolerance unit in metres (default 0.05).
    pub sigma: f64,
    /// Tolerance in units of `sigma` (default 1; the paper's text says 1.5).
    pub k: f64,
    /// Occupancies at or below this read as empty (`Some(0.5)` for log-odds maps).
    pub empty_at_or_below: Option<f32>,
    /// The MRFMap paper's boundary rule: a ray the map does not stop (visibility stays at or
    /// above 0.9) whose held-out depth lies beyond the mapped part counts as *accurate*
    /// instead of *invalid*. Off by default (docs/ALGORITHMS.md 6.1).
    pub beyond_map_is_accurate: bool,
    /// Where the most likely generating surface is and how it is compared.
    pub peak: PeakRule,
}

/// How a ray's most likely generating surface is found and compared with the held-out depth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PeakRule {
    /// docs/ALGORITHMS.md 6.1: the largest `omega` (a voxel's entry), compared as range.
    Entry,
    /// The reference implementation: the voxel with the largest mean `omega` over its length,
    /// located at its exit and compared as z-depth.
    Exit,
}

impl PeakRule {
    /// Every rule with its command-line name.
    const NAMED: [(PeakRule, &'static str); 2] = [(PeakRule::Entry, "algorithms"), (PeakRule::Exit, "reference")];

    /// The command-line name (`--metric`): `algorithms` or `reference`.
    pub fn name(self) -> &'static str {
        Self::NAMED.iter().find(|(r, _)| *r == self).map_or("", |(_, n)| n)
    }
}

impl std::str::FromStr for PeakRule {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Self::NAMED
            .iter()
            .find(|(_, n)| *n == s)
            .map(|(r, _)| *r)
            .ok_or_else(|| format!("unknown metric {s:?}; available: algorithms, reference"))
    }
}

impl AccuracyParams {
    /// Defaults for `map`: sigma 0.05 m, k 1, thresholded reading for log-odds maps.
    pub fn for_map(map: &Map) -> Self {
        AccuracyParams {
            sigma: 0.05,
            k: 1.0,
            empty_at_or_below: (map.engine == EngineKind::LogOdds).then_some(OCCUPIED_THRESHOLD),
            beyond_map_is_accurate: false,
            peak: PeakRule::Entry,
        }
    }

    fn occupancy(&self, v: &MapVoxel) -> f64 {
        match self.empty_at_or_below {
            Some(t) if v.occupancy <= t => 0.0,
            _ => (v.occupancy as f64).clamp(0.0, P_MAX),
        }
    }
}

/// What the metric says about one pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelClass {
    /// The held-out image has no depth here.
    NoDepth,
    /// The map's most likely surface is within `k sigma` of the held-out depth.
    Accurate,
    /// The map puts the surface elsewhere, or claims free space where it is.
    Inaccurate,
    /// The map says nothing about this ray (not counted).
    Invalid,
}

/// One voxel along an evaluated ray, for plots.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProfileStep {
    /// Entry range (m).
    pub s_in: f64,
    /// Exit range (m).
    pub s_out: f64,
    /// Occupancy as the metric reads it (0 for unallocated voxels).
    pub occupancy: f64,
    /// Occlusion density (1/m).
    pub alpha: f64,
    /// Visibility at entry.
    pub visibility: f64,
}

/// The metric's view of one ray.
#[derive(Clone, Debug, PartialEq)]
pub struct RayVerdict {
    /// The classification.
    pub class: PixelClass,
    /// Range of the most likely generating surface, if the visibility fell below 0.9.
    pub peak: Option<f64>,
    /// Held-out range along the ray.
    pub range: f64,
}

/// Where a ray's walk ended, before any tolerance is applied.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Walked {
    /// The ray crossed no mapped voxel.
    Unmapped,
    /// Visibility stayed at or above the floor; `beyond_map`: the held-out depth lies past the
    /// last mapped voxel.
    Unstopped { beyond_map: bool },
    /// The range of the most likely generating surface.
    Peak(f64),
}

impl Walked {
    fn peak(self) -> Option<f64> {
        if let Walked::Peak(s) = self { Some(s) } else { None }
    }
}

/// What the walk needs to know about a brick without visiting its voxels.
#[derive(Clone, Copy, Debug)]
struct BrickSummary {
    /// Every voxel reads as empty: the walk crosses the brick in one step.
    empty: bool,
    /// Every voxel is allocated (so "mapped space" covers the whole brick).
    full: bool,
}

/// Scores views and rays against one map. Building it summarises the map once (bounds,
/// the largest occupancy, which bricks read as empty), so reuse it for many views.
///
/// Rays are walked in two levels: brick by brick, and voxel by voxel only inside bricks that
/// hold something the metric can see. Free and unknown space — most of every ray — is
/// crossed eight voxels at a time. A ray stops once its verdict cannot change: visibility
/// below 0.9 and no voxel of the map dense enough to beat its best peak.
pub struct Scorer<'a> {
    map: &'a Map,
    params: AccuracyParams,
    /// With a model, the tolerance is `k` times its std at the peak ([`Scorer::with_model_tolerance`]).
    noise: Option<&'a NoiseModel>,
    /// Allocated bricks' bounds (unallocated voxels inside read as empty); `None` for an empty map.
    bounds: Option<Aabb>,
    bricks: rustc_hash::FxHashMap<BrickKey, BrickSummary>,
    /// Largest occlusion density of any voxel: bounds what the rest of a ray can add.
    alpha_max: f64,
}

impl<'a> Scorer<'a> {
    /// Summarises `map` for scoring with `params`.
    pub fn new(map: &'a Map, params: AccuracyParams) -> Self {
        let r = map.resolution();
        let bounds = map
            .voxels
            .brick_key_bounds()
            .map(|(lo, hi)| Aabb { min: lo.0.map(|i| i as f64 * r), max: hi.0.map(|i| (i + 1) as f64 * r) });
        let mut p_max = 0.0f64;
        let bricks = map
            .voxels
            .bricks()
            .map(|(k, b)| {
                let brick_max = b.iter().map(|(_, v)| params.occupancy(v)).fold(0.0, f64::max);
                p_max = p_max.max(brick_max);
                (*k, BrickSummary { empty: brick_max == 0.0, full: b.len() == BRICK_VOXELS })
            })
            .collect();
        Scorer { map, params, noise: None, bounds, bricks, alpha_max: -(1.0 - p_max).ln() / r }
    }

    /// Judges against `k` times `noise`'s std at the peak's z-depth for the ray's pixel,
    /// instead of `k sigma`: the reference implementation's tolerance (`get_depth_sigma(s)`)
    /// when it models the sensor, as the MRFMap paper describes its Table I ("used during
    /// inference and accuracy estimation").
    pub fn with_model_tolerance(mut self, noise: &'a NoiseModel) -> Self {
        self.noise = Some(noise);
        self
    }

    /// Walks `origin + s dir` (unit `dir`) through the map and classifies it against the
    /// held-out range `r_d`; `cz` converts range to z-depth (the unit ray's z component in the
    /// camera frame; [`PeakRule::Exit`] compares z-depths); `pixel` is the ray's, for a
    /// per-patch tolerance. `profile` receives every step (a voxel, or a whole empty brick).
    pub fn classify_ray(
        &self,
        origin: [f64; 3],
        dir: [f64; 3],
        (r_d, cz): (f64, f64),
        pixel: (u32, u32),
        profile: impl FnMut(ProfileStep),
    ) -> RayVerdict {
        let walked = self.walk(origin, dir, r_d, profile);
        RayVerdict { class: self.judge(walked, (r_d, cz), pixel, self.noise), peak: walked.peak(), range: r_d }
    }

    /// Walks the ray (see [`Scorer::classify_ray`]) up to where its verdict is settled.
    fn walk(&self, origin: [f64; 3], dir: [f64; 3], r_d: f64, mut profile: impl FnMut(ProfileStep)) -> Walked {
        let Some((s0, s1)) = self.bounds.and_then(|b| b.clip(origin, dir, 0.0, f64::INFINITY)) else {
            return Walked::Unmapped;
        };
        let r = self.map.resolution();
        let mut vis = 1.0f64;
        let mut best = (0.0f64, f64::NAN); // (omega, range)
        let mut last_mapped: Option<f64> = None;
        let brick_edge = r * BRICK_EDGE as f64;
        // The verdict is settled once the visibility is below the floor (so the peak rule
        // applies) and even the densest voxel of the map could not beat the best peak.
        let settled = |vis: f64, best: f64| vis < VISIBILITY_FLOOR && self.alpha_max * vis < best;
        for_each_crossing(origin, dir, s0, s1, brick_edge, |b| {
            let key = BrickKey(b.key.0);
            let empty_step =
                |vis| ProfileStep { s_in: b.s_in, s_out: b.s_out, occupancy: 0.0, alpha: 0.0, visibility: vis };
            match self.bricks.get(&key) {
                None => {
                    profile(empty_step(vis));
                    return ControlFlow::Continue(());
                }
                Some(BrickSummary { empty: true, full: true }) => {
                    last_mapped = Some(b.s_out);
                    profile(empty_step(vis));
                    return ControlFlow::Continue(());
                }
                Some(_) => {}
            }
            let brick = self.map.voxels.brick(key);
            for_each_crossing(origin, dir, b.s_in, b.s_out, r, |c| {
                // Rounding at brick faces can put a voxel in the neighbouring brick.
                let voxel = if c.key.brick() == key {
                    brick.and_then(|br| br.get(c.key.slot()))
                } else {
                    self.map.voxels.get(c.key)
                };
                let p = voxel.map_or(0.0, |v| self.params.occupancy(v));
                if voxel.is_some() {
                    last_mapped = Some(c.s_out);
                }
                // Empty space needs no logarithm or exponential.
                let alpha = if p > 0.0 { -(1.0 - p).ln() / r } else { 0.0 };
                profile(ProfileStep { s_in: c.s_in, s_out: c.s_out, occupancy: p, alpha, visibility: vis });
                if alpha > 0.0 {
                    let after = vis * (-alpha * c.length()).exp();
                    let candidate = match self.params.peak {
                        PeakRule::Entry => (alpha * vis, c.s_in),
                        // Never above alpha * vis, so `settled` below still holds.
                        PeakRule::Exit => ((vis - after) / c.length().max(f64::MIN_POSITIVE), c.s_out),
                    };
                    if candidate.0 > best.0 {
                        best = candidate;
                    }
                    vis = after;
                }
                if settled(vis, best.0) { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
            });
            if settled(vis, best.0) { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        });
        let Some(last_mapped) = last_mapped else { return Walked::Unmapped };
        if vis >= VISIBILITY_FLOOR {
            // Visibility only falls along a ray: it never dropped below the floor.
            return Walked::Unstopped { beyond_map: last_mapped < r_d };
        }
        Walked::Peak(best.1)
    }

    /// The class of a walked ray with held-out range `r_d` (`cz` converts range to z-depth),
    /// judged against `k` times `noise`'s std at the peak, or `k sigma` without a model.
    fn judge(
        &self,
        walked: Walked,
        (r_d, cz): (f64, f64),
        pixel: (u32, u32),
        noise: Option<&NoiseModel>,
    ) -> PixelClass {
        let peak = match walked {
            Walked::Unmapped => return PixelClass::Invalid,
            Walked::Unstopped { beyond_map: false } => return PixelClass::Inaccurate,
            Walked::Unstopped { beyond_map: true } if self.params.beyond_map_is_accurate => {
                return PixelClass::Accurate;
            }
            Walked::Unstopped { beyond_map: true } => return PixelClass::Invalid,
            Walked::Peak(s) => s,
        };
        let miss = match self.params.peak {
            PeakRule::Entry => (peak - r_d).abs(),
            PeakRule::Exit => (peak - r_d).abs() * cz,
        };
        let sigma = match noise {
            Some(noise) => noise.bias_std(pixel.0, pixel.1, peak * cz).1,
            None => self.params.sigma,
        };
        if miss <= self.params.k * sigma { PixelClass::Accurate } else { PixelClass::Inaccurate }
    }

    /// Scores the held-out z-depth image `depth` seen from `pose` (parallel by row).
    pub fn score_view(&self, camera: &Camera, pose: &Pose, depth: &DepthImage) -> ViewScore {
        self.score_view_each(camera, pose, depth, &[self.noise]).pop().expect("one tolerance")
    }

    /// [`Scorer::score_view`] under several tolerances at the cost of one: per entry of
    /// `tolerances`, `k` times that model's std at the peak, or `k sigma` for `None`. Each ray
    /// is walked once; only the verdicts differ.
    pub fn score_view_each(
        &self,
        camera: &Camera,
        pose: &Pose,
        depth: &DepthImage,
        tolerances: &[Option<&NoiseModel>],
    ) -> Vec<ViewScore> {
        let (w, h) = (depth.width(), depth.height());
        let (rotation, origin) = pose_parts(pose);
        let rays: Vec<Option<(Walked, (f64, f64))>> = (0..h)
            .into_par_iter()
            .flat_map_iter(|v| {
                (0..w).map(move |u| {
                    let z = depth.get(u, v)?;
                    let (d, norm) = pixel_direction(camera, &rotation, u, v);
                    let r_d = z as f64 * norm;
                    Some((self.walk(origin, d, r_d, |_| {}), (r_d, 1.0 / norm)))
                })
            })
            .collect();
        tolerances
            .iter()
            .map(|&noise| {
                let classes: Vec<PixelClass> = rays
                    .iter()
                    .enumerate()
                    .map(|(i, ray)| match *ray {
                        None => PixelClass::NoDepth,
                        Some((walked, range)) => self.judge(walked, range, ((i as u32) % w, (i as u32) / w), noise),
                    })
                    .collect();
                let count = |c| classes.iter().filter(|x| **x == c).count();
                ViewScore {
                    width: w,
                    height: h,
                    accurate: count(PixelClass::Accurate),
                    inaccurate: count(PixelClass::Inaccurate),
                    invalid: count(PixelClass::Invalid),
                    classes,
                }
            })
            .collect()
    }

    /// The profile of pixel `(u, v)`'s ray (for the per-ray plot) and its verdict; `None`
    /// when `depth` has no value there or the pixel is outside the image.
    pub fn ray_profile(
        &self,
        camera: &Camera,
        pose: &Pose,
        depth: &DepthImage,
        (u, v): (u32, u32),
    ) -> Option<(Vec<ProfileStep>, RayVerdict)> {
        if u >= depth.width() || v >= depth.height() {
            return None;
        }
        let z = depth.get(u, v)?;
        let (rotation, origin) = pose_parts(pose);
        let (d, norm) = pixel_direction(camera, &rotation, u, v);
        let mut steps = Vec::new();
        let verdict = self.classify_ray(origin, d, (z as f64 * norm, 1.0 / norm), (u, v), |s| steps.push(s));
        Some((steps, verdict))
    }
}

/// Per-pixel classes and counts for one held-out view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewScore {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Class per pixel, row-major.
    pub classes: Vec<PixelClass>,
    /// Accurate pixels.
    pub accurate: usize,
    /// Inaccurate pixels.
    pub inaccurate: usize,
    /// Invalid pixels (not counted).
    pub invalid: usize,
}

impl ViewScore {
    /// Counted pixels: accurate + inaccurate.
    pub fn valid(&self) -> usize {
        self.accurate + self.inaccurate
    }

    /// accurate / valid, `None` when no pixel is valid.
    pub fn accuracy(&self) -> Option<f64> {
        (self.valid() > 0).then(|| self.accurate as f64 / self.valid() as f64)
    }
}

/// Scores `map` against the held-out z-depth image `depth` seen from `pose`; a one-view
/// shorthand for [`Scorer::score_view`].
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::frames::{Camera, DepthImage, look_at};
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{AccuracyParams, score_view};
/// // A solid wall of voxels at x in [2.0, 2.1) seen head-on from the origin.
/// let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
/// for y in -5..5 { for z in -5..5 {
///     map.voxels.insert(VoxelKey([20, y, z]), MapVoxel { occupancy: 0.95, variance: 0.0 });
/// } }
/// let cam = Camera::new(10.0, 10.0, 1.5, 1.5, 4, 4, 1000.0).unwrap();
/// let pose = look_at([0.0, 0.01, 0.01].into(), [1.0, 0.01, 0.01].into()).unwrap();
/// let mut depth = DepthImage::new(4, 4);
/// depth.set(1, 1, 2.02);
/// let score = score_view(&map, &cam, &pose, &depth, &AccuracyParams::for_map(&map));
/// assert_eq!((score.accurate, score.valid()), (1, 1));
/// ```
pub fn score_view(map: &Map, camera: &Camera, pose: &Pose, depth: &DepthImage, params: &AccuracyParams) -> ViewScore {
    Scorer::new(map, *params).score_view(camera, pose, depth)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::VoxelKey;
    use crate::random::Rng;

    fn walk(map: &Map) -> Scorer<'_> {
        Scorer::new(
            map,
            AccuracyParams {
                sigma: 0.05,
                k: 1.0,
                empty_at_or_below: None,
                beyond_map_is_accurate: false,
                peak: PeakRule::Entry,
            },
        )
    }

    /// A map with a slab of voxels at x index `i` (all y, z in -3..3), occupancy `p`.
    fn slab(map: &mut Map, i: i32, p: f32) {
        for y in -3..3 {
            for z in -3..3 {
                map.voxels.insert(VoxelKey([i, y, z]), MapVoxel { occupancy: p, variance: 0.0 });
            }
        }
    }

    const O: [f64; 3] = [0.0, 0.05, 0.05];
    const X: [f64; 3] = [1.0, 0.0, 0.0];

    #[test]
    fn wall_at_the_true_range_is_accurate() {
        let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        slab(&mut map, 0, 0.01);
        slab(&mut map, 20, 0.9);
        let v = walk(&map).classify_ray(O, X, (2.03, 1.0), (0, 0), |_| {});
        assert_eq!(v.class, PixelClass::Accurate);
        assert!((v.peak.unwrap() - 2.0).abs() < 1e-12);
        // 0.2 m further away than the wall: the map explains the ray wrongly.
        assert_eq!(walk(&map).classify_ray(O, X, (2.25, 1.0), (0, 0), |_| {}).class, PixelClass::Inaccurate);
    }

    #[test]
    fn reference_rule_places_the_peak_at_the_exit_and_compares_z_depth() {
        let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        slab(&mut map, 20, 0.9);
        let reference = Scorer::new(&map, AccuracyParams { peak: PeakRule::Exit, ..AccuracyParams::for_map(&map) });
        // The held-out surface at the wall voxel's far face: the entry rule misses by 0.1 m.
        assert_eq!(walk(&map).classify_ray(O, X, (2.1, 1.0), (0, 0), |_| {}).class, PixelClass::Inaccurate);
        let v = reference.classify_ray(O, X, (2.1, 1.0), (0, 0), |_| {});
        assert_eq!(v.class, PixelClass::Accurate);
        assert!((v.peak.unwrap() - 2.1).abs() < 1e-12, "peak {:?}", v.peak);
        // 0.08 m of range is 0.04 m of z-depth on a ray at 60 degrees to the optical axis.
        assert_eq!(reference.classify_ray(O, X, (2.18, 1.0), (0, 0), |_| {}).class, PixelClass::Inaccurate);
        assert_eq!(reference.classify_ray(O, X, (2.18, 0.5), (0, 0), |_| {}).class, PixelClass::Accurate);
        assert_eq!("reference".parse::<PeakRule>(), Ok(PeakRule::Exit));
        assert_eq!(PeakRule::Entry.name().parse::<PeakRule>(), Ok(PeakRule::Entry));
        assert!("exit".parse::<PeakRule>().is_err());
    }

    /// With a model tolerance the pixel's std at the peak's z-depth replaces sigma: a model
    /// whose std grows with depth accepts a 0.08 m miss at 2.1 m (std 0.105), not at 1.1 m
    /// (0.055), and a patch with a 0.01 m std rejects it.
    #[test]
    fn model_tolerance_is_the_pixels_std_at_the_peak() {
        use crate::frames::{PatchModel, Poly};
        // Left patch of a 2x1-patch image: std 0.05 z; right patch: 0.01 m.
        let noise = NoiseModel {
            patches: Some(PatchModel {
                size: 10,
                rows: 1,
                cols: 2,
                bias: vec![Poly::default(); 2],
                std: vec![Poly([0.0, 0.05, 0.0]), Poly([0.01, 0.0, 0.0])],
            }),
            ..NoiseModel::aggregate(Poly::default(), Poly([0.05, 0.0, 0.0]))
        };
        let verdict = |index: i32, depth: f64, pixel: (u32, u32), model: bool| {
            let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
            slab(&mut map, index, 0.9);
            let scorer = Scorer::new(&map, AccuracyParams { peak: PeakRule::Exit, ..AccuracyParams::for_map(&map) });
            let scorer = if model { scorer.with_model_tolerance(&noise) } else { scorer };
            scorer.classify_ray(O, X, (depth, 1.0), pixel, |_| {}).class
        };
        // Peak exits at 2.1 m and 1.1 m; held-out depths 0.08 m further.
        assert_eq!(verdict(20, 2.18, (0, 0), true), PixelClass::Accurate);
        assert_eq!(verdict(20, 2.18, (0, 0), false), PixelClass::Inaccurate, "constant 0.05 m");
        assert_eq!(verdict(20, 2.18, (15, 0), true), PixelClass::Inaccurate, "the 0.01 m patch");
        assert_eq!(verdict(10, 1.18, (0, 0), true), PixelClass::Inaccurate, "std 0.055 at 1.1 m");
    }

    /// One walk, several tolerances: each score equals a scorer of that tolerance's own.
    #[test]
    fn scoring_under_several_tolerances_equals_scoring_under_each() {
        use crate::frames::{Camera, Poly, look_at};
        let mut rng = Rng::new(5);
        let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        for _ in 0..3000 {
            let key =
                VoxelKey([rng.range(10.0, 30.0) as i32, rng.range(-8.0, 8.0) as i32, rng.range(-8.0, 8.0) as i32]);
            map.voxels.insert(key, MapVoxel { occupancy: rng.uniform() as f32, variance: 0.0 });
        }
        let camera = Camera::new(20.0, 20.0, 15.5, 11.5, 32, 24, 1000.0).unwrap();
        let pose = look_at([0.0, 0.0, 0.0].into(), [1.0, 0.05, 0.02].into()).unwrap();
        let mut depth = DepthImage::new(32, 24);
        for v in 0..24 {
            for u in 0..32 {
                if rng.uniform() < 0.9 {
                    depth.set(u, v, rng.range(1.0, 3.5) as f32);
                }
            }
        }
        let noise = NoiseModel::aggregate(Poly::default(), Poly([0.0, 0.0, 0.02]));
        for beyond in [false, true] {
            let params = AccuracyParams {
                peak: PeakRule::Exit,
                beyond_map_is_accurate: beyond,
                ..AccuracyParams::for_map(&map)
            };
            let scorer = Scorer::new(&map, params);
            let both = scorer.score_view_each(&camera, &pose, &depth, &[None, Some(&noise)]);
            // Pixel by pixel, each tolerance on its own scorer.
            let (rotation, origin) = pose_parts(&pose);
            for (scorer, score) in [
                (Scorer::new(&map, params), &both[0]),
                (Scorer::new(&map, params).with_model_tolerance(&noise), &both[1]),
            ] {
                for (i, class) in score.classes.iter().enumerate() {
                    let (u, v) = (i as u32 % 32, i as u32 / 32);
                    let expected = depth.get(u, v).map_or(PixelClass::NoDepth, |z| {
                        let (d, norm) = pixel_direction(&camera, &rotation, u, v);
                        scorer.classify_ray(origin, d, (z as f64 * norm, 1.0 / norm), (u, v), |_| {}).class
                    });
                    assert_eq!(*class, expected, "pixel {u}, {v}");
                }
            }
            let (constant, modelled) = (&both[0], &both[1]);
            assert_eq!(
                modelled,
                &Scorer::new(&map, params).with_model_tolerance(&noise).score_view(&camera, &pose, &depth)
            );
            assert_ne!(constant.classes, modelled.classes, "the tolerances must differ somewhere for this to test");
            assert!(constant.accurate > 0 && constant.inaccurate > 0 && constant.invalid > 0, "{constant:?}");
        }
    }

    #[test]
    fn wall_in_front_of_the_true_surface_is_inaccurate() {
        let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        slab(&mut map, 10, 0.8);
        slab(&mut map, 20, 0.99);
        let v = walk(&map).classify_ray(O, X, (2.0, 1.0), (0, 0), |_| {});
        assert_eq!(v.class, PixelClass::Inaccurate);
        assert!((v.peak.unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn empty_and_free_maps() {
        let map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        assert!(Scorer::new(&map, AccuracyParams::for_map(&map)).bounds.is_none(), "empty map has no bounds");
        let cam = Camera::new(10.0, 10.0, 1.5, 1.5, 4, 4, 1000.0).unwrap();
        let mut depth = DepthImage::new(4, 4);
        depth.set(0, 0, 1.0);
        let pose = crate::frames::look_at([0.0; 3].into(), [1.0, 0.0, 0.0].into()).unwrap();
        let s = score_view(&map, &cam, &pose, &depth, &AccuracyParams::for_map(&map));
        assert_eq!((s.invalid, s.valid(), s.accuracy()), (1, 0, None));
        // Known-free space reaching past the surface: inaccurate; ending before it: invalid.
        let mut free = Map::new(EngineKind::Mrf, 0.1).unwrap();
        for i in 0..15 {
            slab(&mut free, i, 0.001);
        }
        assert_eq!(walk(&free).classify_ray(O, X, (1.0, 1.0), (0, 0), |_| {}).class, PixelClass::Inaccurate);
        assert_eq!(walk(&free).classify_ray(O, X, (2.0, 1.0), (0, 0), |_| {}).class, PixelClass::Invalid);
        let paper = AccuracyParams { beyond_map_is_accurate: true, ..AccuracyParams::for_map(&free) };
        assert_eq!(
            Scorer::new(&free, paper).classify_ray(O, X, (2.0, 1.0), (0, 0), |_| {}).class,
            PixelClass::Accurate
        );
        assert_eq!(
            Scorer::new(&free, paper).classify_ray(O, X, (1.0, 1.0), (0, 0), |_| {}).class,
            PixelClass::Inaccurate
        );
    }

    #[test]
    fn log_odds_maps_read_free_voxels_as_empty() {
        let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        slab(&mut map, 5, 0.45);
        slab(&mut map, 20, 0.8);
        let params = AccuracyParams::for_map(&map);
        assert_eq!(params.empty_at_or_below, Some(0.5));
        let v = Scorer::new(&map, params).classify_ray(O, X, (2.02, 1.0), (0, 0), |_| {});
        assert_eq!(v.class, PixelClass::Accurate);
    }

    #[test]
    fn partial_crossings_occlude_in_proportion_to_length() {
        // A ray clipping a voxel over a quarter of its width loses (1 - p)^(1/4) visibility.
        let mut map = Map::new(EngineKind::Mrf, 0.1).unwrap();
        map.voxels.insert(VoxelKey([5, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        // Off the ray; widens the bounds, and is dense enough that the walk goes on past the
        // partial voxel (it stops once nothing in the map could beat its best peak).
        map.voxels.insert(VoxelKey([9, 5, 0]), MapVoxel { occupancy: 0.999, variance: 0.0 });
        // Enters voxel (5, 0, 0) through x = 0.5 at y = 0.075 and leaves through y = 0.1.
        let dir = [0.6, 0.8, 0.0];
        let origin = [0.5 - 0.06, 0.075 - 0.08, 0.05];
        let mut steps = Vec::new();
        walk(&map).classify_ray(origin, dir, (1.0, 1.0), (0, 0), |s| steps.push(s));
        let s = steps.iter().find(|s| s.occupancy > 0.0).unwrap();
        let fraction = (s.s_out - s.s_in) / 0.1;
        assert!((fraction - 0.3125).abs() < 1e-9, "fraction {fraction}");
        let vis_after = steps.iter().find(|x| x.s_in >= s.s_out).unwrap().visibility;
        assert!((vis_after - 0.1f64.powf(fraction)).abs() < 1e-6, "{vis_after}"); // occupancy is an f32
        assert!(fraction > 0.0 && fraction < 1.0, "fraction {fraction}");
    }

    #[test]
    fn visibility_matches_fine_numerical_integration() {
        let mut rng = Rng::new(99);
        let r = 0.1;
        let mut map = Map::new(EngineKind::Mrf, r).unwrap();
        for _ in 0..400 {
            let k = VoxelKey([0; 3].map(|_| (rng.next_u64() % 8) as i32));
            map.voxels.insert(k, MapVoxel { occupancy: rng.uniform() as f32 * 0.9, variance: 0.0 });
        }
        let w = walk(&map);
        for _ in 0..50 {
            let origin = [0; 3].map(|_| rng.range(0.0, 0.8));
            let mut dir = [0; 3].map(|_| rng.range(-1.0, 1.0));
            let n = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
            dir = dir.map(|d| d / n);
            let mut steps = Vec::new();
            w.classify_ray(origin, dir, (100.0, 1.0), (0, 0), |s| steps.push(s));
            // Integrate alpha by midpoint sampling from the walk's start to each step's entry.
            let h = 1e-5;
            let mut integral = 0.0f64;
            let mut s = steps.first().map_or(0.0, |x| x.s_in);
            for st in &steps {
                while s + h <= st.s_in {
                    let m = s + 0.5 * h;
                    let p = [0, 1, 2].map(|a| origin[a] + m * dir[a]);
                    let occ = map.voxels.get(VoxelKey::from_point(p, r)).map_or(0.0, |v| v.occupancy as f64);
                    integral += -(1.0 - occ.min(P_MAX)).ln() / r * h;
                    s += h;
                }
                let numeric = (-integral).exp();
                assert!((st.visibility - numeric).abs() < 2e-3, "vis {} vs numeric {numeric}", st.visibility);
            }
        }
    }
}
