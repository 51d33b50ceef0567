//! Confidence-rich mapping (CRM paper secs. 4-6, docs/ALGORITHMS.md 5.2): every voxel keeps a
//! discrete distribution over its occupancy `m` (K particles at `m_k = k / (K - 1)`), so it
//! has a mean *and* a variance; each ray updates the voxels it crosses through the sensor
//! cause model derived from the forward noise model.
//!
//! Per ray (voxels `1..N`, plus the final cause `N+1` "the light passed the whole ray"):
//! cause prior `p_c(j) = m_j prod_{l<j} (1 - m_l)` with the current means, sensor cause model
//! `q(j) ∝ nu_j p_c(j)`, and for voxel `i` with `P_before`, `P_on`, `P_after` (prefix and
//! suffix sums of `q`) the pdf update `p(m) <- (alpha m + beta) p(m)`, renormalised. The
//! factors are used multiplied through by `m (1 - m)` (division-free; the same after
//! renormalisation): `alpha' = P_on (1 - m) - P_after m`, `beta' = m (1 - m) P_before + m P_after`.
//! `q` is computed in the log domain, so long rays of confident voxels cannot underflow.
//!
//! Frames: the factors of all rays of a frame are computed in parallel from the map as it was
//! before the frame (a per-frame snapshot of the means, rather than the paper's ray-by-ray
//! order, which cannot run in parallel), then each voxel multiplies in its factors in pixel
//! order. Results do not depend on the number of threads. The final cause's likelihood is the
//! forward model averaged over one voxel past the ray's truncation point (3 std beyond the
//! bias-corrected depth), or over the stretch cut off where the bounds or the max range cut
//! the ray short ([`crate::rays::Segment::beyond`], shared with the MRF engine); beams with no
//! return have no cause on the ray (every voxel's likelihood is 0) and pass it whole.
//!
//! Why it is fast enough to use: along a ray, every voxel before the first one with any
//! likelihood has the factor `1 - m` exactly (no cause before it, none on it), whatever its
//! mean; such *free passes* are only counted per voxel (`n`), and multiplied in as
//! `(1 - m)^n` from a table once a few dozen have gathered (or the voxel gets a factor);
//! until then they stay pending beside its pdf, and its mean is read through them. Where so
//! many passes at once would underflow a confident pdf in f32, they are applied in
//! logarithms instead.
//! Factors within [`FACTOR_EPS`] of constant (voxels behind the surface that explains the
//! reading) are skipped, those within it of `1 - m` counted as passes; the rest (about 25 per
//! ray for a D435 at 0.02 m) are folded into the pdfs brick by brick in parallel. Likelihoods
//! are cut at 6 std ([`crate::frames::TAIL_CUTOFF`]). `engine_equals_plain_per_ray_updates`
//! checks all of this against the plain per-ray update. Speed and memory against log-odds
//! are in BENCHMARKS.md (per frame 18x log-odds with 101 particles, 15x with 15; 6.5x and
//! 5.4x log-odds walking every ray, which this update has to do and log-odds no longer does).
//!
//! A voxel enters the map only when its first frame moves its mean by at least
//! [`NEW_VOXEL_MIN_CHANGE`]: voxels deep behind a surface, which only noisy long readings
//! reach with nearly flat factors, stay unknown instead of sitting at the prior.
//!
//! Known limit: pdfs are f32, so particles whose mass falls below f32's range are lost for
//! good. A voxel seen occupied in a few hundred frames keeps no mass at low occupancy, and if
//! the surface then goes away its mean falls only to the lowest particle left (0.71 after 300
//! frames in `pdfs_stay_normalised_and_finite_over_many_updates`), not towards 0.
//!
//! A limit of the method itself: with voxels much smaller than the noise, a ray's cause
//! model peaks `0.69 sigma^2 / r` in front of its reading through unobserved voxels, and a few
//! readings per voxel leave the surface there (docs/ALGORITHMS.md 5.2; `bench/crm_column.py`
//! checks this engine against the paper's update written again, within 1e-4).

use crate::map::EngineKind;
use std::ops::ControlFlow;
use std::sync::Arc;

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::Engine;
use crate::error::{Error, Result};
use crate::frames::{Frame, NoiseModel, RangeScan, default_noise_model};
use crate::map::{
    BRICK_VOXELS, BrickKey, BrickList, Map, MapVoxel, VoxelKey, check_resolution, key_in_box, mask_set, mask_slots,
};
use crate::rays::{RayLimits, Rays, for_each_crossing};

/// Means are kept in `[MEAN_EPS, 1 - MEAN_EPS]` inside the cause model.
const MEAN_EPS: f64 = 1e-9;

/// Parameters of the CRM engine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CrmParams {
    /// Particles per voxel pdf (the reference: 101). Each allocated voxel costs
    /// `4 * (particles + 1)` bytes (pdf and cached mean), plus 1 KiB of slot table per brick.
    pub particles: usize,
}

impl Default for CrmParams {
    fn default() -> Self {
        CrmParams { particles: 101 }
    }
}

