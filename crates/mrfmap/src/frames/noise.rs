//! The forward sensor noise model (docs/ALGORITHMS.md section 3, MRFMap sec. IV-C).
//!
//! A surface at true z-depth `z` is measured as `Normal(z + bias(z), std(z)^2)`, with
//! polynomials of degree 0-2 in `z`, either one aggregate pair for the whole image or one
//! pair per square pixel patch. Every engine that uses a forward model reads it from here.

use std::fmt::Write as _;
use std::path::Path;

use serde::Deserialize;

use crate::error::{Error, Result, parse_toml, read_text};
use crate::frames::{Camera, DepthImage};
use crate::random::Rng;
use crate::vecmath::VECTOR_LANES;

/// Standard deviations are clamped below at this value (metres), so a fitted polynomial that
/// dips to zero or below never yields a degenerate Gaussian.
pub const STD_FLOOR: f64 = 1e-4;

/// Likelihoods of surfaces more than this many standard deviations from the measurement are 0:
/// the mass beyond (below 1e-9) is nothing next to the voxels near the surface, and cutting
/// there keeps the error function off most of a ray.
pub const TAIL_CUTOFF: f64 = 6.0;

/// A polynomial `c0 + c1 z + c2 z^2` (ascending coefficients, unused ones zero).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Poly(pub [f64; 3]);

impl Poly {
    /// Evaluates the polynomial at `z` (Horner).
    #[inline]
    pub fn eval(&self, z: f64) -> f64 {
        let [c0, c1, c2] = self.0;
        c0 + z * (c1 + z * c2)
    }

    /// The largest value on `[lo, hi]`: at an end, or at the vertex of a downward parabola.
    pub fn max_on(&self, lo: f64, hi: f64) -> f64 {
        let [_, c1, c2] = self.0;
        let mut top = self.eval(lo).max(self.eval(hi));
        if c2 < 0.0 {
            let vertex = -c1 / (2.0 * c2);
            if vertex > lo && vertex < hi {
                top = top.max(self.eval(vertex));
            }
        }
        top
    }

    fn from_coeffs(c: &[f64]) -> std::result::Result<Self, String> {
        if c.is_empty() || c.len() > 3 {
            return Err(format!("a polynomial needs 1 to 3 coefficients, got {}", c.len()));
        }
        if c.iter().any(|v| !v.is_finite()) {
            return Err("polynomial coefficient is NaN or infinite".into());
        }
        let mut p = [0.0; 3];
        p[..c.len()].copy_from_slice(c);
        Ok(Poly(p))
    }
}

/// Per-patch polynomials over a grid of `size x size` pixel patches.
#[derive(Clone, Debug, PartialEq)]
pub struct PatchModel {
    /// Patch side in pixels.
    pub size: u32,
    /// Patch rows: `ceil(height / size)`.
    pub rows: u32,
    /// Patch columns: `ceil(width / size)`.
    pub cols: u32,
    /// Bias polynomial per patch, row-major, top row first.
    pub bias: Vec<Poly>,
    /// Standard-deviation polynomial per patch, same order.
    pub std: Vec<Poly>,
}

