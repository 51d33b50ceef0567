//! Learning a [`NoiseModel`] from pairs of depth images (MRFMap sec. IV-C).
//!
//! Feed a [`Calibrator`] pairs of images of the same views, one measured by the sensor and
//! one "true" (a better sensor, a surveyed plane, a simulator). Per pixel patch and per bin of
//! true depth it keeps the residuals `measured - true`; [`Calibrator::finish`] then
//!
//! 1. rejects outliers per bin (more than 4 robust standard deviations from the median, e.g.
//!    pixels on depth edges where the two images see different surfaces),
//! 2. takes each bin's mean and standard deviation,
//! 3. fits the bias polynomial to the means and the std polynomial to the standard deviations
//!    by weighted least squares, each bin weighted by the inverse variance of its estimate
//!    (`n / s^2` for a mean, `2n / s^2` for a standard deviation),
//! 4. sets the aggregate to the coefficient-wise median over the fitted patches;
//! 5. patches with too few populated bins for their own polynomials (fewer than `degree + 2`)
//!    but some data get the aggregate *adjusted* to their bins: its bias shifted by their
//!    weighted mean offset, its std scaled by their weighted mean ratio. So do patches whose
//!    own fit is implausible anywhere in the calibrated depth range ([`IMPLAUSIBLE`]: a
//!    quadratic through a few close bins can reach metres outside them). Patches with no data
//!    get the aggregate as it is.
//!
//! Memory is bounded: each (patch, bin) cell keeps at most [`RESERVOIR`] residuals, a uniform
//! sample of everything it saw (reservoir sampling, seeded, so results are reproducible).

use super::DepthImage;
use super::noise::{NoiseModel, PatchModel, Poly};
use crate::random::Rng;

/// Residuals kept per (patch, depth bin); beyond this a uniform sample is kept.
pub const RESERVOIR: usize = 2048;

/// Residuals more than this many robust standard deviations from the bin median are outliers.
const CLIP_SIGMAS: f64 = 4.0;

/// A patch's fit is implausible where its std is not positive or this many times the
/// aggregate's, or its bias this many aggregate stds plus a tenth of the depth from the
/// aggregate's bias: the few bins of a patch that
/// sees a narrow range of depths let a quadratic go anywhere outside them (a 9 m std at 2 m
/// was seen on coffin-world). Real patches differ from the median by far less (D435: std
/// within 2x over the image).
pub const IMPLAUSIBLE: f64 = 4.0;

/// Settings of a calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationOptions {
    /// Patch side in pixels (MRFMap uses 20).
    pub patch: u32,
    /// Polynomial degree, 0 to 2.
    pub degree: usize,
    /// True depths below this (metres) are ignored.
    pub min_depth: f64,
    /// True depths at or above this (metres) are ignored.
    pub max_depth: f64,
    /// Depth bin width (metres).
    pub bin: f64,
    /// A bin needs at least this many residuals to enter a fit.
    pub min_samples: usize,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        CalibrationOptions { patch: 20, degree: 2, min_depth: 0.2, max_depth: 10.0, bin: 0.1, min_samples: 30 }
    }
}

impl CalibrationOptions {
    fn check(&self) -> Result<(), String> {
        if self.patch == 0 {
            return Err("patch size must be at least 1 pixel".into());
        }
        if self.degree > 2 {
            return Err(format!("degree must be 0, 1 or 2, got {}", self.degree));
        }
        if !(self.min_depth >= 0.0 && self.max_depth > self.min_depth && self.max_depth.is_finite()) {
            return Err(format!("need 0 <= min depth < max depth, got {} and {}", self.min_depth, self.max_depth));
        }
        if !(self.bin > 0.0) || (self.max_depth - self.min_depth) / self.bin > 100_000.0 {
            return Err(format!("bin width {} is not positive or gives too many bins", self.bin));
        }
        if self.min_samples < 2 {
            return Err("a bin needs at least 2 samples for a standard deviation".into());
        }
        Ok(())
    }

    fn bins(&self) -> usize {
        ((self.max_depth - self.min_depth) / self.bin).ceil() as usize
    }
}

/// One bin of one patch: the statistics its polynomials were fitted to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BinStats {
    /// Mean true z-depth of the kept residuals.
    pub depth: f64,
    /// Mean residual (measured - true).
    pub mean: f64,
    /// Standard deviation of the residuals.
    pub std: f64,
    /// Residuals kept after outlier rejection.
    pub count: usize,
}

