//! Factor-to-voxel messages of one ray factor (MRFMap eqs. 11-14; docs/ALGORITHMS.md 5.3), in
//! time linear in the ray's length.
//!
//! A ray crosses voxels `1..N` in order. Voxel `j` sends the factor `mu_j = mu(o_j = 1)`;
//! `nu_j` is the likelihood of the measurement if the ray's first occupied voxel is `j`;
//! `nu_beyond` is its likelihood if the surface lies beyond the last voxel (the ray's
//! truncation point). With visibility `V_i = prod_{k<i} (1 - mu_k)`,
//! `A_i = sum_{j<i} mu_j nu_j V_j` and the suffix
//! `T_i = sum_{j>i} mu_j nu_j prod_{i<k<j} (1 - mu_k) + nu_beyond prod_{k>i} (1 - mu_k)`
//! the messages are `m1_i = A_i + nu_i V_i` and `m0_i = A_i + V_i T_i`; the voxel receives
//! `m1_i / (m1_i + m0_i)`.
//!
//! **Numerics (rescaled form).** `V_i` underflows on long rays with confident messages
//! (0.01^1000), so everything is divided by `V_i`: with `a_i = A_i / V_i`,
//! `m1_i / V_i = a_i + nu_i` and `m0_i / V_i = a_i + T_i`, where `a_1 = 0`,
//! `a_{i+1} = (a_i + mu_i nu_i) / (1 - mu_i)` grows (never underflows) and `T` is computed
//! backwards as `T_i = mu_{i+1} nu_{i+1} + (1 - mu_{i+1}) T_{i+1}`, a convex combination that
//! stays within `[0, max nu]` (the division-free suffix). Incoming messages are clamped to
//! `[MU_EPS, 1 - MU_EPS]` so `1 - mu` never vanishes, and `a` is capped at `A_CAP`: beyond it
//! every later message is 1/2 to double precision anyway (the ray is occluded).
//!
//! **The engine's form.** The trace holds beliefs as log-odds, so [`ray_log_messages`]
//! takes the incoming messages as odds `e = mu / (1 - mu)` and returns log-odds: the prefix
//! becomes `a_{i+1} = a_i (1 + e_i) + e_i nu_i`, with no division on either recursion's
//! chain, and the logarithms are one vectorised pass. [`ray_messages`] is the probability
//! form on top of it (the brute-force tests below check both).

use crate::inference::sigmoid;
use crate::vecmath::{VECTOR_LANES, ln_clamped_in_place};

/// Incoming messages are kept in `[MU_EPS, 1 - MU_EPS]`.
pub const MU_EPS: f64 = 1e-9;

/// Cap on the rescaled prefix: far above any likelihood, far below `f64::MAX`.
const A_CAP: f64 = 1e250;

/// Outgoing messages `mu(o_i = 1)` (normalised) for every voxel of one ray.
///
/// `mu` and `nu` have one entry per voxel in ray order; `out` receives the messages
/// (cleared first). A ray whose factor carries no information (all likelihoods zero)
/// sends 1/2. The probability form of [`ray_log_messages`], which the engine uses.
///
/// ```
/// use mrfmap::inference::ray_messages;
/// // Three voxels, a confident surface likelihood on the second.
/// let mut out = Vec::new();
/// ray_messages(&[0.1, 0.1, 0.1], &[0.0, 10.0, 0.0], 0.0, &mut out);
/// assert!(out[0] < 0.5 && out[1] > 0.9);
/// ```
pub fn ray_messages(mu: &[f64], nu: &[f64], nu_beyond: f64, out: &mut Vec<f64>) {
    let odds: Vec<f64> = mu
        .iter()
        .map(|m| {
            let m = m.clamp(MU_EPS, 1.0 - MU_EPS);
            m / (1.0 - m)
        })
        .collect();
    ray_log_messages(&odds, nu, nu_beyond, 700.0, out);
    for m in out.iter_mut() {
        *m = sigmoid(*m);
    }
}

/// Largest incoming odds `mu / (1 - mu)` that [`ray_log_messages`] expects: `mu` within
/// `[MU_EPS, 1 - MU_EPS]`, so its log-odds within `+-MAX_LOG_ODDS`.
pub const MAX_LOG_ODDS: f64 = 20.723_265_836_146_06; // ln((1 - MU_EPS) / MU_EPS)

/// Outgoing messages of one ray factor as log-odds `ln(m1_i / m0_i)` clamped to
/// `[-bound, bound]` (`bound` below 700), from the incoming messages as odds
/// `mu_i / (1 - mu_i)` (each within `exp(+-MAX_LOG_ODDS)`).
///
/// The same recursions as [`ray_messages`] without a division on either chain: with odds
/// `e`, `mu = e / (1 + e)` and `1 / (1 - mu) = 1 + e`, so the prefix is
/// `a_{i+1} = a_i (1 + e_i) + e_i nu_i` and the suffix `T_i = mu nu + (1 - mu) T` takes
/// `1 / (1 + e)` computed off the chain. A message is `+-bound` where one side is exactly
/// zero, and 0 where both are (the ray says nothing). The logarithms are taken in one
/// vectorised pass at the end.
#[inline(always)] // (so that the AVX2 copy of a tile trace has it in four lanes)
pub fn ray_log_messages(odds: &[f64], nu: &[f64], nu_beyond: f64, bound: f64, out: &mut Vec<f64>) {
    // (The pair's passes with a second ray of no voxels, which costs nothing.)
    let none = RayFactor { odds: &[], nu: &[], nu_beyond: 0.0, out: &mut Vec::new() };
    ray_log_messages_pair(RayFactor { odds, nu, nu_beyond, out }, none, bound);
}

