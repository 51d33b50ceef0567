//! Depth-camera noise simulation: a clean (rendered) depth image in, what a real sensor would
//! have read out. `mrfmap add-noise` turns a noise-free dataset into a noisy one with it, so
//! users of a renderer (Gazebo, Isaac, ICL-NUIM) get realistic input and keep the clean depth
//! to score against.
//!
//! Two kinds of noise ([`DepthNoise`]):
//! - [`StructuredLight`]: a Kinect-style structured-light sensor, the kind of model Augmented
//!   ICL-NUIM's noisy depth was made with (Handa et al., ICRA 2014, after Barron & Malik, CVPR
//!   2013; Choi, Zhou & Koltun, CVPR 2015 add a fixed low-frequency distortion after Teichman et
//!   al., RSS 2013). Noise lives in disparity `d = f b / z`, not in depth: a jittered lookup (the
//!   dot pattern's lateral error), a fixed smooth distortion field of the sensor, white noise,
//!   quantisation to 1/8 pixel, then holes where the projector cannot reach (shadows behind depth
//!   edges), at grazing angles and in the border the correlation window never covers.
//! - a forward [`NoiseModel`] (`noise.toml`): Gaussian in depth with polynomial bias and std,
//!   per patch or aggregate ([`NoiseModel::sample`]); what `mrfmap calibrate` fits.
//!
//! [`noise_statistics`] summarises noisy against clean depth (median and MAD of the error, its
//! 95th percentile, lost pixels, distinct depth levels): how the simulator is checked against
//! the published noisy ICL-NUIM frames (docs/ALGORITHMS.md section 3.1).

use crate::frames::{Camera, DepthImage, NoiseModel, Poly};
use crate::random::Rng;

/// Image width and height the pixel-valued parameters of [`StructuredLight`] are given at;
/// other image sizes scale them.
const NATIVE: (f64, f64) = (640.0, 480.0);

/// Random Fourier features of the distortion field: enough that the field is Gaussian to the
/// eye and its covariance within a few percent of the kernel's.
const FIELD_FEATURES: usize = 64;

/// Stream tag of the sensor's fixed distortion field, apart from every view's stream.
const FIELD_STREAM: u64 = u64::MAX;

/// A Kinect-style structured-light depth sensor (see the module docs). Pixel-valued
/// parameters are at 640x480 and scale with the image.
#[derive(Clone, Debug, PartialEq)]
pub struct StructuredLight {
    /// Projector-camera baseline (m); disparity in pixels is `fx * baseline / z`, and the
    /// projector sits on the camera's +x side.
    pub baseline: f64,
    /// Disparity steps per pixel: the sensor reports disparity quantised to `1 / subpixel` px.
    pub subpixel: f64,
    /// Std (px) of the per-pixel lateral jitter of where depth is looked up.
    pub shift_std: f64,
    /// Std (px) of white disparity noise, drawn per pixel and frame.
    pub white_std: f64,
    /// Std (px) of the sensor's fixed, smooth disparity distortion (the same in every frame).
    pub distortion_std: f64,
    /// Correlation length (px) of that distortion (squared-exponential kernel).
    pub distortion_length: f64,
    /// Constant disparity offset (px); negative reads surfaces farther.
    pub disparity_offset: f64,
    /// Pixels with no depth at the left, right, top and bottom edges.
    pub border: [u32; 4],
    /// Surfaces seen at a smaller |cos| of the incidence angle return nothing (0 disables).
    pub grazing_min_cos: f64,
    /// Pixels the projector cannot see (behind a nearer surface from its side) return nothing.
    pub shadows: bool,
}