/// A depth sensor's forward noise model.
///
/// ```
/// use mrfmap::frames::{NoiseModel, Poly};
/// let model = NoiseModel::aggregate(Poly([0.0, 0.0, 0.004]), Poly([0.002, 0.0, 0.0035]));
/// let (bias, std) = model.bias_std(10, 10, 2.0);
/// assert!((bias - 0.016).abs() < 1e-12);
/// assert!((std - 0.016).abs() < 1e-12);
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseModel {
    /// Aggregate bias polynomial.
    pub bias: Poly,
    /// Aggregate standard-deviation polynomial.
    pub std: Poly,
    /// Optional per-patch polynomials; when present they replace the aggregate.
    pub patches: Option<PatchModel>,
    /// The likelihood's standard deviation over the model's (1, the default: the model as
    /// fitted). The MRFMap reference implementation's coffin-world configuration infers
    /// with a constant std of 0.05 m but a depth potential three times as wide (`3.0f *
    /// get_depth_sigma` in its kernels), which this reproduces with 3. Only the likelihood
    /// widens: rays still end 3 std (unscaled) past the measurement, as there.
    pub likelihood_scale: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct NoiseFile {
    bias: Vec<f64>,
    std: Vec<f64>,
    likelihood_scale: Option<f64>,
    patches: Option<PatchFile>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PatchFile {
    size: u32,
    rows: u32,
    cols: u32,
    bias: Vec<Vec<f64>>,
    std: Vec<Vec<f64>>,
}

impl NoiseModel {
    /// One pair of polynomials for every pixel.
    pub fn aggregate(bias: Poly, std: Poly) -> Self {
        NoiseModel { bias, std, patches: None, likelihood_scale: 1.0 }
    }

    /// Reads a `noise.toml` file.
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_toml(&read_text(path)?, path)
    }

    /// Parses `noise.toml` text; `origin` names the file in errors.
    pub fn from_toml(text: &str, origin: &Path) -> Result<Self> {
        let file: NoiseFile = parse_toml(text, origin)?;
        Self::from_file(file).map_err(|m| Error::file(origin, m))
    }

    /// Parses the `[noise]` table of a scene file (same keys as `noise.toml`).
    pub(crate) fn from_value(value: toml::Value, origin: &Path) -> Result<Self> {
        let file: NoiseFile =
            value.try_into().map_err(|e: toml::de::Error| Error::file(origin, format!("[noise]: {e}")))?;
        Self::from_file(file).map_err(|m| Error::file(origin, format!("[noise]: {m}")))
    }

    fn from_file(f: NoiseFile) -> std::result::Result<Self, String> {
        let bias = Poly::from_coeffs(&f.bias).map_err(|m| format!("bias: {m}"))?;
        let std = Poly::from_coeffs(&f.std).map_err(|m| format!("std: {m}"))?;
        // A fitted polynomial may dip below zero at depths it saw little of (STD_FLOOR covers
        // that), but a std that is nowhere positive over a depth camera's range is a typo.
        let working = (0..=48).map(|i| 0.2 + 0.1 * i as f64);
        if working.clone().all(|z| std.eval(z) <= 0.0) {
            return Err(format!(
                "std is not positive at any depth from 0.2 to 5 m (coefficients {:?}): a standard deviation \
                 must be positive",
                std.0
            ));
        }
        let likelihood_scale = f.likelihood_scale.unwrap_or(1.0);
        if !(likelihood_scale.is_finite() && (0.01..=100.0).contains(&likelihood_scale)) {
            return Err(format!("likelihood_scale must lie in [0.01, 100], got {likelihood_scale}"));
        }
        let patches = match f.patches {
            None => None,
            Some(p) => {
                let n = p.rows as usize * p.cols as usize;
                if p.size == 0 || n == 0 {
                    return Err("patches: size, rows and cols must be positive".into());
                }
                if p.bias.len() != n || p.std.len() != n {
                    return Err(format!(
                        "patches: rows * cols = {n} but bias has {} and std has {} entries",
                        p.bias.len(),
                        p.std.len()
                    ));
                }
                let parse = |list: &[Vec<f64>], what: &str| {
                    list.iter()
                        .enumerate()
                        .map(|(i, c)| Poly::from_coeffs(c).map_err(|m| format!("patches.{what}[{i}]: {m}")))
                        .collect::<std::result::Result<Vec<_>, _>>()
                };
                Some(PatchModel {
                    size: p.size,
                    rows: p.rows,
                    cols: p.cols,
                    bias: parse(&p.bias, "bias")?,
                    std: parse(&p.std, "std")?,
                })
            }
        };
        Ok(NoiseModel { bias, std, patches, likelihood_scale })
    }

    /// Checks that the patch grid covers exactly the camera's image.
    pub fn check_camera(&self, camera: &Camera) -> std::result::Result<(), String> {
        if let Some(p) = &self.patches {
            let rows = camera.height.div_ceil(p.size);
            let cols = camera.width.div_ceil(p.size);
            if p.rows != rows || p.cols != cols {
                return Err(format!(
                    "patch grid {}x{} of {} px does not fit a {}x{} image (needs {rows} rows, {cols} cols)",
                    p.rows, p.cols, p.size, camera.width, camera.height
                ));
            }
        }
        Ok(())
    }

    /// The bias and std polynomials that apply to pixel `(u, v)`.
    #[inline]
    pub fn polys(&self, u: u32, v: u32) -> (&Poly, &Poly) {
        match &self.patches {
            Some(p) => {
                let row = (v / p.size).min(p.rows - 1);
                let col = (u / p.size).min(p.cols - 1);
                let i = (row * p.cols + col) as usize;
                (&p.bias[i], &p.std[i])
            }
            None => (&self.bias, &self.std),
        }
    }

    /// Bias and standard deviation (clamped to [`STD_FLOOR`]) at pixel `(u, v)` and z-depth `z`.
    #[inline]
    pub fn bias_std(&self, u: u32, v: u32, z: f64) -> (f64, f64) {
        let (b, s) = self.polys(u, v);
        (b.eval(z), s.eval(z).max(STD_FLOOR))
    }

    /// Likelihood density (per metre of measured z-depth) of measuring `measured` at pixel
    /// `(u, v)` when the surface lies somewhere in the true z-depth interval `[z0, z1]`,
    /// uniformly: the forward model averaged over a voxel's extent along the ray. Averaging
    /// (instead of evaluating at one point) keeps voxels informative when the noise is much
    /// smaller than a voxel. One interval of [`RayLikelihood::over`], which walks a ray.
    ///
    /// ```
    /// use mrfmap::frames::{NoiseModel, Poly};
    /// let m = NoiseModel::aggregate(Poly([0.0, 0.0, 0.0]), Poly([0.01, 0.0, 0.0]));
    /// // A 1 cm-std sensor, measured 2.0 m; a voxel spanning the whole bell holds ~all mass.
    /// let l = m.likelihood_over(0, 0, 1.9, 2.1, 2.0);
    /// assert!((l * 0.2 - 1.0).abs() < 1e-6);
    /// assert!(m.likelihood_over(0, 0, 2.5, 2.6, 2.0) < 1e-100);
    /// ```
    pub fn likelihood_over(&self, u: u32, v: u32, z0: f64, z1: f64, measured: f64) -> f64 {
        self.along_ray(u, v, measured).over(z0, z1)
    }

    /// The forward model of pixel `(u, v)` measuring `measured`, for the consecutive voxels
    /// of its ray ([`RayLikelihood::over`]).
    #[inline]
    pub fn along_ray(&self, u: u32, v: u32, measured: f64) -> RayLikelihood<'_> {
        let (bias, std) = self.polys(u, v);
        let scale = self.likelihood_scale;
        // Where a surface would put the reading more than TAIL_CUTOFF std beyond it, `over` is
        // exactly 0: `z + bias(z) + TAIL_CUTOFF std(z) < measured`. Bounding bias and std
        // over [0, measured] gives one z-depth before which that holds everywhere (less a
        // margin far above rounding), so the long stretch in front of a reading (most of a
        // ray) costs no evaluations.
        let reach = bias.max_on(0.0, measured) + TAIL_CUTOFF * scale * std.max_on(0.0, measured).max(STD_FLOOR);
        let zero_before = (measured - reach).min(measured) - 1e-6 * (1.0 + measured.abs());
        RayLikelihood { bias, std, scale, measured, zero_before, last: None }
    }

    /// What this sensor reads, without noise, where `truth` holds true z-depths: each valid
    /// pixel's `z + bias(z)` (pixels with no return stay so). The MRFMap reference
    /// implementation scores coffin-world against this target rather than the truth.
    ///
    /// ```
    /// use mrfmap::frames::{DepthImage, NoiseModel, Poly};
    /// let model = NoiseModel::aggregate(Poly([0.01, 0.0, 0.02]), Poly([0.01, 0.0, 0.0]));
    /// let mut truth = DepthImage::new(2, 1);
    /// truth.set(0, 0, 2.0);
    /// let read = model.biased(&truth);
    /// assert!((read.get(0, 0).unwrap() - 2.09).abs() < 1e-6);
    /// assert_eq!(read.get(1, 0), None);
    /// ```
    pub fn biased(&self, truth: &DepthImage) -> DepthImage {
        let mut out = truth.clone();
        for v in 0..truth.height() {
            for u in 0..truth.width() {
                if let Some(z) = truth.get(u, v) {
                    let z = f64::from(z);
                    out.set(u, v, (z + self.polys(u, v).0.eval(z)) as f32);
                }
            }
        }
        out
    }

    /// A noisy reading of `truth` drawn from this model, per patch when it has patches:
    /// `z + bias(z) + std(z) N(0, 1)` at each valid pixel (a draw at or below 0 is a hole).
    /// Deterministic in `(seed, view)` whatever the thread count: each row has its own stream.
    pub fn sample(&self, truth: &DepthImage, seed: u64, view: u64) -> DepthImage {
        use rayon::prelude::*;
        let w = truth.width() as usize;
        let mut data = truth.data().to_vec();
        data.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
            let mut rng = Rng::stream(seed, view, v as u64);
            for (u, z) in row.iter_mut().enumerate() {
                let n = rng.normal(); // drawn for every pixel so streams do not depend on validity
                if *z > 0.0 {
                    let (bias, std) = self.bias_std(u as u32, v as u32, f64::from(*z));
                    let m = f64::from(*z) + bias + std * n;
                    *z = if m > 0.0 { m as f32 } else { 0.0 };
                }
            }
        });
        DepthImage::from_vec(truth.width(), truth.height(), data).expect("same size")
    }

    /// The `noise.toml` text of this model.
    pub fn to_toml(&self) -> String {
        let poly = |p: &Poly| format!("[{:?}, {:?}, {:?}]", p.0[0], p.0[1], p.0[2]);
        let mut s = String::from(
            "# Forward sensor noise model: measured z ~ Normal(z + bias(z), std(z)^2), z = true z-depth (m).\n\
             # Polynomials with ascending coefficients [c0, c1, c2].\n",
        );
        let _ = writeln!(s, "bias = {}\nstd = {}", poly(&self.bias), poly(&self.std));
        if self.likelihood_scale != 1.0 {
            let _ = writeln!(s, "likelihood_scale = {:?}", self.likelihood_scale);
        }
        if let Some(p) = &self.patches {
            let _ = writeln!(s, "\n[patches]\nsize = {}\nrows = {}\ncols = {}", p.size, p.rows, p.cols);
            for (name, list) in [("bias", &p.bias), ("std", &p.std)] {
                let _ = writeln!(s, "{name} = [");
                for q in list {
                    let _ = writeln!(s, "  {},", poly(q));
                }
                let _ = writeln!(s, "]");
            }
        }
        s
    }
}