/// Division-free CRM factors `(alpha', beta')` for every voxel of one ray, from the voxels'
/// current means, their likelihoods `nu` and the final cause's likelihood `nu_beyond`.
/// A ray whose cause model carries no information gives `(0, 1)` (no change).
///
/// ```
/// use mrfmap::inference::crm_ray_factors;
/// let mut f = Vec::new();
/// crm_ray_factors(&[0.5, 0.5, 0.5], &[0.0, 10.0, 0.0], 0.0, &mut f);
/// // The middle voxel explains the reading: alpha > 0 (more occupied); the first is passed.
/// assert!(f[1].0 > 0.0 && f[0].0 < 0.0);
/// ```
pub fn crm_ray_factors(means: &[f64], nu: &[f64], nu_beyond: f64, out: &mut Vec<(f64, f64)>) {
    let n = means.len();
    // `out[j].0` holds log q(j) up to a constant, then q(j), j = 0..=n (n = the final cause),
    // before it is overwritten with voxel j's factors: no allocation per ray.
    out.clear();
    let mut log_vis = 0.0f64;
    for j in 0..n {
        let m = means[j].clamp(MEAN_EPS, 1.0 - MEAN_EPS);
        out.push((nu[j].ln() + m.ln() + log_vis, 0.0));
        log_vis += (1.0 - m).ln();
    }
    out.push((nu_beyond.ln() + log_vis, 0.0));
    let max = out.iter().map(|q| q.0).fold(f64::NEG_INFINITY, f64::max);
    if !max.is_finite() {
        out.clear();
        out.resize(n, (0.0, 1.0));
        return;
    }
    let mut total = 0.0;
    for q in out.iter_mut() {
        q.0 = (q.0 - max).exp();
        total += q.0;
    }
    let mut after: f64 = total - out[0].0;
    let mut before = 0.0;
    for j in 0..n {
        let (q_j, q_next) = (out[j].0, out[j + 1].0);
        let m = means[j].clamp(MEAN_EPS, 1.0 - MEAN_EPS);
        let (p_on, p_after, p_before) = (q_j / total, after.max(0.0) / total, before / total);
        out[j] = (p_on * (1.0 - m) - p_after * m, m * (1.0 - m) * p_before + m * p_after);
        before += q_j;
        after -= q_next;
    }
    out.truncate(n);
}

/// Normalised factors `a m + b` (maximum 1 on [0, 1]) within this of constant are skipped,
/// and within this of `1 - m` are counted as free passes: most voxels of a long window in
/// front of or behind the surface, where the cause model gives them no weight to speak of.
const FACTOR_EPS: f64 = 1e-6;

/// Largest free-pass count with a precomputed power table; larger counts compose powers.
const POWER_TABLE: usize = 64;

/// A voxel's free passes are multiplied into its pdf once they reach this many (fewer stay
/// pending; see [`CrmEngine::apply`]). Many passes at once can underflow every particle of a
/// confident pdf in f32; [`CrmEngine::log_pass_weights`] then redoes them in logarithms.
const LAZY_PASSES: usize = 48;

/// One brick of the CRM map: the voxels allocated in it, each with a pdf, its mean, and
/// free passes not yet multiplied in: the voxel's distribution is `pdf (1 - m)^pending`,
/// renormalised (see [`CrmEngine::apply`]).
#[derive(Clone, Debug)]
struct CrmBrick {
    /// Slot -> index into `means` (`u16::MAX`: not allocated). Boxed: a frame's bricks move
    /// out of the map and back, and moving 1 KiB each way was 6% of a laser log's build.
    local: Box<[u16; BRICK_VOXELS]>,
    /// The mean of `pdfs` (without the pending passes).
    means: Vec<f32>,
    /// `particles` probabilities per allocated voxel.
    pdfs: Vec<f32>,
    /// Free passes per allocated voxel not yet in its pdf (below [`LAZY_PASSES`]).
    pending: Vec<u8>,
}

impl CrmBrick {
    fn new() -> Self {
        CrmBrick { local: Box::new([u16::MAX; BRICK_VOXELS]), means: Vec::new(), pdfs: Vec::new(), pending: Vec::new() }
    }

    #[inline]
    fn index(&self, slot: usize) -> Option<usize> {
        let i = self.local[slot];
        (i != u16::MAX).then_some(i as usize)
    }

    /// Index of `slot`, allocating a uniform pdf (mean 0.5) if new.
    fn index_or_insert(&mut self, slot: usize, k: usize) -> usize {
        if let Some(i) = self.index(slot) {
            return i;
        }
        let i = self.means.len();
        // Grow by a quarter (at least 8 voxels), not by doubling: a brick's pdfs are most of a
        // CRM map, and doubling leaves a quarter of them spare on average (measured peaks: 447
        // instead of 528 MiB at 0.01 m in the `memory_estimate` test's room, 2.45 instead of
        // 2.56 GB for intel-lab's laser log at 0.05 m). Still geometric: copies stay linear.
        if i == self.means.capacity() {
            let more = (i / 4).max(8);
            self.means.reserve_exact(more);
            self.pending.reserve_exact(more);
            self.pdfs.reserve_exact(more * k);
        }
        self.local[slot] = i as u16;
        self.means.push(0.5);
        self.pending.push(0);
        self.pdfs.extend(std::iter::repeat_n(1.0 / k as f32, k));
        i
    }
}

/// What one frame does to one brick: per slot the number of rays that passed through it
/// without any chance of having caused their reading (their factor is `1 - m`), and the
/// normalised factors `(alpha, beta)` of the rays whose cause model gave it some weight, in
/// ray order.
struct FrameBrick {
    passes: Box<[u32; BRICK_VOXELS]>,
    factors: Vec<(u16, f32, f32)>,
}

impl FrameBrick {
    fn new() -> Self {
        FrameBrick { passes: Box::new([0; BRICK_VOXELS]), factors: Vec::new() }
    }
}

/// A frame's updates, per brick, gathered by one block of rows (and merged in row order).
#[derive(Default)]
struct FrameUpdates {
    bricks: BrickList<FrameBrick>,
}

impl FrameUpdates {
    #[inline]
    fn brick(&mut self, key: BrickKey) -> usize {
        self.bricks.index_or_insert_with(key, FrameBrick::new)
    }

    /// Appends `other` (the rays after this block's), keeping ray order per brick.
    fn merge(mut self, other: FrameUpdates) -> FrameUpdates {
        for (key, b) in other.bricks.into_items() {
            let i = self.brick(key);
            let mine = self.bricks.value_mut(i);
            for (a, n) in mine.passes.iter_mut().zip(b.passes.iter()) {
                *a += n;
            }
            mine.factors.extend(b.factors);
        }
        self
    }
}