impl StructuredLight {
    /// The sensor of Augmented ICL-NUIM's published noisy depth, measured on its frames 0-4 of
    /// livingroom1 against their clean depth (docs/ALGORITHMS.md section 3.1 says how):
    /// depth levels at `35.13 / (k / 8)` m (f b = 35.13 px m, Handa et al.'s constant 35130 at
    /// fx = 525, so `baseline` = 0.0669 m), disparity error = a fixed field of std 0.11 px and
    /// correlation length 40 px plus 0.05 px white noise, -0.03 px offset, lateral jitter 0.5 px
    /// (Handa et al.), an 8 / 32 / 12 / 12 px border, no return below cos 0.1 (measured hole rate
    /// above 0.9 there). No projector shadows: the published frames have none (0.4% of their
    /// interior pixels are lost, none beside depth edges); a real Kinect has them
    /// ([`StructuredLight::shadows`], `add-noise --shadows`).
    pub fn kinect() -> Self {
        StructuredLight {
            baseline: 35.13 / 525.0,
            subpixel: 8.0,
            shift_std: 0.5,
            white_std: 0.05,
            distortion_std: 0.11,
            distortion_length: 40.0,
            disparity_offset: -0.027,
            border: [8, 32, 12, 12],
            grazing_min_cos: 0.1,
            shadows: false,
        }
    }

    /// The forward model of this sensor in depth, for the engines: a disparity error of std `s`
    /// px is `z^2 s / (f b)` m in depth, so std and bias are quadratics in `z` (quantisation
    /// counted as a uniform step's std; jitter and holes are not a Gaussian and are left out).
    pub fn forward_model(&self, camera: &Camera) -> NoiseModel {
        let fb = camera.fx * self.baseline;
        let step = 1.0 / self.subpixel;
        let s = (self.white_std.powi(2) + self.distortion_std.powi(2) + step * step / 12.0).sqrt();
        NoiseModel::aggregate(Poly([0.0, 0.0, -self.disparity_offset / fb]), Poly([0.0, 0.0, s / fb]))
    }

    /// A noisy reading of `clean` (z-depths, 0 = none) seen by this sensor on `camera`.
    /// The distortion field depends on `seed` only (it is the sensor's); jitter and white noise
    /// on `(seed, view)`. Deterministic whatever the thread count.
    pub fn apply(&self, clean: &DepthImage, camera: &Camera, seed: u64, view: u64) -> DepthImage {
        use rayon::prelude::*;
        let (w, h) = (clean.width(), clean.height());
        let scale = ((f64::from(w) / NATIVE.0), (f64::from(h) / NATIVE.1));
        let fb = camera.fx * self.baseline;
        let lost = self.lost(clean, camera, fb);
        let field = Field::new(seed, (w, h), self.distortion_std, self.distortion_length * scale.0);
        let px = |n: u32, s: f64| (f64::from(n) * s).round() as u32;
        let [left, right, top, bottom] = self.border;
        let (left, right, top, bottom) = (px(left, scale.0), px(right, scale.0), px(top, scale.1), px(bottom, scale.1));
        let inside = |u: u32, v: u32| u >= left && u + right < w && v >= top && v + bottom < h;
        let mut data = vec![0f32; clean.data().len()];
        data.par_chunks_mut(w as usize).enumerate().for_each(|(v, row)| {
            let v = v as u32;
            let mut rng = Rng::stream(seed, view, u64::from(v));
            let distortion = field.row(v);
            for (u, out) in row.iter_mut().enumerate() {
                // Drawn for every pixel so the streams do not depend on the scene.
                let (du, dv, n) = (rng.normal(), rng.normal(), rng.normal());
                let u = u as u32;
                if !inside(u, v) {
                    continue;
                }
                let su = (f64::from(u) + du * self.shift_std).round();
                let sv = (f64::from(v) + dv * self.shift_std).round();
                if su < 0.0 || sv < 0.0 || su >= f64::from(w) || sv >= f64::from(h) {
                    continue;
                }
                let (su, sv) = (su as u32, sv as u32);
                let Some(z) = clean.get(su, sv) else { continue };
                if lost[(sv * w + su) as usize] {
                    continue;
                }
                let d = fb / f64::from(z) + self.disparity_offset + distortion[u as usize] + self.white_std * n;
                let quantised = (d * self.subpixel).round() / self.subpixel;
                if quantised > 0.0 {
                    *out = (fb / quantised) as f32;
                }
            }
        });
        DepthImage::from_vec(w, h, data).expect("sized from the input")
    }