/// How a patch's polynomials were obtained.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PatchFit {
    /// Fitted to its own bins.
    Fitted,
    /// The aggregate, shifted (bias) and scaled (std) to match its few bins.
    Adjusted,
    /// Its own fit was implausible somewhere in the calibrated depth range (a std that is not
    /// positive or over [`IMPLAUSIBLE`] times the aggregate's, or a bias far from the
    /// aggregate's, see there): the aggregate adjusted to its bins instead.
    Implausible,
    /// No data: the aggregate.
    Aggregate,
}

/// What a calibration produced.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// The learnt model: aggregate plus one pair of polynomials per patch.
    pub model: NoiseModel,
    /// Per patch (row-major): how its polynomials were obtained.
    pub fits: Vec<PatchFit>,
    /// Per patch: the bins used (populated bins only).
    pub bins: Vec<Vec<BinStats>>,
    /// Valid pixel pairs seen (both depths valid, true depth in range).
    pub samples: u64,
    /// Residuals rejected as outliers (among those kept in the reservoirs).
    pub outliers: u64,
    /// Image pairs added.
    pub images: usize,
}

#[derive(Clone, Default)]
struct Cell {
    seen: u64,
    kept: Vec<(f32, f32)>, // (true depth, residual)
}

/// Accumulates residuals from image pairs; see the module documentation.
///
/// ```
/// use mrfmap::frames::{CalibrationOptions, Calibrator, DepthImage};
/// let opts = CalibrationOptions { patch: 4, degree: 0, min_samples: 2, ..Default::default() };
/// let mut cal = Calibrator::new(opts).unwrap();
/// for (i, z) in [1.0f32, 1.5, 2.0].into_iter().enumerate() {
///     let truth = DepthImage::from_vec(4, 4, vec![z; 16]).unwrap();
///     // A sensor that reads 1 cm long, +-2 mm.
///     let noisy = (0..16).map(|k| z + 0.01 + if (k + i) % 2 == 0 { 0.002 } else { -0.002 }).collect();
///     cal.add(&DepthImage::from_vec(4, 4, noisy).unwrap(), &truth).unwrap();
/// }
/// let result = cal.finish().unwrap();
/// assert!((result.model.bias.0[0] - 0.01).abs() < 1e-6);
/// assert!((result.model.std.0[0] - 0.002).abs() < 2e-4);
/// ```
pub struct Calibrator {
    options: CalibrationOptions,
    size: Option<(u32, u32)>,
    cells: Vec<Cell>, // patch-major, then bin
    rng: Rng,
    samples: u64,
    images: usize,
}

impl Calibrator {
    /// A calibrator with these settings (checked here).
    pub fn new(options: CalibrationOptions) -> Result<Self, String> {
        options.check()?;
        Ok(Calibrator { options, size: None, cells: Vec::new(), rng: Rng::new(0x5EED), samples: 0, images: 0 })
    }

    /// Patch grid `(rows, cols)` for the images seen so far (`None` before the first).
    pub fn grid(&self) -> Option<(u32, u32)> {
        self.size.map(|(w, h)| (h.div_ceil(self.options.patch), w.div_ceil(self.options.patch)))
    }

    /// Adds one pair. Both images must have the same size as each other and as every earlier
    /// pair. Pixels where either depth is 0 (no return) or not finite are skipped.
    pub fn add(&mut self, measured: &DepthImage, truth: &DepthImage) -> Result<(), String> {
        let (w, h) = (truth.width(), truth.height());
        if (measured.width(), measured.height()) != (w, h) {
            return Err(format!(
                "measured image is {}x{} but the true image is {w}x{h}",
                measured.width(),
                measured.height()
            ));
        }
        match self.size {
            Some(s) if s != (w, h) => {
                return Err(format!("image is {w}x{h} but earlier images were {}x{}", s.0, s.1));
            }
            Some(_) => {}
            None => {
                self.size = Some((w, h));
                let (rows, cols) = self.grid().expect("size just set");
                self.cells = vec![Cell::default(); (rows * cols) as usize * self.options.bins()];
            }
        }
        let (_, cols) = self.grid().expect("size set");
        let o = &self.options;
        let nbins = o.bins();
        for v in 0..h {
            for u in 0..w {
                let (Some(m), Some(t)) = (measured.get(u, v), truth.get(u, v)) else { continue };
                let t64 = t as f64;
                if !(t64 >= o.min_depth && t64 < o.max_depth) {
                    continue;
                }
                let bin = (((t64 - o.min_depth) / o.bin) as usize).min(nbins - 1);
                let patch = ((v / o.patch) * cols + u / o.patch) as usize;
                let cell = &mut self.cells[patch * nbins + bin];
                cell.seen += 1;
                let sample = (t, m - t);
                if cell.kept.len() < RESERVOIR {
                    cell.kept.push(sample);
                } else {
                    let j = (self.rng.next_u64() % cell.seen) as usize;
                    if j < RESERVOIR {
                        cell.kept[j] = sample;
                    }
                }
                self.samples += 1;
            }
        }
        self.images += 1;
        Ok(())
    }