/// The forward model along one ray: the likelihood of each voxel in turn, where consecutive
/// voxels share the boundary between them. The measurement given a surface at true z-depth `z`
/// is `Normal(w(z), std(z)^2)` with `w(z) = z + bias(z)` (`std` times
/// [`NoiseModel::likelihood_scale`]); the probability of measuring within
/// the reading's resolution, for a surface uniform in `[z0, z1]`, is taken as the normal
/// probability between the standardised boundaries `(measured - w(z)) / std(z)`, over
/// `w(z1) - w(z0)`. So the probabilities of consecutive intervals add up exactly (they
/// telescope), and each boundary costs one bias and std evaluation and one tail lookup,
/// shared by the two voxels it separates: half the work of evaluating each voxel alone.
#[derive(Clone, Debug)]
pub struct RayLikelihood<'a> {
    bias: &'a Poly,
    std: &'a Poly,
    /// [`NoiseModel::likelihood_scale`].
    scale: f64,
    measured: f64,
    /// Intervals ending before this z-depth lie more than [`TAIL_CUTOFF`] std in front of the
    /// reading (their likelihood is 0).
    zero_before: f64,
    /// The last interval's far boundary: its z and what was computed there.
    last: Option<(f64, Boundary)>,
}

/// Buffers of [`RayLikelihood::over_each`], reused across rays.
#[derive(Clone, Debug, Default)]
pub struct Intervals {
    /// Per interval, its likelihood density.
    pub density: Vec<f64>,
    /// The boundaries' z-depths, from the first interval that may be nonzero on: its near end,
    /// then every interval's far end, padded to whole vectors.
    z: Vec<f64>,
    /// The boundaries of the intervals from the first that may be nonzero on, field by field
    /// ([`Boundary`]'s), so that each step is a loop the compiler vectorises: the first one's
    /// near boundary, then each one's far one. An interval's near boundary is the last one's
    /// far one, but where they leave a gap.
    w: Vec<f64>,
    sigma: Vec<f64>,
    x: Vec<f64>,
    tail: Vec<f64>,
    /// Per interval, 1 where its density is patched (a gap before it, or too short).
    marks: Vec<u8>,
}

