//! `exp` and `ln` for loops over whole slices that the compiler vectorises.
//!
//! The MRF's trace takes one exponential (a voxel's cavity as odds) and one logarithm (its
//! message as log-odds) per voxel a ray crosses, and the noise model's tail one exponential
//! per voxel boundary ([`crate::frames::upper_tail`]): called from libm, one value at a time,
//! they were 13% of a trace's instructions. Here they are plain arithmetic on the bits of
//! IEEE doubles, with no calls, tables or branches, so each loop runs as SIMD on any
//! x86-64 (two lanes of SSE2) or aarch64. Both are accurate to a few units in the 14th
//! significant digit over the ranges documented, far finer than the `f32` messages they
//! feed (tested against `std` below).

use std::f64::consts::LOG2_E;

/// Doubles in the widest vectors a loop here is compiled for (AVX2's four). A loop whose
/// length is a multiple of this runs as whole vectors, with no scalar remainder: on slices of
/// a dozen values the remainder of each loop took about as long as its vectors.
pub(crate) const VECTOR_LANES: usize = 4;

/// Adding and subtracting this rounds a double of magnitude below 2^51 to an integer and
/// leaves the integer in the low bits of the sum (1.5 * 2^52: the sum stays in one binade).
const SHIFTER: f64 = 6_755_399_441_055_744.0;

/// `ln 2` split so that `k * LN2_HI` is exact for `|k| < 2^11` (Cody and Waite).
const LN2_HI: f64 = 0.693_147_180_369_123_8;
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;

/// `1 / n!` for `n = 11 down to 2`: the Taylor series of `e^r - 1 - r`, Horner order.
const EXP_TAYLOR: [f64; 10] = [
    1.0 / 39_916_800.0,
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40_320.0,
    1.0 / 5_040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
];

/// `e^x`, for `|x| <= 700` (beyond, the argument is clamped to +-700), with no call and no
/// branch, so that a loop of it vectorises.
///
/// `x = k ln 2 + r` with `|r| <= ln 2 / 2`; `e^r` by its Taylor series to `r^11` (truncation
/// below 7e-15 relative); `2^k` written straight into a double's exponent bits.
#[inline(always)] // (so that the AVX2 copy of a tile trace has it in four lanes)
pub(crate) fn exp(x: f64) -> f64 {
    let v = x.clamp(-700.0, 700.0);
    let t = v * LOG2_E + SHIFTER;
    let k = t - SHIFTER;
    let r = (v - k * LN2_HI) - k * LN2_LO;
    let mut p = EXP_TAYLOR[0];
    for c in &EXP_TAYLOR[1..] {
        p = p * r + c;
    }
    let e_r = 1.0 + r + r * r * p;
    // `t`'s low bits hold k (two's complement within the mantissa); 2^k is the double
    // with biased exponent k + 1023.
    let k_bits = t.to_bits().wrapping_sub(SHIFTER.to_bits());
    let scale = f64::from_bits(k_bits.wrapping_add(1023) << 52);
    e_r * scale
}

/// `1 / (2n + 1)` for `n = 8 down to 1`: the series of `atanh(s) / s - 1` in `s^2`.
const ATANH_SERIES: [f64; 8] =
    [1.0 / 17.0, 1.0 / 15.0, 1.0 / 13.0, 1.0 / 11.0, 1.0 / 9.0, 1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0];