    /// Pixels of `clean` that return nothing whatever the noise: in the projector's shadow or
    /// seen at a grazing angle.
    fn lost(&self, clean: &DepthImage, camera: &Camera, fb: f64) -> Vec<bool> {
        let (w, h) = (clean.width(), clean.height());
        let mut lost = vec![false; (w * h) as usize];
        for v in 0..h {
            let row = clean.row(v);
            let lost = &mut lost[(v * w) as usize..((v + 1) * w) as usize];
            if self.shadows {
                // The projector, `baseline` to the camera's right, sees pixel u at projector column
                // u - d(u). Scanning from the right, a pixel whose projector column lies beyond
                // one already seen further right is behind that (nearer) surface for the projector.
                // The half-pixel margin keeps depth rounding on a smooth surface from casting any.
                let mut nearest = f64::INFINITY;
                for u in (0..w as usize).rev() {
                    if row[u] > 0.0 {
                        let p = u as f64 - fb / f64::from(row[u]);
                        lost[u] |= p > nearest + 0.5;
                        nearest = nearest.min(p);
                    }
                }
            }
            if self.grazing_min_cos > 0.0 && v > 0 && v + 1 < h {
                for u in 1..w - 1 {
                    lost[u as usize] |= incidence_cos(clean, camera, u, v).is_some_and(|c| c < self.grazing_min_cos);
                }
            }
        }
        lost
    }
}

/// |cos| of the angle between the viewing ray of pixel `(u, v)` and the surface normal there,
/// from central differences of the back-projected depth; `None` where a neighbour has no depth
/// or the depth is not locally planar (an edge, not a slanted surface).
fn incidence_cos(depth: &DepthImage, camera: &Camera, u: u32, v: u32) -> Option<f64> {
    let point = |u: u32, v: u32| {
        let z = f64::from(depth.get(u, v)?);
        Some(camera.pixel_ray(f64::from(u), f64::from(v)) * z)
    };
    let c = point(u, v)?;
    let (l, r, t, b) = (point(u - 1, v)?, point(u + 1, v)?, point(u, v - 1)?, point(u, v + 1)?);
    // On a plane inverse depth is affine in the pixel coordinates, however slanted the plane, so
    // its second difference vanishes; across an edge it is as large as the first differences.
    // The floor on the tolerance covers depths stored to the millimetre.
    let curved = |a: f64, b: f64| {
        let (ia, ic, ib) = (1.0 / a, 1.0 / c.z, 1.0 / b);
        (ia + ib - 2.0 * ic).abs() > 0.25 * ((ib - ic).abs() + (ic - ia).abs()) + 2e-3 * ic
    };
    if curved(l.z, r.z) || curved(t.z, b.z) {
        return None;
    }
    let normal = (r - l).cross(&(b - t));
    let n = normal.norm() * c.norm();
    (n > 0.0).then(|| (normal.dot(&c) / n).abs())
}

/// A smooth Gaussian field over the image (random Fourier features of a squared-exponential
/// kernel): `std * sqrt(2/K) * sum_k cos(a_k u + b_k v + phi_k)`, with frequencies
/// `N(0, 1/length^2)` per axis, less its mean over the image. One image holds only a few
/// dozen correlation lengths, so a draw's mean would move the whole image by a sizeable part of
/// `std`; the sensor's mean is [`StructuredLight::disparity_offset`]'s to set. Separable:
/// per-column cosines and sines are kept, a row combines them with its own.
struct Field {
    std: f64,
    /// The raw field's mean over the image, subtracted.
    mean: f64,
    /// Per feature: `cos(a_k u)` and `sin(a_k u)` for every column.
    columns: Vec<(Vec<f64>, Vec<f64>)>,
    /// Per feature: `(b_k, phi_k)`.
    rows: Vec<(f64, f64)>,
}