    /// Fits the model. Fails when no patch has enough data.
    pub fn finish(self) -> Result<Calibration, String> {
        let Some((rows, cols)) = self.grid() else {
            return Err("no image pairs were added".into());
        };
        let o = &self.options;
        let nbins = o.bins();
        let mut outliers = 0;
        let mut fits: Vec<Option<(Poly, Poly)>> = Vec::new();
        let mut all_bins = Vec::new();
        for cells in self.cells.chunks(nbins) {
            let mut bins = Vec::new();
            for cell in cells {
                if let Some((stats, rejected)) = bin_stats(&cell.kept, o.min_samples) {
                    outliers += rejected;
                    bins.push(stats);
                }
            }
            let fit = (bins.len() >= o.degree + 2).then(|| fit_bins(&bins, o.degree)).flatten();
            fits.push(fit);
            all_bins.push(bins);
        }
        let fitted: Vec<(Poly, Poly)> = fits.iter().flatten().copied().collect();
        if fitted.is_empty() {
            return Err(format!(
                "no patch has {} depth bins with at least {} valid pixels each: add more image pairs, \
                 widen the depth range or lower the degree",
                o.degree + 2,
                o.min_samples
            ));
        }
        let median_poly = |pick: fn(&(Poly, Poly)) -> Poly| {
            let mut c = [0.0; 3];
            for (k, ck) in c.iter_mut().enumerate() {
                let mut v: Vec<f64> = fitted.iter().map(|f| pick(f).0[k]).collect();
                *ck = median(&mut v);
            }
            Poly(c)
        };
        let aggregate = (median_poly(|f| f.0), median_poly(|f| f.1));
        // The depths calibrated, where every patch's fit must be plausible.
        let depths = all_bins.iter().flatten().map(|b| b.depth);
        let (lo, hi) = depths.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), z| (lo.min(z), hi.max(z)));
        let plausible = |(bias, std): &(Poly, Poly)| {
            (0..=16).all(|k| {
                let z = lo + (hi - lo) * k as f64 / 16.0;
                let agg_std = aggregate.1.eval(z).max(1e-3);
                let s = std.eval(z);
                // Biases differ across an image by more than stds do at close range (a D435's
                // by centimetres where its std is millimetres): a tenth of the depth more.
                let bias_slack = IMPLAUSIBLE * agg_std + 0.1 * z;
                s > 0.0 && s <= IMPLAUSIBLE * agg_std && (bias.eval(z) - aggregate.0.eval(z)).abs() <= bias_slack
            })
        };
        let mut kinds = Vec::with_capacity(fits.len());
        let polys: Vec<(Poly, Poly)> = fits
            .iter()
            .zip(&all_bins)
            .map(|(fit, bins)| match fit {
                Some(f) if plausible(f) => {
                    kinds.push(PatchFit::Fitted);
                    *f
                }
                Some(_) => {
                    kinds.push(PatchFit::Implausible);
                    adjust(aggregate, bins)
                }
                None if !bins.is_empty() => {
                    kinds.push(PatchFit::Adjusted);
                    adjust(aggregate, bins)
                }
                None => {
                    kinds.push(PatchFit::Aggregate);
                    aggregate
                }
            })
            .collect();
        let model = NoiseModel {
            bias: aggregate.0,
            std: aggregate.1,
            patches: Some(PatchModel {
                size: o.patch,
                rows,
                cols,
                bias: polys.iter().map(|p| p.0).collect(),
                std: polys.iter().map(|p| p.1).collect(),
            }),
            likelihood_scale: 1.0,
        };
        Ok(Calibration { model, fits: kinds, bins: all_bins, samples: self.samples, outliers, images: self.images })
    }
}

/// The aggregate `(bias, std)` shifted and scaled to a patch's few bins: bias offset by the
/// bins' mean residual minus the aggregate bias (weights `n / s^2`), std scaled by the mean
/// ratio of the bins' std to the aggregate's (weights `n`).
fn adjust((bias, std): (Poly, Poly), bins: &[BinStats]) -> (Poly, Poly) {
    let (mut wo, mut so, mut wr, mut sr) = (0.0, 0.0, 0.0, 0.0);
    for b in bins {
        let w = b.count as f64 / (b.std * b.std).max(1e-12);
        wo += w;
        so += w * (b.mean - bias.eval(b.depth));
        let agg = std.eval(b.depth);
        if agg > 0.0 {
            wr += b.count as f64;
            sr += b.count as f64 * b.std / agg;
        }
    }
    let offset = if wo > 0.0 { so / wo } else { 0.0 };
    let scale = if wr > 0.0 { sr / wr } else { 1.0 };
    let mut b = bias;
    b.0[0] += offset;
    (b, Poly(std.0.map(|c| c * scale)))
}