/// Beta `(alpha, beta)` with a voxel's mean and variance (moment matching); a variance at or
/// above the Bernoulli bound `m (1 - m)` is clipped just below it.
fn beta_of(v: MapVoxel) -> (f64, f64) {
    let m = (v.occupancy as f64).clamp(1e-6, 1.0 - 1e-6);
    let var = (v.variance as f64).clamp(1e-12, m * (1.0 - m) * 0.999);
    let n = m * (1.0 - m) / var - 1.0;
    (m * n, (1.0 - m) * n)
}

/// Merging CRM maps ([`super::merge`]): each voxel moment-matched to a Beta, the two
/// multiplied over the uniform prior.
pub(super) fn merge_rule() -> impl Fn(MapVoxel, MapVoxel) -> MapVoxel {
    |a, b| {
        let (aa, ba) = beta_of(a);
        let (ab, bb) = beta_of(b);
        // Parameters below a small floor would be a pdf CRM's particles cannot hold.
        let (al, be) = ((aa + ab - 1.0).max(0.05), (ba + bb - 1.0).max(0.05));
        let n = al + be;
        MapVoxel { occupancy: (al / n) as f32, variance: (al * be / (n * n * (n + 1.0))) as f32 }
    }
}

/// Confidence-rich mapping.
///
/// ```
/// use mrfmap::inference::{CrmEngine, CrmParams, Engine};
/// let e = CrmEngine::new(0.05, Default::default(), CrmParams::default()).unwrap();
/// assert!(e.map().has_variance);
/// ```
pub struct CrmEngine {
    bricks: FxHashMap<BrickKey, CrmBrick>,
    resolution: f64,
    /// Particle positions `m_k = k / (K - 1)`.
    grid: Vec<f32>,
    /// `(1 - m_k)^n` for `n < POWER_TABLE`, row-major by `n`.
    powers: Vec<f32>,
    /// `ln(1 - m_k)`, for passes that underflow f32 (see [`CrmEngine::log_pass_weights`]).
    log_free: Vec<f64>,
    limits: RayLimits,
    default_noise: Arc<NoiseModel>,
}

impl CrmEngine {
    /// An empty map; needs 2 to 65535 particles and a valid resolution.
    pub fn new(resolution: f64, limits: RayLimits, params: CrmParams) -> Result<Self> {
        let k = params.particles;
        if !(2..=65_535).contains(&k) {
            return Err(Error::Invalid(format!("CRM needs 2 to 65535 particles, got {k}")));
        }
        check_resolution(resolution)?;
        limits.validate()?;
        let grid: Vec<f32> = (0..k).map(|j| (j as f64 / (k - 1) as f64) as f32).collect();
        let powers =
            (0..POWER_TABLE).flat_map(|n| grid.iter().map(move |m| (1.0 - *m as f64).powi(n as i32) as f32)).collect();
        let log_free = grid.iter().map(|m| (1.0 - *m as f64).ln()).collect();
        Ok(CrmEngine {
            bricks: FxHashMap::default(),
            resolution,
            grid,
            powers,
            log_free,
            limits,
            default_noise: Arc::new(default_noise_model()),
        })
    }

    /// Particles per voxel.
    pub fn particles(&self) -> usize {
        self.grid.len()
    }

    /// Number of allocated voxels.
    pub fn voxel_count(&self) -> usize {
        self.bricks.values().map(|b| b.means.len()).sum()
    }

    /// Mean and variance of a voxel's occupancy, `None` if never observed.
    pub fn mean_variance(&self, key: VoxelKey) -> Option<(f64, f64)> {
        let b = self.bricks.get(&key.brick())?;
        let i = b.index(key.slot())?;
        Some(self.moments(b, i))
    }

    /// Mean and variance of voxel `i` of brick `b`, its pending passes included.
    fn moments(&self, b: &CrmBrick, i: usize) -> (f64, f64) {
        let k = self.particles();
        let pdf = &b.pdfs[i * k..(i + 1) * k];
        let n = b.pending[i] as usize;
        // Sums of p, m p and m^2 p.
        let add = |acc: &mut [f64; 3], m: f32, p: f64| {
            let m = m as f64;
            *acc = [acc[0] + p, acc[1] + m * p, acc[2] + m * m * p];
        };
        let mut acc = [0.0; 3];
        // One loop in the common case (a map's export reads every voxel this way).
        let power = &self.powers[n * k..(n + 1) * k];
        pdf.iter().zip(power).zip(&self.grid).for_each(|((p, w), m)| add(&mut acc, *m, (*p * *w) as f64));
        if n > 0 && !(acc[0] > MIN_SUM as f64 && acc[0].is_finite()) {
            acc = [0.0; 3];
            let mut each = |j: usize, p: f64| add(&mut acc, self.grid[j], p);
            // (Passes that leave nothing, only possible for a pdf all at m = 1, are ignored.)
            if !self.log_pass_weights(pdf, n, &mut each) {
                pdf.iter().enumerate().for_each(|(j, p)| each(j, *p as f64));
            }
        }
        let (mean, second) = (acc[1] / acc[0], acc[2] / acc[0]);
        (mean, (second - mean * mean).max(0.0))
    }

    /// The mean of voxel `i` of brick `b`, its pending passes included.
    fn mean(&self, b: &CrmBrick, i: usize) -> f32 {
        let n = b.pending[i] as usize;
        if n == 0 {
            return b.means[i];
        }
        // The common case inline (this is read for every voxel of a ray's window).
        let k = self.particles();
        let pdf = &b.pdfs[i * k..(i + 1) * k];
        let (sum, weighted) = product_sums(pdf, &self.powers[n * k..(n + 1) * k], &self.grid);
        if sum > MIN_SUM && sum.is_finite() {
            return weighted / sum;
        }
        let (mut sum, mut weighted) = (0.0, 0.0);
        let usable = self.log_pass_weights(pdf, n, |j, p| {
            sum += p;
            weighted += self.grid[j] as f64 * p;
        });
        if usable { (weighted / sum) as f32 } else { b.means[i] }
    }