impl Field {
    fn new(seed: u64, (width, height): (u32, u32), std: f64, length: f64) -> Self {
        let mut rng = Rng::stream(seed, FIELD_STREAM, 0);
        let mut columns = Vec::with_capacity(FIELD_FEATURES);
        let mut rows = Vec::with_capacity(FIELD_FEATURES);
        let mut sum = 0.0;
        for _ in 0..FIELD_FEATURES {
            let a = rng.normal() / length;
            let b = rng.normal() / length;
            let phi = rng.range(0.0, std::f64::consts::TAU);
            let (s, c): (Vec<f64>, Vec<f64>) = (0..width).map(|u| (a * f64::from(u)).sin_cos()).unzip();
            // sum over u, v of cos(A_u + B_v) = (sum cos A)(sum cos B) - (sum sin A)(sum sin B).
            let (sin_b, cos_b) = (0..height)
                .map(|v| (b * f64::from(v) + phi).sin_cos())
                .fold((0.0, 0.0), |(s0, c0), (s1, c1)| (s0 + s1, c0 + c1));
            sum += c.iter().sum::<f64>() * cos_b - s.iter().sum::<f64>() * sin_b;
            columns.push((c, s));
            rows.push((b, phi));
        }
        let gain = std * (2.0 / FIELD_FEATURES as f64).sqrt();
        let mean = gain * sum / (f64::from(width) * f64::from(height));
        Field { std, mean, columns, rows }
    }

    /// The field along row `v`.
    fn row(&self, v: u32) -> Vec<f64> {
        let width = self.columns.first().map_or(0, |c| c.0.len());
        let mut out = vec![-self.mean; width];
        if self.std == 0.0 {
            return out;
        }
        let gain = self.std * (2.0 / FIELD_FEATURES as f64).sqrt();
        for ((cos_a, sin_a), &(b, phi)) in self.columns.iter().zip(&self.rows) {
            // cos(A + B) = cos A cos B - sin A sin B, with B = b v + phi.
            let (sin_b, cos_b) = (b * f64::from(v) + phi).sin_cos();
            for ((o, ca), sa) in out.iter_mut().zip(cos_a).zip(sin_a) {
                *o += gain * (ca * cos_b - sa * sin_b);
            }
        }
        out
    }
}

/// How `mrfmap add-noise` makes depth noisy.
#[derive(Clone, Debug, PartialEq)]
pub enum DepthNoise {
    /// A structured-light sensor simulated in disparity.
    StructuredLight(StructuredLight),
    /// Gaussian noise in depth from a forward model (`noise.toml`).
    Model(NoiseModel),
}

impl DepthNoise {
    /// A noisy reading of `clean` as frame `view` of this sensor, deterministic in
    /// `(seed, view)`.
    pub fn apply(&self, clean: &DepthImage, camera: &Camera, seed: u64, view: u64) -> DepthImage {
        match self {
            DepthNoise::StructuredLight(s) => s.apply(clean, camera, seed, view),
            DepthNoise::Model(m) => m.sample(clean, seed, view),
        }
    }

    /// The forward model the engines should map this noise with.
    pub fn forward_model(&self, camera: &Camera) -> NoiseModel {
        match self {
            DepthNoise::StructuredLight(s) => s.forward_model(camera),
            DepthNoise::Model(m) => m.clone(),
        }
    }
}

/// Noisy depth summarised against clean depth of the same view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseStatistics {
    /// Median of noisy - clean (m) over pixels valid in both. Stored depths are whole steps of
    /// `1 / depth_scale` (millimetres), so errors are too and a plain median could only move by
    /// a whole step; this is the grouped-data median, interpolated within its step.
    pub median: f64,
    /// Median absolute deviation of noisy - clean about its median (m).
    pub mad: f64,
    /// 95th percentile of |noisy - clean| (m).
    pub p95_abs: f64,
    /// Share of the clean image's valid pixels that have no depth in the noisy one.
    pub lost: f64,
    /// Distinct stored depth values (`round(z * depth_scale)`) in the noisy image.
    pub levels: usize,
    /// Pixels valid in both images.
    pub compared: usize,
}