/// One boundary of [`RayLikelihood`]: `w(z)`, `std(z)`, the standardised position and its tail.
#[derive(Clone, Copy, Debug)]
struct Boundary {
    w: f64,
    sigma: f64,
    x: f64,
    /// `upper_tail(|x|)`, NaN until needed.
    tail: f64,
}

impl Boundary {
    #[inline]
    fn tail(&mut self) -> f64 {
        if self.tail.is_nan() {
            self.tail = upper_tail(self.x.abs());
        }
        self.tail
    }
}

impl RayLikelihood<'_> {
    #[inline]
    fn boundary(&self, z: f64) -> Boundary {
        let w = z + self.bias.eval(z);
        let sigma = self.std.eval(z).max(STD_FLOOR) * self.scale;
        Boundary { w, sigma, x: (w - self.measured) / sigma, tail: f64::NAN }
    }

    /// Likelihood density (per metre of measured z-depth) when the surface lies uniformly in
    /// the true z-depth interval `[z0, z1]` (see [`NoiseModel::likelihood_over`]). Cheapest
    /// when `z0` is the previous call's `z1`. Intervals more than [`TAIL_CUTOFF`] std from
    /// the measurement give 0; tiny ones the point density at their middle.
    #[inline]
    pub fn over(&mut self, z0: f64, z1: f64) -> f64 {
        if z1 < self.zero_before {
            return 0.0;
        }
        let mut a = match self.last {
            Some((z, b)) if z == z0 => b,
            _ => self.boundary(z0),
        };
        let mut b = self.boundary(z1);
        let density = self.density(&mut a, &mut b);
        self.last = Some((z1, b)); // (with its tail, if computed)
        density
    }

    /// [`RayLikelihood::over`] of consecutive intervals `[z0[j], z1[j]]` (ascending, each
    /// starting where the last ended or later) into `out.density` (cleared first): the same
    /// values, bit for bit, in a fraction of the instructions. The intervals more than
    /// [`TAIL_CUTOFF`] std in front of the reading are skipped whole (their density is 0, and
    /// how many they are is returned); for the rest each step (the boundaries' fields, their
    /// tails, the densities) is a loop of its own over the intervals, on one vector per field,
    /// and the rare cases (gaps between intervals, intervals too short for the tails) are
    /// patched afterwards.
    #[inline(always)] // (so that the AVX2 copy of a tile trace has it in four lanes)
    pub fn over_each(&mut self, z0: &[f64], z1: &[f64], out: &mut Intervals) -> usize {
        debug_assert_eq!(z0.len(), z1.len());
        // (Counted in whole vectors, the intervals being ascending: a binary search, a chain of
        // dependent loads, cost more on rays of two dozen voxels.)
        let zero_before = self.zero_before;
        let start = z1.iter().filter(|&&z| z < zero_before).count();
        let n = z1.len();
        out.density.clear();
        out.density.resize(n, 0.0);
        if start == n {
            return start;
        }
        let (z0, z1) = (&z0[start..], &z1[start..]);
        let Intervals { density, z, w, sigma, x, tail, marks } = out;
        let (bias, std, scale, measured) = (self.bias, self.std, self.scale, self.measured);
        // Every loop runs over whole vectors: `m4` intervals, those past `m` copies of the
        // last, computed and never read. (A ray crosses a dozen voxels with any likelihood on
        // icl-livingroom-5 at 0.02 m: the scalar remainders of the loops in four lanes were
        // a large part of its likelihood.)
        let m = z1.len();
        let m4 = m.next_multiple_of(VECTOR_LANES);
        // Boundaries: `m + 1` of them, over whole vectors as well.
        let b4 = (m + 1).next_multiple_of(VECTOR_LANES);
        // (The buffers only grow, and every value read is written first: zeroing them for each
        // ray was a memset call per buffer, 1% of a trace.)
        for v in [&mut *z, &mut *w, &mut *sigma, &mut *x, &mut *tail] {
            if v.len() < m4 + VECTOR_LANES {
                v.resize(m4 + VECTOR_LANES, 0.0);
            }
        }
        z[0] = z0[0];
        z[1..=m].copy_from_slice(z1);
        z[m + 1..b4].fill(z1[m - 1]);
        density.resize(start + m4, 0.0);
        // Each interval's boundaries ([`RayLikelihood::boundary`], field by field): the first
        // one's near boundary at 0, then every interval's far one, so that interval `j` lies
        // between boundaries `j` and `j + 1`. (Plain loops: `extend` of a mapped iterator went
        // through a `fold` that the AVX2 copy of the trace did not inline. The near boundary
        // in the loops too: on its own it was a scalar `upper_tail`, a long chain of
        // dependent operations per ray.)
        let fields = w[..b4].iter_mut().zip(sigma[..b4].iter_mut()).zip(x[..b4].iter_mut());
        for (&z, ((w, sigma), x)) in z[..b4].iter().zip(fields) {
            *w = z + bias.eval(z);
            *sigma = std.eval(z).max(STD_FLOOR) * scale;
            *x = (*w - measured) / *sigma;
        }
        for (tail, &x) in tail[..b4].iter_mut().zip(&x[..b4]) {
            *tail = upper_tail(x.abs());
        }
        let bound = |j: usize| Boundary { w: w[j], sigma: sigma[j], x: x[j], tail: tail[j] };
        // Each interval from the last one's far boundary to its own, the first from its own near
        // one; then the gaps and the intervals too short for the tails again, from their own near
        // boundaries, as `over` takes them.
        let density = &mut density[start..];
        let pairs = (w.iter().zip(&w[1..]), x.iter().zip(&x[1..]), tail.iter().zip(&tail[1..]));
        for (d, ((w, x), tail)) in density.iter_mut().zip(pairs.0.zip(pairs.1).zip(pairs.2)) {
            let a = Boundary { w: *w.0, sigma: 0.0, x: *x.0, tail: *tail.0 };
            let b = Boundary { w: *w.1, sigma: 0.0, x: *x.1, tail: *tail.1 };
            *d = mass_density(&a, &b);
        }
        // (Where an interval is neither, `density` gives what the loop gave, far off or not. The
        // intervals to patch are marked in a loop of their own and found eight marks at a time:
        // a branch per interval cost more than the densities' loop.)
        if marks.len() < m {
            marks.resize(m, 0);
        }
        let marks = &mut marks[..m];
        let tiny = |(wa, wb): (&f64, &f64), (sa, sb): (&f64, &f64)| u8::from(wb - wa <= 1e-3 * sa.min(*sb));
        marks[0] = tiny((&w[0], &w[1]), (&sigma[0], &sigma[1]));
        let (gaps, fields) =
            (z0[1..].iter().zip(&z1[..m - 1]), w[1..].iter().zip(&w[2..]).zip(sigma[1..].iter().zip(&sigma[2..])));
        for (mark, ((z0, z1), (w, sigma))) in marks[1..].iter_mut().zip(gaps.zip(fields)) {
            *mark = u8::from(z0 != z1) | tiny(w, sigma);
        }
        for (c, word) in marks.chunks(8).enumerate() {
            if word.iter().all(|&m| m == 0) {
                continue;
            }
            for j in (8 * c..).zip(word).filter(|(_, m)| **m != 0).map(|(j, _)| j) {
                let gap = j > 0 && z0[j] != z1[j - 1];
                let mut a = if gap { self.boundary(z0[j]) } else { bound(j) };
                density[j] = self.density(&mut a, &mut bound(j + 1));
            }
        }
        self.last = Some((z1[m - 1], bound(m)));
        out.density.truncate(n);
        start
    }

    /// The density between boundaries `a` and `b` (see [`RayLikelihood::over`]).
    #[inline]
    fn density(&self, a: &mut Boundary, b: &mut Boundary) -> f64 {
        if a.x > TAIL_CUTOFF || b.x < -TAIL_CUTOFF {
            // Over `cutoff` std away: zero next to any voxel near the surface.
            0.0
        } else if b.w - a.w > 1e-3 * a.sigma.min(b.sigma) {
            // P(x_a < X < x_b) from the smaller tails, so far-tail intervals keep precision.
            // (`mass_density`'s arithmetic, with the tails computed when first needed: calling
            // it from here instead made an MRF build 1.035x slower, measured.)
            let mass = if a.x >= 0.0 {
                a.tail() - b.tail()
            } else if b.x <= 0.0 {
                b.tail() - a.tail()
            } else {
                1.0 - a.tail() - b.tail()
            };
            mass.max(0.0) / (b.w - a.w)
        } else {
            let sigma = 0.5 * (a.sigma + b.sigma);
            let d = (self.measured - 0.5 * (a.w + b.w)) / sigma;
            (-0.5 * d * d).exp() / (sigma * (2.0 * std::f64::consts::PI).sqrt())
        }
    }
}