/// Replaces every `y` in `ys` by `ln y` clamped to `[-bound, bound]`, for `y` positive
/// (zero and infinity clamp to the bounds; NaN reads as 0). `bound` must be below 700.
///
/// `y = 2^e m` with `m` in `[sqrt(1/2), sqrt(2))`; `ln m = 2 atanh(s)`, `s = (m - 1) / (m + 1)`,
/// `|s| <= 0.172`, by its series to `s^17` (truncation below 2e-16).
#[inline(always)] // (so that the AVX2 copy of a tile trace has it in four lanes)
pub(crate) fn ln_clamped_in_place(ys: &mut [f64], bound: f64) {
    const MANTISSA: u64 = (1 << 52) - 1;
    // `e^-bound` and `e^bound` are normal doubles: clamping first keeps zeros, infinities
    // and subnormals out of the bit arithmetic.
    let (lo, hi) = ((-bound).exp(), bound.exp());
    for y in ys.iter_mut() {
        let nan = y.is_nan();
        let v = y.clamp(lo, hi);
        let bits = v.to_bits();
        // The mantissa as a double in [1, 2), halved when above sqrt(2) (and the exponent
        // counted one higher).
        let m = f64::from_bits((bits & MANTISSA) | 1.0f64.to_bits());
        let big = m > std::f64::consts::SQRT_2;
        let m = if big { 0.5 * m } else { m };
        // The biased exponent as a double, without an integer conversion (none is
        // vectorised on SSE2): 2^52 + e read back as a double is exact.
        let e = f64::from_bits((bits >> 52) | 0x4330_0000_0000_0000) - (4_503_599_627_370_496.0 + 1023.0);
        let e = if big { e + 1.0 } else { e };
        let s = (m - 1.0) / (m + 1.0);
        let s2 = s * s;
        let mut p = ATANH_SERIES[0];
        for c in &ATANH_SERIES[1..] {
            p = p * s2 + c;
        }
        let ln_m = 2.0 * s + 2.0 * s * s2 * p;
        let ln = e * LN2_HI + (e * LN2_LO + ln_m);
        *y = if nan { 0.0 } else { ln.clamp(-bound, bound) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// Against `std`'s `exp` across the whole domain, relative error.
    #[test]
    fn exp_matches_std() {
        let mut rng = Rng::new(5);
        let mut xs: Vec<f64> = (0..200_000).map(|_| rng.range(-700.0, 700.0)).collect();
        xs.extend((0..200_000).map(|_| rng.range(-21.0, 21.0)));
        xs.extend([0.0, -0.0, 1.0, -1.0, LN2_HI / 2.0, -LN2_HI / 2.0, 700.0, -700.0]);
        let got: Vec<f64> = xs.iter().map(|&x| exp(x)).collect();
        for (x, g) in xs.iter().zip(&got) {
            let want = x.exp();
            assert!(((g - want) / want).abs() < 2e-14, "exp({x}) = {g}, std says {want}");
        }
        // Beyond the domain: clamped.
        let far = [1e6, -1e6].map(exp);
        for (g, want) in far.iter().zip([700f64.exp(), (-700f64).exp()]) {
            assert!(((g - want) / want).abs() < 2e-14, "{g} vs {want}");
        }
    }

    /// Against `std`'s `ln` across many binades, absolute error (log-odds are summed), and the
    /// special values.
    #[test]
    fn ln_matches_std() {
        let mut rng = Rng::new(6);
        let bound = 600.0;
        let mut ys: Vec<f64> = (0..200_000).map(|_| 10f64.powf(rng.range(-250.0, 250.0))).collect();
        ys.extend((0..200_000).map(|_| rng.range(0.5, 2.0)));
        ys.extend([1.0, std::f64::consts::SQRT_2, 2.0, 0.5, f64::MIN_POSITIVE, f64::MAX]);
        let mut got = ys.clone();
        ln_clamped_in_place(&mut got, bound);
        for (y, g) in ys.iter().zip(&got) {
            let want = y.ln().clamp(-bound, bound);
            assert!((g - want).abs() < 1e-14 * want.abs().max(1.0), "ln({y}) = {g}, std says {want}");
        }
        let mut special = [0.0, f64::INFINITY, f64::NAN, 1e-300, 1e300];
        ln_clamped_in_place(&mut special, 13.8);
        assert_eq!(special, [-13.8, 13.8, 0.0, -13.8, 13.8]);
    }
}