/// [`NoiseStatistics`] of `noisy` against `clean` (same size); `None` when no pixel is valid in
/// both.
pub fn noise_statistics(noisy: &DepthImage, clean: &DepthImage, depth_scale: f64) -> Option<NoiseStatistics> {
    assert_eq!((noisy.width(), noisy.height()), (clean.width(), clean.height()), "images of one view");
    let mut errors = Vec::new();
    let mut clean_valid = 0usize;
    let mut lost = 0usize;
    let mut levels = Vec::new();
    for (&n, &c) in noisy.data().iter().zip(clean.data()) {
        if n > 0.0 {
            levels.push((f64::from(n) * depth_scale).round() as i64);
        }
        if c > 0.0 {
            clean_valid += 1;
            if n > 0.0 {
                errors.push(f64::from(n) - f64::from(c));
            } else {
                lost += 1;
            }
        }
    }
    if errors.is_empty() {
        return None;
    }
    levels.sort_unstable();
    levels.dedup();
    let median = grouped_median(&mut errors, 1.0 / depth_scale);
    let mut deviations: Vec<f64> = errors.iter().map(|e| (e - median).abs()).collect();
    let mut magnitudes: Vec<f64> = errors.iter().map(|e| e.abs()).collect();
    Some(NoiseStatistics {
        median,
        mad: quantile(&mut deviations, 0.5),
        p95_abs: quantile(&mut magnitudes, 0.95),
        lost: lost as f64 / clean_valid as f64,
        levels: levels.len(),
        compared: errors.len(),
    })
}

/// The median of `values` read as whole steps of `step`: the step holding the middle value,
/// entered in proportion to how far into its count the middle falls (reorders `values`).
fn grouped_median(values: &mut [f64], step: f64) -> f64 {
    let middle = quantile(values, 0.5);
    let bin = (middle / step).round();
    let (lo, hi) = ((bin - 0.5) * step, (bin + 0.5) * step);
    let below = values.iter().filter(|&&e| e < lo).count() as f64;
    let inside = values.iter().filter(|&&e| e >= lo && e < hi).count() as f64;
    if inside == 0.0 {
        return middle;
    }
    lo + (0.5 * values.len() as f64 - below) / inside * step
}