/// One ray's factor for [`ray_log_messages_pair`]: [`ray_log_messages`]'s arguments.
pub(crate) struct RayFactor<'a> {
    pub odds: &'a [f64],
    pub nu: &'a [f64],
    pub nu_beyond: f64,
    pub out: &'a mut Vec<f64>,
}

/// [`ray_log_messages`] of two rays, each's messages bit for bit what it alone gives. Each
/// recursion is a chain of dependent multiplies and adds, one link per voxel, that the
/// processor cannot overlap with itself; two rays' chains side by side it overlaps.
#[inline(always)] // (as `ray_log_messages`)
pub(crate) fn ray_log_messages_pair(a: RayFactor, b: RayFactor, bound: f64) {
    let m = a.odds.len().min(b.odds.len());
    for f in [&a, &b] {
        debug_assert_eq!(f.odds.len(), f.nu.len());
    }
    let (a_out, b_out) = (a.out, b.out);
    // (The logarithms at the end run over whole vectors, [`VECTOR_LANES`]: the padding is
    // cut off after.)
    for (f, out) in [(a.odds, &mut *a_out), (b.odds, &mut *b_out)] {
        out.clear();
        out.resize(f.len().next_multiple_of(VECTOR_LANES), 0.0);
    }
    // Backward (`T_i` stored in `out` for the forward pass), from each ray's end: side by side
    // over the last `m` voxels of each, then the rest of the longer alone.
    let (mut ta, mut tb) = (a.nu_beyond, b.nu_beyond);
    let mut ia = a.odds.iter().zip(a.nu).zip(a_out.iter_mut()).rev();
    let mut ib = b.odds.iter().zip(b.nu).zip(b_out.iter_mut()).rev();
    for (va, vb) in ia.by_ref().take(m).zip(ib.by_ref().take(m)) {
        ta = suffix_step(va, ta);
        tb = suffix_step(vb, tb);
    }
    ia.for_each(|v| ta = suffix_step(v, ta));
    ib.for_each(|v| tb = suffix_step(v, tb));
    // Forward with the rescaled prefix a_i = A_i / V_i, from each ray's start.
    let (mut pa, mut pb) = (0.0f64, 0.0f64);
    let mut ia = a.odds.iter().zip(a.nu).zip(a_out.iter_mut());
    let mut ib = b.odds.iter().zip(b.nu).zip(b_out.iter_mut());
    for (va, vb) in ia.by_ref().take(m).zip(ib.by_ref().take(m)) {
        pa = prefix_step(va, pa);
        pb = prefix_step(vb, pb);
    }
    ia.for_each(|v| pa = prefix_step(v, pa));
    ib.for_each(|v| pb = prefix_step(v, pb));
    ln_clamped_in_place(a_out, bound);
    ln_clamped_in_place(b_out, bound);
    a_out.truncate(a.odds.len());
    b_out.truncate(b.odds.len());
}

/// One voxel of the backward pass: stores `T_i` (`t`) in `out` and returns `T_{i-1}`.
#[inline(always)]
fn suffix_step(((&odds, &nu), out): ((&f64, &f64), &mut f64), t: f64) -> f64 {
    *out = t;
    let q = 1.0 / (1.0 + odds); // 1 - mu
    q * t + odds * q * nu
}