    /// Calls `each(j, w_j)` with weights proportional to `pdf_j (1 - m_j)^n`, `n > 0`, computed
    /// in logarithms relative to the largest: for passes whose product with the power table
    /// underflows f32 (a confident pdf near m = 1 does after a few dozen passes; the callers
    /// try the table first). False, with no calls, if nothing is left (every particle with
    /// mass is at m = 1).
    fn log_pass_weights(&self, pdf: &[f32], n: usize, mut each: impl FnMut(usize, f64)) -> bool {
        // (At m = 1, `ln(1 - m)` is -inf and so is the weight, as `n > 0`.)
        debug_assert!(n > 0);
        let log_weight = |j: usize| {
            if pdf[j] > 0.0 { (pdf[j] as f64).ln() + n as f64 * self.log_free[j] } else { f64::NEG_INFINITY }
        };
        let top = (0..pdf.len()).map(log_weight).fold(f64::NEG_INFINITY, f64::max);
        if !top.is_finite() {
            return false;
        }
        (0..pdf.len()).for_each(|j| each(j, (log_weight(j) - top).exp()));
        true
    }

    /// Multiplies `n` free passes, `(1 - m)^n`, into `p` and renormalises it; returns its mean,
    /// or `None` if nothing would be left (`p` is then to be restored by the caller).
    fn multiply_passes(&self, p: &mut [f32], n: usize) -> Option<f32> {
        let k = self.particles();
        let (mut left, mut mean) = (n, None);
        while left > 0 {
            let step = left.min(POWER_TABLE - 1);
            let power = &self.powers[step * k..(step + 1) * k];
            // The sums of the products first, so that `p` is still there if they underflow.
            let (sum, weighted) = product_sums(p, power, &self.grid);
            if !(sum > MIN_SUM && sum.is_finite()) {
                let before = p.to_vec();
                if !self.log_pass_weights(&before, left, |j, w| p[j] = w as f32) {
                    return None;
                }
                return Some(scale_to_one(p, sums(p, &self.grid)));
            }
            let inv = 1.0 / sum;
            p.iter_mut().zip(power).for_each(|(x, w)| *x = *x * *w * inv);
            mean = Some(weighted * inv);
            left -= step;
        }
        mean
    }