/// The `q` quantile of `values` (the element at rank `round(q (n - 1))`; reorders them).
fn quantile(values: &mut [f64], q: f64) -> f64 {
    let k = (q * (values.len() - 1) as f64).round() as usize;
    *values.select_nth_unstable_by(k, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(w: u32, h: u32) -> Camera {
        Camera::new(
            525.0 * f64::from(w) / 640.0,
            525.0 * f64::from(w) / 640.0,
            f64::from(w) / 2.0,
            f64::from(h) / 2.0,
            w,
            h,
            1000.0,
        )
        .unwrap()
    }

    /// A fronto-parallel wall at `z` over the whole image.
    fn wall(w: u32, h: u32, z: f32) -> DepthImage {
        DepthImage::from_vec(w, h, vec![z; (w * h) as usize]).unwrap()
    }

    /// Only white noise and quantisation: nothing moves a pixel or loses it.
    fn quiet() -> StructuredLight {
        StructuredLight {
            shift_std: 0.0,
            distortion_std: 0.0,
            border: [0; 4],
            grazing_min_cos: 0.0,
            ..StructuredLight::kinect()
        }
    }

    #[test]
    fn depths_are_quantised_in_disparity() {
        let cam = camera(160, 120);
        let fb = cam.fx * StructuredLight::kinect().baseline;
        let clean =
            DepthImage::from_vec(160, 120, (0..160 * 120).map(|i| 0.8 + (i % 997) as f32 * 0.003).collect()).unwrap();
        let noisy = StructuredLight::kinect().apply(&clean, &cam, 3, 0);
        let mut seen = 0;
        for &z in noisy.data().iter().filter(|&&z| z > 0.0) {
            let steps = fb / f64::from(z) * 8.0;
            assert!((steps - steps.round()).abs() < 1e-3, "{z} m is {steps} eighths of a pixel");
            seen += 1;
        }
        // A 0.003 m/px ramp is steep: where it is slanted beyond cos 0.1 it is lost.
        assert!(seen > 5_000, "{seen}");
    }

    #[test]
    fn seeded_and_independent_of_threads() {
        let cam = camera(96, 72);
        let clean = wall(96, 72, 2.0);
        let sensor = StructuredLight::kinect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| sensor.apply(&clean, &cam, 9, 4))
        };
        let one = run(1);
        assert_eq!(one, run(2));
        assert_ne!(one, sensor.apply(&clean, &cam, 9, 5), "another view draws other noise");
        assert_ne!(one, sensor.apply(&clean, &cam, 10, 4), "another sensor");
    }

    #[test]
    fn white_noise_and_quantisation_have_the_forward_models_moments() {
        // Disparity error = white N(0, s^2) plus rounding to 1/8 px (std 1/(8 sqrt 12)) plus the
        // offset; in depth that is `forward_model`'s quadratic bias and std.
        let (w, h, z) = (320, 240, 2.0);
        let cam = camera(w, h);
        let sensor = StructuredLight { white_std: 0.2, disparity_offset: -0.05, ..quiet() };
        let model = sensor.forward_model(&cam);
        let (bias, std) = model.bias_std(0, 0, z);
        let noisy = sensor.apply(&wall(w, h, z as f32), &cam, 1, 0);
        let e: Vec<f64> = noisy.data().iter().map(|&m| f64::from(m) - z).collect();
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        let sd = (e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / e.len() as f64).sqrt();
        // The mean against quadrature of E[f b / round_8(f b / z + offset + s N(0, 1))]: 1/d is
        // convex, so it sits a second-order `z (s/d)^2` above the quadratic model's bias.
        let d = cam.fx * sensor.baseline / z;
        let expected: f64 = (-8000..=8000)
            .map(|k| {
                let n = f64::from(k) * 1e-3;
                let q = ((d + sensor.disparity_offset + sensor.white_std * n) * 8.0).round() / 8.0;
                (-0.5 * n * n).exp() / std::f64::consts::TAU.sqrt() * 1e-3 * (d * z / q - z)
            })
            .sum();
        let standard_error = std / (e.len() as f64).sqrt();
        assert!((mean - expected).abs() < 4.0 * standard_error, "mean {mean} vs {expected}");
        assert!((mean - bias).abs() < 0.2 * bias, "mean {mean} vs model bias {bias}");
        assert!((sd - std).abs() < 0.05 * std, "std {sd} vs model std {std}");
    }

    #[test]
    fn projector_shadows_fall_left_of_a_nearer_surface() {
        // Wall at 2 m, a post at 1 m over columns 60..80: the projector (to the right) cannot
        // light the wall for f b (1/1 - 1/2) px left of the post.
        let (w, h) = (160, 8);
        let cam = camera(w, h);
        let mut clean = wall(w, h, 2.0);
        for v in 0..h {
            for u in 60..80 {
                clean.set(u, v, 1.0);
            }
        }
        let sensor = StructuredLight { shadows: true, white_std: 0.0, ..quiet() };
        let fb = cam.fx * sensor.baseline;
        let width = fb * (1.0 - 0.5);
        let noisy = sensor.apply(&clean, &cam, 0, 0);
        for u in 0..w {
            let shadowed = f64::from(u) >= 60.0 - width + 0.5 && u < 60;
            let near_edge = (f64::from(u) - (60.0 - width)).abs() < 1.0;
            if !near_edge {
                assert_eq!(noisy.get(u, 4).is_none(), shadowed, "column {u} (shadow {width:.1} px wide)");
            }
        }
        let unshadowed = StructuredLight { white_std: 0.0, ..quiet() }.apply(&clean, &cam, 0, 0);
        assert_eq!(unshadowed.valid_count(), (w * h) as usize);
    }

    #[test]
    fn grazing_surfaces_return_nothing() {
        // A floor plane seen from above at increasing slant: rows where the view ray meets it
        // at |cos| below 0.1 are lost, steeper ones kept.
        let (w, h) = (64, 240);
        let cam = Camera::new(525.0, 525.0, 32.0, 10.0, w, h, 1000.0).unwrap();
        let mut clean = DepthImage::new(w, h);
        // Plane y = 0.5 m below the camera (y down): depth along pixel v is 0.5 fy / (v - cy).
        for v in 0..h {
            let dy = f64::from(v) - cam.cy;
            if dy > 0.0 {
                for u in 0..w {
                    clean.set(u, v, (0.5 * cam.fy / dy) as f32);
                }
            }
        }
        let sensor = StructuredLight { grazing_min_cos: 0.1, white_std: 0.0, ..quiet() };
        let noisy = sensor.apply(&clean, &cam, 0, 0);
        let mut lost_rows = 0;
        for v in 2..h - 2 {
            let dy = f64::from(v) - cam.cy;
            if dy <= 1.0 {
                continue;
            }
            // At the central column the ray (0, dy, fy) meets the plane's normal (0, 1, 0).
            let cos = dy / (dy * dy + cam.fy * cam.fy).sqrt();
            let lost = noisy.get(w / 2, v).is_none();
            if (cos - 0.1).abs() > 0.01 {
                assert_eq!(lost, cos < 0.1, "row {v}: cos {cos:.3}");
            }
            lost_rows += usize::from(lost);
        }
        assert!(lost_rows > 10, "{lost_rows}");
    }

    #[test]
    fn border_scales_with_the_image() {
        for (w, h) in [(640, 480), (320, 240)] {
            let sensor = StructuredLight { white_std: 0.0, ..quiet() };
            let sensor = StructuredLight { border: StructuredLight::kinect().border, ..sensor };
            let noisy = sensor.apply(&wall(w, h, 1.5), &camera(w, h), 0, 0);
            let s = f64::from(w) / 640.0;
            let (l, r, t, b) = ((8.0 * s) as u32, (32.0 * s) as u32, (12.0 * s) as u32, (12.0 * s) as u32);
            assert_eq!(noisy.valid_count(), ((w - l - r) * (h - t - b)) as usize, "{w}x{h}");
            assert!(noisy.get(l, t).is_some() && noisy.get(l - 1, t).is_none() && noisy.get(w - r, t).is_none());
        }
    }

    #[test]
    fn distortion_field_has_its_std_and_length() {
        let (w, h, length) = (320, 240, 20.0);
        let (mut var, mut lag, mut n) = (0.0, 0.0, 0.0);
        for seed in 0..8 {
            let field = Field::new(seed, (w, h), 0.1, length);
            let rows: Vec<Vec<f64>> = (0..h).map(|v| field.row(v)).collect();
            let mean = rows.iter().flatten().sum::<f64>() / f64::from(w * h);
            assert!(mean.abs() < 1e-9, "mean over the image removed: {mean}");
            for row in &rows {
                for u in 0..(w as usize - length as usize) {
                    var += row[u] * row[u];
                    lag += row[u] * row[u + length as usize];
                    n += 1.0;
                }
            }
        }
        let (var, corr) = (var / n, lag / var);
        // Less than 0.01 in variance: the removed mean and a finite image take a little.
        assert!((var.sqrt() - 0.1).abs() < 0.02, "std {}", var.sqrt());
        // Squared-exponential kernel: correlation exp(-1/2) at one length.
        assert!((corr - (-0.5f64).exp()).abs() < 0.15, "correlation at one length {corr}");
        // The same seed is the same sensor.
        assert_eq!(Field::new(3, (w, h), 0.1, length).row(7), Field::new(3, (w, h), 0.1, length).row(7));
    }

    #[test]
    fn statistics_of_known_images() {
        let clean = DepthImage::from_vec(4, 2, vec![1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 0.0, 2.0]).unwrap();
        let noisy = DepthImage::from_vec(4, 2, vec![1.002, 1.002, 0.998, 0.0, 2.01, 2.002, 1.5, 2.002]).unwrap();
        let s = noise_statistics(&noisy, &clean, 1000.0).unwrap();
        assert_eq!(s.compared, 6);
        assert!((s.lost - 1.0 / 7.0).abs() < 1e-12);
        // Levels: 998, 1002, 1500, 2002, 2010 mm.
        assert_eq!(s.levels, 5);
        // Errors in mm: 2, 2, -2, 10, 2, 2: the middle (3 of 6) is the second of the 2 mm step's
        // four values, one below it: halfway into the step.
        assert!((s.median - 0.002).abs() < 1e-6, "{}", s.median);
        assert!((s.p95_abs - 0.01).abs() < 1e-6);
        assert!(noise_statistics(&DepthImage::new(4, 2), &clean, 1000.0).is_none());
    }
}