/// Median of `v` (reorders it); `v` must not be empty.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// Robust statistics of one bin: `None` if fewer than `min` residuals survive clipping.
/// Also returns how many residuals were clipped.
fn bin_stats(kept: &[(f32, f32)], min: usize) -> Option<(BinStats, u64)> {
    if kept.len() < min {
        return None;
    }
    let mut r: Vec<f64> = kept.iter().map(|&(_, r)| r as f64).collect();
    let med = median(&mut r);
    let mut dev: Vec<f64> = r.iter().map(|x| (x - med).abs()).collect();
    let sigma = 1.4826 * median(&mut dev);
    let limit = CLIP_SIGMAS * sigma;
    let inliers = kept.iter().filter(|&&(_, r)| (r as f64 - med).abs() <= limit);
    let (mut n, mut sz, mut sr, mut srr) = (0usize, 0.0, 0.0, 0.0);
    for &(z, r) in inliers {
        let r = r as f64 - med; // centred for a numerically clean variance
        n += 1;
        sz += z as f64;
        sr += r;
        srr += r * r;
    }
    if n < min {
        return None;
    }
    let nf = n as f64;
    let mean = sr / nf;
    let var = ((srr - nf * mean * mean) / (nf - 1.0)).max(0.0);
    let stats = BinStats { depth: sz / nf, mean: med + mean, std: var.sqrt(), count: n };
    Some((stats, (kept.len() - n) as u64))
}

/// Fits bias and std polynomials of `degree` to a patch's bins (weighted least squares).
fn fit_bins(bins: &[BinStats], degree: usize) -> Option<(Poly, Poly)> {
    let z: Vec<f64> = bins.iter().map(|b| b.depth).collect();
    // Inverse variances of the estimates; a tiny floor keeps noise-free bins finite.
    let var = |b: &BinStats| (b.std * b.std).max(1e-12);
    let w_mean: Vec<f64> = bins.iter().map(|b| b.count as f64 / var(b)).collect();
    let w_std: Vec<f64> = bins.iter().map(|b| 2.0 * b.count as f64 / var(b)).collect();
    let means: Vec<f64> = bins.iter().map(|b| b.mean).collect();
    let stds: Vec<f64> = bins.iter().map(|b| b.std).collect();
    Some((weighted_polyfit(&z, &means, &w_mean, degree)?, weighted_polyfit(&z, &stds, &w_std, degree)?))
}