    /// The cause-model factors of every ray of `rays`, from the map as it was before.
    fn gather(&self, rays: &Rays, noise: &NoiseModel) -> FrameUpdates {
        // Blocks fixed by the input (so results do not depend on the thread count): 32 rows
        // of an image, large enough that merging their per-brick counts stays cheap; each row
        // of a scan's few (64 beams), so that a scan's rays are not all on one core.
        let block_rows = (rays.rows() / 8).clamp(1, 32);
        let r = self.resolution;
        // Crossings outside the bounds are left out (`RayLimits::bounds_keys`: rounding at the
        // box's faces).
        let bounds = self.limits.bounds_keys(r);
        let outside = |key: VoxelKey| bounds.is_some_and(|b| !key_in_box(key.0, b));
        let blocks: Vec<FrameUpdates> = (0..rays.rows().div_ceil(block_rows))
            .into_par_iter()
            .map(|b| {
                let mut up = FrameUpdates::default();
                let (mut window, mut means, mut nus, mut factors) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
                let mut cached: Option<(BrickKey, Option<&CrmBrick>)> = None;
                // The brick of `up` written last: consecutive voxels of a ray share bricks.
                let mut current: Option<(BrickKey, usize)> = None;
                let mut slot_of = |up: &mut FrameUpdates, key: VoxelKey| {
                    let brick = key.brick();
                    match current {
                        Some((k, i)) if k == brick => i,
                        _ => {
                            let i = up.brick(brick);
                            current = Some((brick, i));
                            i
                        }
                    }
                };
                for v in b * block_rows..((b + 1) * block_rows).min(rays.rows()) {
                    for ray in rays.row(v) {
                        let Some(seg) = self.limits.forward_model_segment(&ray, noise) else { continue };
                        let z = ray.range * ray.cz;
                        let mut likelihood = noise.along_ray(ray.u, ray.v, z);
                        window.clear();
                        means.clear();
                        nus.clear();
                        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, r, |c| {
                            if outside(c.key) {
                                return ControlFlow::Continue(());
                            }
                            // A beam with no return could not have been stopped by any voxel.
                            let nu =
                                if ray.returned { likelihood.over(c.s_in * ray.cz, c.s_out * ray.cz) } else { 0.0 };
                            if nu == 0.0 && window.is_empty() {
                                // No cause weight here or before: the factor is exactly 1 - m,
                                // whatever this voxel's mean, so it is only counted.
                                let i = slot_of(&mut up, c.key);
                                up.bricks.value_mut(i).passes[c.key.slot()] += 1;
                                return ControlFlow::Continue(());
                            }
                            let brick = c.key.brick();
                            let b = match cached {
                                Some((k, b)) if k == brick => b,
                                _ => {
                                    let b = self.bricks.get(&brick);
                                    cached = Some((brick, b));
                                    b
                                }
                            };
                            let mean = b.and_then(|b| Some(self.mean(b, b.index(c.key.slot())?))).unwrap_or(0.5);
                            window.push(c.key);
                            means.push(mean as f64);
                            nus.push(nu);
                            ControlFlow::Continue(())
                        });
                        let beyond = seg.beyond(&ray, noise, &mut likelihood, r);
                        if window.is_empty() && beyond == 0.0 {
                            // The cause model carries no information (a surface beyond every
                            // voxel's likelihood, which the segment's end rules out in practice):
                            // take back the passes counted on the way.
                            for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, r, |c| {
                                if outside(c.key) {
                                    return ControlFlow::Continue(());
                                }
                                let i = slot_of(&mut up, c.key);
                                up.bricks.value_mut(i).passes[c.key.slot()] -= 1;
                                ControlFlow::Continue(())
                            });
                            continue;
                        }
                        crm_ray_factors(&means, &nus, beyond, &mut factors);
                        for (key, &(alpha, beta)) in window.iter().zip(&factors) {
                            // Scaled so the factor's maximum over [0, 1] is 1.
                            let top = beta.max(alpha + beta);
                            if !(top > 0.0 && top.is_finite()) {
                                continue;
                            }
                            let (a, b) = (alpha / top, beta / top);
                            if a.abs() <= FACTOR_EPS {
                                continue; // flat: the voxel lies behind the cause, no change
                            }
                            let i = slot_of(&mut up, *key);
                            if (a + b).abs() <= FACTOR_EPS {
                                up.bricks.value_mut(i).passes[key.slot()] += 1; // 1 - m to within FACTOR_EPS
                            } else {
                                up.bricks.value_mut(i).factors.push((key.slot() as u16, a as f32, b as f32));
                            }
                        }
                    }
                }
                up
            })
            .collect();
        blocks.into_iter().reduce(FrameUpdates::merge).unwrap_or_default()
    }

    /// Multiplies a frame's factors into the pdfs, brick by brick in parallel.
    fn apply(&mut self, updates: FrameUpdates) {
        let k = self.particles();
        // The frame's bricks leave the map for the update and come back after it: finding them
        // by walking the whole map per frame cost a quarter of a laser log's build once the
        // map held 100k bricks.
        let mut work: Vec<(BrickKey, CrmBrick, FrameBrick)> = updates
            .bricks
            .into_items()
            .into_iter()
            .map(|(key, fb)| (key, self.bricks.remove(&key).unwrap_or_else(CrmBrick::new), fb))
            .collect();
        let engine = &*self;
        let grid = &engine.grid;
        // The pdf of a voxel new to the map; a scratch pdf per thread.
        let uniform = vec![1.0 / k as f32; k];
        work.par_iter_mut().for_each_init(
            || vec![0f32; k],
            |p, (_, brick, fb)| {
                // Factors grouped by slot, ray order kept within a slot.
                fb.factors.sort_by_key(|f| f.0);
                let mut touched = [0u64; 8];
                for (slot, n) in fb.passes.iter().enumerate() {
                    if *n > 0 {
                        mask_set(&mut touched, slot);
                    }
                }
                for f in &fb.factors {
                    mask_set(&mut touched, f.0 as usize);
                }
                let mut next_factor = 0;
                for slot in mask_slots(&touched) {
                    let existing = brick.index(slot);
                    let has_factors = fb.factors.get(next_factor).is_some_and(|f| f.0 as usize == slot);
                    let mut n = fb.passes[slot] as usize;
                    if let Some(i) = existing {
                        // Free passes only (most voxels a frame touches) are counted, not
                        // multiplied in: the pdf is read and written once per few dozen passes,
                        // or when a factor or a ray's cause model needs it. The factors commute,
                        // so this changes rounding only.
                        let total = n + brick.pending[i] as usize;
                        if !has_factors && total < LAZY_PASSES {
                            brick.pending[i] = total as u8;
                            continue;
                        }
                        n = total;
                        brick.pending[i] = 0;
                    }
                    // The pdf before this frame, read in place (copying it was a fifth of a laser
                    // log's build): the fallback if every particle underflows.
                    let last: &[f32] = match existing {
                        Some(i) => &brick.pdfs[i * k..(i + 1) * k],
                        None => &uniform,
                    };
                    p.copy_from_slice(last);
                    let mut mean = None;
                    if n > 0 {
                        mean = engine.multiply_passes(p, n);
                        if mean.is_none() {
                            p.copy_from_slice(last);
                        }
                    }
                    // Factors are scaled to a maximum of 1, so a few of them in a row cannot
                    // underflow: renormalise every few.
                    let mut pending = 0;
                    while next_factor < fb.factors.len() && fb.factors[next_factor].0 as usize == slot {
                        let (_, alpha, beta) = fb.factors[next_factor];
                        for (pj, m) in p.iter_mut().zip(grid) {
                            *pj *= alpha * m + beta;
                        }
                        mean = None;
                        pending += 1;
                        if pending == RENORMALISE_EVERY {
                            normalise(p, last, grid);
                            pending = 0;
                        }
                        next_factor += 1;
                    }
                    let mean = mean.unwrap_or_else(|| normalise(p, last, grid));
                    // A voxel seen for the first time whose evidence hardly moves it (voxels deep
                    // behind a surface that noisy long readings reach) stays unknown instead of
                    // entering the map at its prior.
                    if existing.is_none() && (mean - 0.5).abs() < NEW_VOXEL_MIN_CHANGE {
                        continue;
                    }
                    let i = existing.unwrap_or_else(|| brick.index_or_insert(slot, k));
                    brick.pdfs[i * k..(i + 1) * k].copy_from_slice(p);
                    brick.means[i] = mean;
                }
            },
        );
        for (key, brick, _) in work {
            self.bricks.insert(key, brick);
        }
    }
}

/// A new voxel enters the map only if its first frame moves its mean this far from 0.5.
const NEW_VOXEL_MIN_CHANGE: f32 = 1e-3;

/// A pdf's sum below this counts as underflowed (f32 keeps normal numbers down to 1e-38, so
/// particles lost to underflow are below 1e-8 of such a sum together).
const MIN_SUM: f32 = 1e-30;

/// Factors multiplied in between renormalisations.
const RENORMALISE_EVERY: usize = 8;

/// Sums of `p` and of `p * grid`, in eight lanes (element `j` to lane `j mod 8`) whose order,
/// and so the result, is fixed. (The compiler leaves this loop scalar; writing it so that it
/// vectorises made no measurable difference: the pdfs' memory traffic dominates.)
#[inline]
fn sums(p: &[f32], grid: &[f32]) -> (f32, f32) {
    sums_of(p, p, grid, |a, _| a)
}

/// [`sums`] of `p * w` (each product rounded to f32 first, as if `p` had been scaled).
#[inline]
fn product_sums(p: &[f32], w: &[f32], grid: &[f32]) -> (f32, f32) {
    sums_of(p, w, grid, |a, b| a * b)
}