/// The density between boundaries `a` and `b` whose tails are known and that lie at least
/// `1e-3` std apart (the first case of [`RayLikelihood::density`], its arithmetic alike).
#[inline(always)]
fn mass_density(a: &Boundary, b: &Boundary) -> f64 {
    let mass = if a.x >= 0.0 {
        a.tail - b.tail
    } else if b.x <= 0.0 {
        b.tail - a.tail
    } else {
        1.0 - a.tail - b.tail
    };
    let far_off = a.x > TAIL_CUTOFF || b.x < -TAIL_CUTOFF;
    if far_off { 0.0 } else { mass.max(0.0) / (b.w - a.w) }
}

/// From here on [`upper_tail`] reads as 0 (the tail is below 6.2e-16).
const TAIL_END: f64 = 8.0;

/// The Mills ratio `P(X > x) / phi(x)` on `[0, TAIL_END]` as `P(x) / R(x)`, ascending
/// coefficients: a rational least-squares fit of degree 5 over 6 on 4,000 Chebyshev nodes,
/// relative error below 1.6e-11 on a grid 4e-5 fine (`bench/fit_upper_tail.py` makes and checks
/// it). `R` has no root there (its coefficients are positive).
const MILLS_P: [f64; 6] = [
    1.253_314_137_315_500_1, // sqrt(pi / 2): the tail at 0 is 1/2
    1.216_096_365_511_366_8,
    0.579_310_782_089_957_9,
    0.158_444_491_653_661_45,
    0.024_703_606_600_926_5,
    0.001_776_325_449_371_598,
];
const MILLS_R: [f64; 7] = [
    1.0,
    1.768_189_074_268_394_8,
    1.373_033_913_053_833,
    0.603_809_804_261_958_3,
    0.160_235_013_963_100_3,
    0.024_702_997_732_531_536,
    0.001_776_337_546_417_834_6,
];