/// Weighted least-squares polynomial of `degree` (0-2) through `(x, y)`, solved by SVD of the
/// row-scaled Vandermonde matrix (stable where normal equations lose digits).
///
/// ```
/// use mrfmap::frames::weighted_polyfit;
/// let x = [0.5, 1.0, 2.0, 3.0];
/// let y: Vec<f64> = x.iter().map(|x| 1.0 - 2.0 * x + 0.5 * x * x).collect();
/// let p = weighted_polyfit(&x, &y, &[1.0, 2.0, 3.0, 4.0], 2).unwrap();
/// assert!((p.0[0] - 1.0).abs() < 1e-9 && (p.0[1] + 2.0).abs() < 1e-9 && (p.0[2] - 0.5).abs() < 1e-9);
/// ```
pub fn weighted_polyfit(x: &[f64], y: &[f64], w: &[f64], degree: usize) -> Option<Poly> {
    use nalgebra::{DMatrix, DVector};
    let n = x.len();
    if degree > 2 || n <= degree || y.len() != n || w.len() != n {
        return None;
    }
    // Scale x to about unit size so the columns are comparable.
    let scale = x.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
    let a = DMatrix::from_fn(n, degree + 1, |i, k| w[i].sqrt() * (x[i] / scale).powi(k as i32));
    let b = DVector::from_fn(n, |i, _| w[i].sqrt() * y[i]);
    let c = a.svd(true, true).solve(&b, 1e-12).ok()?;
    let mut p = [0.0; 3];
    for k in 0..=degree {
        p[k] = c[k] / scale.powi(k as i32);
    }
    p.iter().all(|v| v.is_finite()).then_some(Poly(p))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    #[test]
    fn recovers_known_polynomials_and_rejects_outliers() {
        let bias = Poly([0.01, -0.004, 0.006]);
        let std = Poly([0.002, 0.001, 0.003]);
        let opts = CalibrationOptions { patch: 8, ..Default::default() };
        let mut cal = Calibrator::new(opts).unwrap();
        let mut rng = Rng::new(7);
        for step in 0..30 {
            let z = 0.6 + 0.1 * step as f64;
            let truth = DepthImage::from_vec(16, 16, vec![z as f32; 256]).unwrap();
            let noisy = (0..256)
                .map(|k| {
                    if k % 50 == 0 {
                        return (z + 1.5) as f32; // an edge pixel seeing the background
                    }
                    if k % 37 == 0 {
                        return 0.0; // no return
                    }
                    (z + bias.eval(z) + std.eval(z) * rng.normal()) as f32
                })
                .collect();
            cal.add(&DepthImage::from_vec(16, 16, noisy).unwrap(), &truth).unwrap();
        }
        let out = cal.finish().unwrap();
        assert_eq!(out.fits, vec![PatchFit::Fitted; 4]);
        assert!(out.outliers > 0);
        for z in [1.0, 2.0, 3.0] {
            let (b, s) = out.model.bias_std(12, 3, z);
            assert!((b - bias.eval(z)).abs() < 2e-3, "bias at {z}: {b} vs {}", bias.eval(z));
            assert!((s / std.eval(z) - 1.0).abs() < 0.1, "std at {z}: {s} vs {}", std.eval(z));
        }
    }

    #[test]
    fn a_patch_fit_that_runs_off_outside_its_few_depths_falls_back_to_the_aggregate() {
        // Five 4x4 patches in a row. The first four see 1-3 m with a 1 cm bias and 1 cm std;
        // the fifth sees only 1.0-1.3 m, with a bias that rises steeply there (as a patch on
        // a depth edge can): its own quadratic reaches metres of bias at 3 m.
        let opts = CalibrationOptions { patch: 4, min_samples: 8, ..Default::default() };
        let mut cal = Calibrator::new(opts).unwrap();
        let mut rng = Rng::new(3);
        for i in 0..84 {
            let far = 1.0 + 2.0 * (i % 21) as f64 / 20.0;
            let near = 1.05 + 0.1 * (i % 4) as f64;
            let truth: Vec<f32> = (0..80).map(|k| if k % 20 >= 16 { near } else { far } as f32).collect();
            let noisy = truth
                .iter()
                .enumerate()
                .map(|(k, &z)| {
                    let z = z as f64;
                    let bias = if k % 20 >= 16 { 3.0 * (z - 1.0).powi(2) } else { 0.01 };
                    (z + bias + 0.01 * rng.normal()) as f32
                })
                .collect();
            cal.add(&DepthImage::from_vec(20, 4, noisy).unwrap(), &DepthImage::from_vec(20, 4, truth).unwrap())
                .unwrap();
        }
        let out = cal.finish().unwrap();
        assert_eq!(out.fits, [[PatchFit::Fitted; 4].as_slice(), &[PatchFit::Implausible]].concat());
        // The fifth patch: the aggregate shifted to its bins' mean bias, not metres off at 3 m.
        let (b, s) = out.model.bias_std(18, 2, 3.0);
        assert!(b.abs() < 0.5 && s > 0.0 && s < 0.05, "bias {b}, std {s}");
        let own = fit_bins(&out.bins[4], 2).unwrap();
        assert!(own.0.eval(3.0) > 5.0, "its own fit: {:?}", own.0);
    }

    #[test]
    fn bad_input_is_refused() {
        assert!(Calibrator::new(CalibrationOptions { degree: 3, ..Default::default() }).is_err());
        assert!(Calibrator::new(CalibrationOptions { bin: 0.0, ..Default::default() }).is_err());
        assert!(Calibrator::new(CalibrationOptions { min_depth: 3.0, max_depth: 1.0, ..Default::default() }).is_err());
        let mut cal = Calibrator::new(CalibrationOptions::default()).unwrap();
        let a = DepthImage::from_vec(4, 4, vec![1.0; 16]).unwrap();
        let b = DepthImage::from_vec(4, 2, vec![1.0; 8]).unwrap();
        assert!(cal.add(&a, &b).unwrap_err().contains("4x2"));
        cal.add(&a, &a).unwrap();
        assert!(cal.add(&b, &b).unwrap_err().contains("earlier images were 4x4"));
        let e = cal.finish().unwrap_err();
        assert!(e.contains("no patch has 4 depth bins"), "{e}");
        assert!(Calibrator::new(CalibrationOptions::default()).unwrap().finish().is_err());
    }
}