/// Sums of `value(p_j, w_j)` and of `value(p_j, w_j) * grid_j`.
#[inline(always)]
fn sums_of(p: &[f32], w: &[f32], grid: &[f32], value: impl Fn(f32, f32) -> f32) -> (f32, f32) {
    let (mut s, mut m) = ([0f32; 8], [0f32; 8]);
    let (pc, wc, gc) = (p.chunks_exact(8), w.chunks_exact(8), grid.chunks_exact(8));
    let (pr, wr, gr) = (pc.remainder(), wc.remainder(), gc.remainder());
    for ((a, b), g) in pc.zip(wc).zip(gc) {
        for j in 0..8 {
            let x = value(a[j], b[j]);
            s[j] += x;
            m[j] += x * g[j];
        }
    }
    for (j, ((a, b), g)) in pr.iter().zip(wr).zip(gr).enumerate() {
        let x = value(*a, *b);
        s[j] += x;
        m[j] += x * g;
    }
    (s.iter().sum(), m.iter().sum())
}

/// Renormalises `p` to sum 1 and returns its mean; if every particle underflowed (or the
/// sum is not finite) it falls back to `last`, the pdf before this frame, so a voxel is never
/// lost.
#[inline]
fn normalise(p: &mut [f32], last: &[f32], grid: &[f32]) -> f32 {
    let (sum, weighted) = sums(p, grid);
    if !(sum > MIN_SUM && sum.is_finite()) {
        p.copy_from_slice(last);
        return scale_to_one(p, sums(p, grid));
    }
    scale_to_one(p, (sum, weighted))
}

/// Divides `p` by `sum` and returns the mean, given `(sum, weighted)` from [`sums`].
#[inline]
fn scale_to_one(p: &mut [f32], (sum, weighted): (f32, f32)) -> f32 {
    let inv = 1.0 / sum;
    p.iter_mut().for_each(|x| *x *= inv);
    weighted * inv
}

impl Engine for CrmEngine {
    fn kind(&self) -> EngineKind {
        EngineKind::Crm
    }

    fn resolution(&self) -> f64 {
        self.resolution
    }

    fn integrate(&mut self, frame: &Frame) -> Result<()> {
        let noise = frame.noise.clone().unwrap_or_else(|| self.default_noise.clone());
        let updates = self.gather(&Rays::of_frame(frame), &noise);
        self.apply(updates);
        Ok(())
    }

    fn integrate_scan(&mut self, scan: &RangeScan) -> Result<()> {
        let noise = scan.noise.clone().unwrap_or_else(|| self.default_noise.clone());
        let updates = self.gather(&Rays::of_scan(scan), &noise);
        self.apply(updates);
        Ok(())
    }

    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.mean_variance(key).map(map_voxel)
    }

    fn has_variance(&self) -> bool {
        true
    }

    fn map(&self) -> Map {
        let mut map = Map::new(self.kind(), self.resolution).expect("valid resolution");
        map.has_variance = true;
        let k = self.particles();
        for (bk, b) in &self.bricks {
            for slot in 0..BRICK_VOXELS {
                if let Some(i) = b.index(slot) {
                    map.voxels.insert(bk.voxel(slot), map_voxel(self.moments(b, i)));
                }
            }
        }
        map.params.insert("particles".into(), k.to_string());
        map
    }
}