/// `P(X > x)` for a standard normal `X` and `x >= 0`: `phi(x)` times the Mills ratio, a
/// rational function (`MILLS_P` / `MILLS_R`), relative error below 1.6e-11 (the exponential's 2e-14
/// included; tested against `erfc` and by integration). No table and no branch, so that a
/// loop of them vectorises: a tabulated cubic before it cost 45 instructions a boundary, the
/// largest single part of an MRF tile trace.
#[inline(always)] // (so that the AVX2 copy of a tile trace has it in four lanes)
pub fn upper_tail(x: f64) -> f64 {
    let horner = |c: &[f64]| c.iter().rev().fold(0.0, |acc, &c| acc * x + c);
    let (p, r) = (horner(&MILLS_P), horner(&MILLS_R));
    let phi =
        crate::vecmath::exp(-0.5 * x * x) * (0.5 * std::f64::consts::FRAC_2_SQRT_PI * std::f64::consts::FRAC_1_SQRT_2);
    if x < TAIL_END { phi * p / r } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn patchy() -> NoiseModel {
        let n = 4;
        NoiseModel {
            bias: Poly([0.0, 0.0, 0.0]),
            std: Poly([0.01, 0.0, 0.0]),
            patches: Some(PatchModel {
                size: 20,
                rows: 2,
                cols: 2,
                bias: (0..n).map(|i| Poly([i as f64 * 0.001, 0.0, 0.0])).collect(),
                std: (0..n).map(|i| Poly([0.002, i as f64 * 0.001, -1.0])).collect(),
            }),
            likelihood_scale: 2.5,
        }
    }

    /// A widened likelihood is the likelihood of a model with that much larger std, while
    /// `bias_std` (where rays end) keeps the fitted std; bad scales are refused.
    #[test]
    fn likelihood_scale_widens_only_the_likelihood() {
        let text = "bias = [0.01]\nstd = [0.05]\nlikelihood_scale = 3.0\n";
        let wide = NoiseModel::from_toml(text, Path::new("n.toml")).unwrap();
        let plain = NoiseModel::aggregate(Poly([0.01, 0.0, 0.0]), Poly([0.15, 0.0, 0.0]));
        assert_eq!(wide.bias_std(3, 4, 2.0), (0.01, 0.05));
        for (z0, z1) in [(1.5, 1.52), (1.9, 1.92), (2.2, 2.3), (2.6, 2.61)] {
            let (a, b) = (wide.likelihood_over(3, 4, z0, z1, 2.0), plain.likelihood_over(3, 4, z0, z1, 2.0));
            assert!((a - b).abs() <= 1e-12 * b.max(1e-300), "{z0}-{z1}: {a} vs {b}");
        }
        for bad in ["0.0", "-1.0", "1000.0", "nan"] {
            let e = NoiseModel::from_toml(
                &format!("bias = [0.0]\nstd = [0.01]\nlikelihood_scale = {bad}\n"),
                Path::new("n.toml"),
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains("n.toml") && e.contains("likelihood_scale"), "{e}");
        }
    }

    #[test]
    fn toml_round_trip_and_patch_lookup() {
        let m = patchy();
        let back = NoiseModel::from_toml(&m.to_toml(), Path::new("x.toml")).unwrap();
        assert_eq!(back, m);
        assert_eq!(m.bias_std(25, 5, 1.0).0, 0.001); // row 0, col 1
        assert_eq!(m.bias_std(5, 25, 1.0).0, 0.002); // row 1, col 0
        assert_eq!(m.bias_std(0, 0, 1.0).1, STD_FLOOR, "negative std is floored");
        let cam = Camera::new(1.0, 1.0, 0.0, 0.0, 40, 40, 1.0).unwrap();
        assert!(m.check_camera(&cam).is_ok());
        let cam = Camera::new(1.0, 1.0, 0.0, 0.0, 64, 40, 1.0).unwrap();
        assert!(m.check_camera(&cam).is_err());
    }

    /// Reference for [`upper_tail`]: the complementary error function, fractional error below
    /// 1.2e-7 everywhere (Chebyshev fit of Numerical Recipes' `erfcc`).
    fn erfc(x: f64) -> f64 {
        let z = x.abs();
        let t = 1.0 / (1.0 + 0.5 * z);
        let poly = -z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
        let r = t * poly.exp();
        if x >= 0.0 { r } else { 2.0 - r }
    }

    #[test]
    fn upper_tail_against_erfc() {
        assert!((upper_tail(0.0) - 0.5).abs() < 1e-14);
        // Against `erfc` above, itself good to 1.2e-7 relative (the bound the fit must meet here).
        for i in 0..4000 {
            let x = i as f64 * 0.002 + 0.000_37;
            let e = 0.5 * erfc(x / std::f64::consts::SQRT_2);
            assert!((upper_tail(x) - e).abs() <= 1.3e-7 * e + 1e-12, "x = {x}: {} vs {e}", upper_tail(x));
        }
        assert_eq!(upper_tail(8.5), 0.0);
        assert!((upper_tail(7.999) - 6.25e-16).abs() < 2e-17, "{}", upper_tail(7.999));
        // Against phi integrated to 12 (Simpson, 24,000 steps: far finer than the fit), in
        // relative error, far tail included.
        for i in 0..47 {
            let x = i as f64 * 0.17 + 0.003;
            let phi = |t: f64| (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
            let n = 24_000;
            let h = (12.0 - x) / n as f64;
            let sum: f64 = (0..=n).map(|j| [2.0, 4.0][j % 2] * phi(x + j as f64 * h)).sum::<f64>() - phi(x) - phi(12.0);
            let want = sum * h / 3.0;
            assert!((upper_tail(x) - want).abs() <= 1.6e-11 * want, "x = {x}: {} vs {want}", upper_tail(x));
        }
    }

    #[test]
    fn interval_probabilities_against_numerical_integration() {
        // Unit std, no bias, measured 0: the standardised boundaries are the z-depths.
        let m = NoiseModel::aggregate(Poly([0.0; 3]), Poly([1.0, 0.0, 0.0]));
        for (a, b) in [(-1.0, 1.0), (0.5, 2.0), (-3.0, -0.2), (4.0, 5.0), (-6.0, 6.0), (5.5, 5.9)] {
            let n = 200_000;
            let h = (b - a) / n as f64;
            let integral: f64 = (0..n)
                .map(|i| {
                    let x = a + (i as f64 + 0.5) * h;
                    (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt() * h
                })
                .sum();
            let got = m.likelihood_over(0, 0, a, b, 0.0) * (b - a);
            assert!((got - integral).abs() <= 1e-9 * integral.max(1e-300) + 1e-12, "[{a}, {b}]: {got} vs {integral}");
        }
    }

    /// Walking a ray gives each voxel exactly what evaluating it alone gives, and the
    /// probabilities of consecutive voxels add up to that of their union.
    #[test]
    fn walking_a_ray_shares_boundaries_exactly() {
        let m = NoiseModel::aggregate(Poly([0.01, 0.0, -0.004]), Poly([0.002, 0.0, 0.0035]));
        let measured = 2.5;
        let mut walk = m.along_ray(0, 0, measured);
        let (mut z, step) = (2.3, 0.0137);
        let mut total = 0.0;
        while z < 2.75 {
            let alone = m.likelihood_over(0, 0, z, z + step, measured);
            assert_eq!(walk.over(z, z + step), alone, "voxel at {z}");
            let w = |z: f64| z + 0.01 - 0.004 * z * z;
            total += alone * (w(z + step) - w(z));
            z += step;
        }
        let union = m.likelihood_over(0, 0, 2.3, z, measured);
        let (w0, w1) = (2.3 + 0.01 - 0.004 * 2.3 * 2.3, z + 0.01 - 0.004 * z * z);
        assert!((total - union * (w1 - w0)).abs() < 1e-9, "{total} vs {}", union * (w1 - w0));
        assert!(total > 0.999, "nearly all the mass lies within the walk: {total}");
    }

    /// The batched walk gives every interval exactly what `over` gives it, bit for bit: with
    /// gaps between intervals (voxels a ray skips), intervals too short for the tails, whole
    /// rays in front of the reading, and across rays sharing the buffers.
    #[test]
    fn batched_intervals_equal_the_walk_bit_for_bit() {
        let mut rng = crate::random::Rng::new(17);
        let mut out = Intervals::default();
        let (mut gaps, mut tiny) = (0, 0);
        for trial in 0..400 {
            let bias = Poly([rng.range(-0.05, 0.05), rng.range(-0.03, 0.03), rng.range(-0.02, 0.04)]);
            let std = Poly([rng.range(0.001, 0.03), rng.range(0.0, 0.01), rng.range(0.0, 0.01)]);
            let mut m = NoiseModel::aggregate(bias, std);
            m.likelihood_scale = [1.0, 2.0, 0.5][trial % 3];
            let measured = rng.range(0.3, 6.0);
            let (mut z0, mut z1) = (Vec::new(), Vec::new());
            let mut z = rng.range(0.0, if trial % 10 == 0 { 0.1 } else { measured });
            let end = [measured + 0.5, measured * 0.5][usize::from(trial % 10 == 0)];
            while z < end {
                let width = if rng.uniform() < 0.1 { rng.range(0.0, 1e-6) } else { rng.range(0.001, 0.05) };
                tiny += usize::from(width < 1e-6);
                z0.push(z);
                z1.push(z + width);
                z += width;
                if rng.uniform() < 0.05 {
                    z += rng.range(0.01, 0.2);
                    gaps += 1;
                }
            }
            let mut walk = m.along_ray(0, 0, measured);
            let want: Vec<u64> = z0.iter().zip(&z1).map(|(&a, &b)| walk.over(a, b).to_bits()).collect();
            let mut batch = m.along_ray(0, 0, measured);
            batch.over_each(&z0, &z1, &mut out);
            let got: Vec<u64> = out.density.iter().map(|d| d.to_bits()).collect();
            assert_eq!(got, want, "trial {trial}");
            // And the walk carries on from the batch's last boundary alike.
            assert_eq!(batch.over(z, z + 0.01).to_bits(), walk.over(z, z + 0.01).to_bits(), "trial {trial}");
        }
        assert!(gaps > 100 && tiny > 100, "{gaps} gaps, {tiny} tiny intervals");
    }

    /// The stretch `over` skips in front of a reading gives exactly what evaluating it would
    /// (0), for quadratic bias and std of either curvature, and `Poly::max_on` bounds each
    /// polynomial on a dense sampling of its interval.
    #[test]
    fn skipping_the_stretch_before_a_reading_changes_nothing() {
        let mut rng = crate::random::Rng::new(11);
        let mut skipped = 0;
        for trial in 0..300 {
            let poly = |rng: &mut crate::random::Rng, scale: f64| {
                Poly([rng.range(-1.0, 1.0) * scale, rng.range(-1.0, 1.0) * scale, rng.range(-1.0, 1.0) * scale])
            };
            let bias = poly(&mut rng, 0.05);
            let std = Poly([rng.range(0.001, 0.05), rng.range(-0.01, 0.01), rng.range(-0.01, 0.01)]);
            let mut m = NoiseModel::aggregate(bias, std);
            m.likelihood_scale = [1.0, 3.0, 0.5][trial % 3];
            let measured = rng.range(0.3, 6.0);
            for p in [&bias, &std] {
                let top = p.max_on(0.0, measured);
                assert!((0..=1000).all(|i| p.eval(measured * i as f64 / 1000.0) <= top + 1e-12), "trial {trial}");
            }
            let mut fast = m.along_ray(0, 0, measured);
            let mut full = RayLikelihood { zero_before: f64::NEG_INFINITY, ..m.along_ray(0, 0, measured) };
            let step = rng.range(0.005, 0.05);
            let mut z = 0.0;
            while z < measured + 1.0 {
                skipped += usize::from(z + step < fast.zero_before);
                assert_eq!(fast.over(z, z + step).to_bits(), full.over(z, z + step).to_bits(), "trial {trial}, z {z}");
                z += step;
            }
        }
        assert!(skipped > 10_000, "the shortcut was taken ({skipped} intervals)");
    }

    #[test]
    fn errors_name_file_and_problem() {
        let p = Path::new("noise.toml");
        let e = NoiseModel::from_toml("bias = [0.0]\nstd = [0.1]\nwobble = 1\n", p).unwrap_err().to_string();
        assert!(e.contains("noise.toml") && e.contains("wobble"), "{e}");
        let e = NoiseModel::from_toml("bias = [0.0, 1, 2, 3]\nstd = [0.1]\n", p).unwrap_err().to_string();
        assert!(e.contains("1 to 3 coefficients"), "{e}");
        let bad =
            "bias = [0.0]\nstd = [0.1]\n[patches]\nsize = 20\nrows = 2\ncols = 2\nbias = [[0.0]]\nstd = [[0.1]]\n";
        let e = NoiseModel::from_toml(bad, p).unwrap_err().to_string();
        assert!(e.contains("rows * cols = 4"), "{e}");
    }
}