/// One voxel of the forward pass: turns `T_i` in `out` into `m1_i / m0_i` with the prefix
/// `a` (`a_i`), and returns `a_{i+1}`.
#[inline(always)]
fn prefix_step(((&odds, &nu), out): ((&f64, &f64), &mut f64), a: f64) -> f64 {
    let (m1, m0) = (a + nu, a + *out);
    *out = m1 / m0; // (0 / 0 = NaN where the ray says nothing: log-odds 0)
    (a * (1.0 + odds) + odds * nu).min(A_CAP)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// Brute force over all 2^N occupancy states of MRF eq. (3) with the beyond term:
    /// psi(o) = nu_j for the first occupied voxel j, nu_beyond when none is occupied.
    fn brute_force(mu: &[f64], nu: &[f64], nu_beyond: f64) -> Vec<f64> {
        let n = mu.len();
        let mut m = vec![[0.0f64; 2]; n];
        for state in 0u32..(1 << n) {
            let first = (0..n).find(|&j| state >> j & 1 == 1);
            let psi = first.map_or(nu_beyond, |j| nu[j]);
            for (i, mi) in m.iter_mut().enumerate() {
                let oi = (state >> i & 1) as usize;
                let mut w = psi;
                for j in (0..n).filter(|&j| j != i) {
                    w *= if state >> j & 1 == 1 { mu[j] } else { 1.0 - mu[j] };
                }
                mi[oi] += w;
            }
        }
        // An uninformative factor (all likelihoods zero) sends 1/2, as the fast form does.
        m.iter().map(|[m0, m1]| if m0 + m1 > 0.0 { m1 / (m0 + m1) } else { 0.5 }).collect()
    }

    #[test]
    fn matches_brute_force_enumeration() {
        let mut rng = Rng::new(2024);
        let mut out = Vec::new();
        for trial in 0..400 {
            let n = 1 + (trial % 12);
            let mu: Vec<f64> = (0..n).map(|_| rng.range(0.01, 0.99)).collect();
            // Likelihoods across many orders of magnitude, some exactly zero.
            let nu: Vec<f64> =
                (0..n).map(|_| if rng.uniform() < 0.15 { 0.0 } else { 10f64.powf(rng.range(-4.0, 2.0)) }).collect();
            let beyond = if trial % 3 == 0 { 0.0 } else { 10f64.powf(rng.range(-4.0, 1.0)) };
            ray_messages(&mu, &nu, beyond, &mut out);
            let expected = brute_force(&mu, &nu, beyond);
            for i in 0..n {
                assert!((out[i] - expected[i]).abs() < 1e-9, "trial {trial}, voxel {i}: {} vs {}", out[i], expected[i]);
            }
        }
    }

    #[test]
    fn long_confident_rays_stay_finite_and_normalised() {
        let mut rng = Rng::new(7);
        let mut out = Vec::new();
        for &n in &[1000usize, 5000] {
            for pattern in 0..4 {
                let mu: Vec<f64> = (0..n)
                    .map(|i| match pattern {
                        0 => 0.999, // everything confidently occupied
                        1 => 1e-6,  // everything confidently free
                        2 => {
                            if i % 2 == 0 {
                                1.0 - 1e-12
                            } else {
                                1e-12
                            }
                        } // extremes, clamped
                        _ => rng.range(0.0, 1.0),
                    })
                    .collect();
                let nu: Vec<f64> = (0..n).map(|i| if i == n - 10 { 50.0 } else { rng.range(0.0, 1e-3) }).collect();
                ray_messages(&mu, &nu, 1e-6, &mut out);
                assert!(out.iter().all(|m| m.is_finite() && (0.0..=1.0).contains(m)), "pattern {pattern}");
            }
        }
        // Free space in front of a likely surface: voxels before it are told "empty", the
        // surface voxel "occupied", even 1000 voxels along.
        let n = 1200;
        let mu = vec![0.001; n]; // converged free space
        let mut nu = vec![1e-6; n];
        nu[1000] = 20.0;
        ray_messages(&mu, &nu, 0.0, &mut out);
        assert!(out[10] < 0.2 && out[999] < 0.2 && out[1000] > 0.9, "{} {} {}", out[10], out[999], out[1000]);
    }

    /// Two rays' messages side by side are each ray's alone, bit for bit: rays of every pair
    /// of lengths (none included), either the longer, with zero likelihoods and beyond terms.
    #[test]
    fn a_pair_of_rays_gives_each_rays_own_messages() {
        fn factor<'a>(r: &'a (Vec<f64>, Vec<f64>, f64), out: &'a mut Vec<f64>) -> RayFactor<'a> {
            RayFactor { odds: &r.0, nu: &r.1, nu_beyond: r.2, out }
        }
        let mut rng = Rng::new(31);
        let mut ray = |n: usize| {
            let odds: Vec<f64> = (0..n).map(|_| rng.range(-20.0, 20.0).exp()).collect();
            let nu: Vec<f64> =
                (0..n).map(|_| if rng.uniform() < 0.3 { 0.0 } else { 10f64.powf(rng.range(-6.0, 2.0)) }).collect();
            let beyond = if rng.uniform() < 0.3 { 0.0 } else { rng.range(0.0, 3.0) };
            (odds, nu, beyond)
        };
        let (mut alone, mut pair) = ((Vec::new(), Vec::new()), (Vec::new(), Vec::new()));
        let mut differ = 0;
        for na in 0..9 {
            for nb in [0, 1, 2, 5, 8, 40] {
                let (a, b) = (ray(na), ray(nb));
                ray_log_messages(&a.0, &a.1, a.2, 20.0, &mut alone.0);
                ray_log_messages(&b.0, &b.1, b.2, 20.0, &mut alone.1);
                ray_log_messages_pair(factor(&a, &mut pair.0), factor(&b, &mut pair.1), 20.0);
                let bits = |v: &Vec<f64>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&alone.0), bits(&pair.0), "lengths {na} and {nb}: the first ray");
                assert_eq!(bits(&alone.1), bits(&pair.1), "lengths {na} and {nb}: the second ray");
                differ += alone.0.iter().zip(&alone.1).filter(|(x, y)| x != y).count();
            }
        }
        assert!(differ > 100, "the two rays' messages differ in only {differ} places");
    }
}