/// A map voxel of a voxel's occupancy mean and variance.
fn map_voxel((mean, variance): (f64, f64)) -> MapVoxel {
    MapVoxel { occupancy: mean as f32, variance: variance as f32 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// CRM (18) evaluated directly with the case ratios of CRM (19): for voxel i and a
    /// particle value m, sum over causes c of q(c) * p(c | m_i = m) / p(c), with every
    /// product written out (quadratic in the ray length).
    fn direct(means: &[f64], nu: &[f64], nu_beyond: f64, i: usize, m: f64) -> f64 {
        let n = means.len();
        let prior = |c: usize, mi: Option<f64>| -> f64 {
            // p(c | b) with voxel i's occupancy optionally fixed to mi; c == n is the final cause.
            let occ = |l: usize| if Some(l) == mi.map(|_| i) { mi.unwrap() } else { means[l] };
            let mut p = if c < n { occ(c) } else { 1.0 };
            for l in 0..c.min(n) {
                p *= 1.0 - occ(l);
            }
            p
        };
        let eta: f64 = (0..=n).map(|c| if c < n { nu[c] } else { nu_beyond } * prior(c, None)).sum();
        (0..=n)
            .map(|c| {
                let q = if c < n { nu[c] } else { nu_beyond } * prior(c, None) / eta;
                q * prior(c, Some(m)) / prior(c, None)
            })
            .sum()
    }

    #[test]
    fn linear_update_equals_direct_evaluation() {
        let mut rng = Rng::new(5);
        let mut f = Vec::new();
        for trial in 0..300 {
            let n = 1 + trial % 10;
            let means: Vec<f64> = (0..n).map(|_| rng.range(0.02, 0.98)).collect();
            let nu: Vec<f64> = (0..n).map(|_| 10f64.powf(rng.range(-3.0, 1.0))).collect();
            let beyond = if trial % 4 == 0 { 0.0 } else { 10f64.powf(rng.range(-3.0, 0.0)) };
            crm_ray_factors(&means, &nu, beyond, &mut f);
            for (i, (alpha, beta)) in f.iter().enumerate() {
                // Both are the same function of m up to a positive factor: compare normalised
                // over a set of particles.
                let ms = [0.0, 0.1, 0.37, 0.5, 0.9, 1.0];
                let fast: Vec<f64> = ms.iter().map(|m| alpha * m + beta).collect();
                let slow: Vec<f64> = ms.iter().map(|m| direct(&means, &nu, beyond, i, *m)).collect();
                let (sf, ss): (f64, f64) = (fast.iter().sum(), slow.iter().sum());
                for (a, b) in fast.iter().zip(&slow) {
                    assert!((a / sf - b / ss).abs() < 1e-9, "trial {trial} voxel {i}: {fast:?} vs {slow:?}");
                }
            }
        }
    }

    fn wall_frames(n: usize, shift: f32) -> Vec<crate::frames::Frame> {
        use crate::frames::{Camera, DepthImage, Frame, look_at};
        let camera = Camera::new(20.0, 20.0, 7.5, 5.5, 16, 12, 5000.0).unwrap();
        (0..n)
            .map(|i| {
                let mut depth = DepthImage::new(16, 12);
                for v in 0..12 {
                    for u in 0..16 {
                        depth.set(u, v, 1.02 + shift * (i % 2) as f32);
                    }
                }
                let pose = look_at([0.0, 0.013, 0.017].into(), [1.0, 0.013, 0.017].into()).unwrap();
                Frame { index: i, timestamp: i as f64, depth, pose, camera, noise: None }
            })
            .collect()
    }

    /// With bounds whose faces lie on voxel faces, crossed by the rays going in and coming
    /// out, no voxel outside the box is touched (the wall lies beyond it).
    #[test]
    fn nothing_outside_the_bounds_is_touched() {
        let bounds = crate::map::Aabb { min: [0.5, -0.2, -0.15], max: [0.9, 0.2, 0.2] };
        let limits = RayLimits { max_range: None, bounds: Some(bounds) };
        let mut e = CrmEngine::new(0.05, limits, CrmParams::default()).unwrap();
        for f in wall_frames(4, 0.0) {
            e.integrate(&f).unwrap();
        }
        let (lo, hi) = crate::map::box_keys(&bounds, 0.05);
        let map = e.map();
        let outside = map.voxels.iter().filter(|(k, _)| !key_in_box(k.0, (lo, hi))).count();
        assert_eq!(outside, 0, "{outside} of {} voxels outside the bounds", map.voxels.len());
        assert!(map.voxels.len() > 100, "{} voxels", map.voxels.len());
    }

    #[test]
    fn many_passes_at_once_match_f64_where_f32_underflows() {
        let e = CrmEngine::new(0.05, Default::default(), CrmParams::default()).unwrap();
        let k = e.particles();
        // Confidently occupied: mass near m = 1, and none (in f32) below m = 0.6.
        let raw: Vec<f64> = e.grid.iter().map(|m| (*m as f64).powi(180)).collect();
        let total: f64 = raw.iter().sum();
        let pdf: Vec<f32> = raw.iter().map(|x| (x / total) as f32).collect();
        for n in [1, 8, 30, 47, 63, 64, 200] {
            let exact: Vec<f64> =
                pdf.iter().zip(&e.grid).map(|(p, m)| *p as f64 * (1.0 - *m as f64).powi(n as i32)).collect();
            let sum: f64 = exact.iter().sum();
            let exact_mean = exact.iter().zip(&e.grid).map(|(x, m)| x * *m as f64).sum::<f64>() / sum;
            let underflows = n < POWER_TABLE && product_sums(&pdf, &e.powers[n * k..(n + 1) * k], &e.grid).0 <= MIN_SUM;
            assert_eq!(underflows, (30..POWER_TABLE).contains(&n), "n = {n}: the test should reach both paths");
            // Multiplied in...
            let mut p = pdf.clone();
            let mean = e.multiply_passes(&mut p, n).unwrap() as f64;
            assert!((mean - exact_mean).abs() < 1e-5, "n = {n}: {mean} vs {exact_mean}");
            let psum: f64 = p.iter().map(|x| *x as f64).sum();
            assert!((psum - 1.0).abs() < 1e-5 && p.iter().all(|x| x.is_finite() && *x >= 0.0), "n = {n}");
            // ... or pending (below the lazy cap), read through.
            if n < LAZY_PASSES {
                let mut b = CrmBrick::new();
                b.index_or_insert(0, k);
                b.pdfs.copy_from_slice(&pdf);
                b.pending[0] = n as u8;
                assert!((e.mean(&b, 0) as f64 - exact_mean).abs() < 1e-5, "n = {n}");
                assert!((e.moments(&b, 0).0 - exact_mean).abs() < 1e-5, "n = {n}");
            }
        }
        // A pdf all at m = 1 has nothing left after a pass.
        let mut p = vec![0f32; k];
        p[k - 1] = 1.0;
        assert_eq!(e.multiply_passes(&mut p, 3), None);
    }

    #[test]
    fn pdfs_stay_normalised_and_finite_over_many_updates() {
        let mut e = CrmEngine::new(0.05, Default::default(), CrmParams::default()).unwrap();
        for f in wall_frames(300, 0.0) {
            e.integrate(&f).unwrap();
        }
        for b in e.bricks.values() {
            for (i, pdf) in b.pdfs.chunks(e.particles()).enumerate() {
                let sum: f64 = pdf.iter().map(|p| *p as f64).sum();
                assert!(pdf.iter().all(|p| *p >= 0.0 && p.is_finite()), "voxel {i}");
                assert!((sum - 1.0).abs() < 1e-3, "voxel {i}: sum {sum}");
                assert!(b.means[i].is_finite());
            }
        }
        // The wall voxel is confidently occupied, the space in front confidently free.
        let (m_wall, _) = e.mean_variance(VoxelKey([20, 0, 0])).unwrap();
        let (m_free, _) = e.mean_variance(VoxelKey([10, 0, 0])).unwrap();
        assert!(m_wall > 0.9 && m_free < 0.05, "wall {m_wall}, free {m_free}");
        // The wall moves back 0.5 m: the confident voxels where it was only get free passes
        // now (pending, then multiplied in). Their means fall, but not below the lowest
        // particle that kept any mass in f32 while 300 frames saw the wall (0.71 here): the
        // pdf's support does not grow back.
        for f in wall_frames(600, 0.5).iter().skip(1).step_by(2) {
            e.integrate(f).unwrap();
        }
        let (m_old, _) = e.mean_variance(VoxelKey([20, 0, 0])).unwrap();
        assert!(m_old < m_wall - 0.1, "old wall {m_old} (was {m_wall})");
        let new_wall = e.bricks.keys().flat_map(|b| (0..BRICK_VOXELS).map(move |s| b.voxel(s)));
        let new_wall = new_wall.filter(|k| k.0[0] == 30).filter_map(|k| e.mean_variance(k)).map(|m| m.0);
        assert!(new_wall.fold(0.0, f64::max) > 0.9);
        for b in e.bricks.values() {
            for pdf in b.pdfs.chunks(e.particles()) {
                let sum: f64 = pdf.iter().map(|p| *p as f64).sum();
                assert!(pdf.iter().all(|p| *p >= 0.0 && p.is_finite()) && (sum - 1.0).abs() < 1e-3);
            }
        }
    }

    /// The engine (free passes counted, factors folded per brick) against the plain
    /// definition: every ray's factors from `crm_ray_factors` over the whole ray, applied in
    /// f64 to a map of pdfs, one frame at a time from the previous frame's means.
    #[test]
    fn engine_equals_plain_per_ray_updates() {
        use crate::rays::Rays;
        use std::collections::HashMap;
        let k = 21;
        let mut engine = CrmEngine::new(0.05, Default::default(), CrmParams { particles: k }).unwrap();
        let noise = default_noise_model();
        let grid: Vec<f64> = (0..k).map(|j| j as f64 / (k - 1) as f64).collect();
        let mut plain: HashMap<VoxelKey, Vec<f64>> = HashMap::new();
        let mean = |p: &[f64]| p.iter().zip(&grid).map(|(a, m)| a * m).sum::<f64>();
        let mut frames = wall_frames(6, 0.07);
        // Oblique views too, so rays cross each other's windows.
        for (i, f) in frames.iter_mut().enumerate() {
            f.pose = crate::frames::look_at([0.0, 0.1 * i as f64, 0.05].into(), [1.0, 0.0, 0.0].into()).unwrap();
        }
        for f in &frames {
            engine.integrate(f).unwrap();
            let means: HashMap<VoxelKey, f64> = plain.iter().map(|(key, p)| (*key, mean(p))).collect();
            let rays = Rays::of_frame(f);
            let mut updates: Vec<(VoxelKey, f64, f64)> = Vec::new();
            for v in 0..rays.rows() {
                for ray in rays.row(v) {
                    let seg = RayLimits::default().forward_model_segment(&ray, &noise).unwrap();
                    let cs = crate::rays::crossings(ray.origin, ray.dir, seg.start, seg.end, 0.05);
                    let z = ray.range * ray.cz;
                    let m: Vec<f64> = cs.iter().map(|c| *means.get(&c.key).unwrap_or(&0.5)).collect();
                    let nu: Vec<f64> = cs
                        .iter()
                        .map(|c| noise.likelihood_over(ray.u, ray.v, c.s_in * ray.cz, c.s_out * ray.cz, z))
                        .collect();
                    let z_end = seg.end * ray.cz;
                    let beyond = noise.likelihood_over(ray.u, ray.v, z_end, z_end + 0.05 * ray.cz, z);
                    let mut f = Vec::new();
                    crm_ray_factors(&m, &nu, beyond, &mut f);
                    updates.extend(cs.iter().zip(&f).map(|(c, (a, b))| (c.key, *a, *b)));
                }
            }
            for (key, a, b) in updates {
                let p = plain.entry(key).or_insert_with(|| vec![1.0 / k as f64; k]);
                p.iter_mut().zip(&grid).for_each(|(pj, m)| *pj *= a * m + b);
                let sum: f64 = p.iter().sum();
                p.iter_mut().for_each(|pj| *pj /= sum);
            }
        }
        // Voxels the engine left out (first-frame evidence too weak) sit at the prior.
        assert!(engine.voxel_count() <= plain.len() && engine.voxel_count() > plain.len() / 2);
        // Free passes still pending (not in the pdfs) are part of what is compared below.
        let pending = engine.bricks.values().flat_map(|b| &b.pending).filter(|&&n| n > 0).count();
        assert!(pending > 100, "{pending} voxels with pending passes");
        let prior_var = (k as f64 + 1.0) / (12.0 * (k as f64 - 1.0));
        let mut worst = 0.0f64;
        for (key, p) in &plain {
            let pm = mean(p);
            let Some((m, var)) = engine.mean_variance(*key) else {
                let pvar = p.iter().zip(&grid).map(|(a, x)| a * (x - pm) * (x - pm)).sum::<f64>();
                assert!((pm - 0.5).abs() < 2e-3 && (pvar - prior_var).abs() < 1e-2, "left out {key:?}: {pm}, {pvar}");
                continue;
            };
            let pvar = p.iter().zip(&grid).map(|(a, x)| a * (x - pm) * (x - pm)).sum::<f64>();
            worst = worst.max((m - pm).abs()).max((var - pvar).abs());
        }
        assert!(worst < 1e-4, "largest difference in mean or variance: {worst}");
    }

    #[test]
    fn conflicting_evidence_keeps_variance_high() {
        // Consistent: the wall at 1.02 m every time. Conflicting: every other reading 10 cm
        // further, as two misaligned scans of a thin object would say.
        let run = |shift| {
            let mut e = CrmEngine::new(0.05, Default::default(), CrmParams::default()).unwrap();
            for f in wall_frames(40, shift) {
                e.integrate(&f).unwrap();
            }
            e.mean_variance(VoxelKey([20, 0, 0])).unwrap().1
        };
        let (consistent, conflicting) = (run(0.0), run(0.1));
        assert!(consistent < 0.01 && conflicting > 3.0 * consistent, "{consistent} vs {conflicting}");
    }

    #[test]
    fn long_confident_rays_give_finite_non_negative_factors() {
        let mut f = Vec::new();
        for means in [vec![1.0 - 1e-12; 2000], vec![1e-12; 2000]] {
            let nu = vec![1e-3; 2000];
            crm_ray_factors(&means, &nu, 1e-6, &mut f);
            for (a, b) in &f {
                assert!(a.is_finite() && b.is_finite() && *b >= 0.0 && a + b >= -1e-12);
            }
        }
    }
}
