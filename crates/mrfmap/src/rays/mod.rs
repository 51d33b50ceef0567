//! Rays: from a frame's pixels (or a scan's beams) to world-space rays, and from rays to the
//! voxels they cross.
//!
//! [`FrameRays`] turns each valid depth pixel into a [`PixelRay`] (origin, unit direction,
//! measured range, and the `cz` that converts range to z-depth for the noise model);
//! [`ScanRays`] does the same for the beams of a [`RangeScan`], and [`Rays`] is either, for
//! engines that take both.
//! [`RayLimits`] applies the user's max range and bounding box, and [`for_each_crossing`] walks the
//! voxels of the resulting segment. Every engine consumes rays through these three pieces.
//! For a whole depth image, [`Projector`] finds the same voxels as walking every ray,
//! by projecting boxes of voxels into the image instead (much less work when many rays cross
//! each voxel); the log-odds engine uses it.

mod frustum;
mod traversal;

pub use frustum::{CrossedVoxels, Projector};
pub use traversal::{Crossing, Walk, crossings, for_each_crossing};

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::frames::{Camera, DepthImage, Frame, NoiseModel, Pose, RangeScan, RayLikelihood};
use crate::map::{Aabb, box_keys, floor_i32_lanes};

/// A world-space ray through one valid depth pixel (or one beam of a range scan).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelRay {
    /// Pixel column (beam index for scans).
    pub u: u32,
    /// Pixel row (0 for scans).
    pub v: u32,
    /// Camera centre in the world frame.
    pub origin: [f64; 3],
    /// Unit direction in the world frame.
    pub dir: [f64; 3],
    /// Range (metres along `dir`) to the measured surface.
    pub range: f64,
    /// z component of the unit ray in the camera frame: z-depth = range * cz (1 for scans,
    /// whose noise model is in range).
    pub cz: f64,
    /// `false` for a scan beam with no return: `range` is then the sensor's maximum range,
    /// and the ray only says the space up to it is free.
    pub returned: bool,
}

/// Unit world direction of pixel `(u, v)` for a camera with rotation `rotation` (camera to
/// world), and the norm of its z = 1 camera ray: range = z-depth * norm.
#[inline]
pub fn pixel_direction(camera: &Camera, rotation: &Matrix3<f64>, u: u32, v: u32) -> ([f64; 3], f64) {
    let ray = camera.pixel_ray(u as f64, v as f64);
    let (unit, norm, _) = unit_ray(ray.x, ray.y);
    let d = rotation * unit;
    ([d.x, d.y, d.z], norm)
}

/// The unit ray along `(x, y, 1)`, the norm of `(x, y, 1)`, and its reciprocal. One division,
/// not three: [`CameraRays`] does this for every pixel.
#[inline]
fn unit_ray(x: f64, y: f64) -> (Vector3<f64>, f64, f64) {
    let norm = z1_norm(x, y * y);
    let inv = 1.0 / norm;
    (unit_along(x, y, inv), norm, inv)
}

/// The norm of `(x, y, 1)`, with `y2 = y * y`: every copy of the rays computes it so (`x * x +
/// y2 + 1.0` evaluates left to right), and so gets the same bits.
#[inline(always)]
fn z1_norm(x: f64, y2: f64) -> f64 {
    (x * x + y2 + 1.0).sqrt()
}

/// The unit ray along `(x, y, 1)`, whose norm has reciprocal `inv`.
#[inline(always)]
fn unit_along(x: f64, y: f64, inv: f64) -> Vector3<f64> {
    Vector3::new(x * inv, y * inv, inv)
}

/// The rotation matrix and origin of a pose, in the form ray generation wants.
pub fn pose_parts(pose: &Pose) -> (Matrix3<f64>, [f64; 3]) {
    let t = pose.translation.vector;
    (*pose.rotation.to_rotation_matrix().matrix(), [t.x, t.y, t.z])
}

/// The camera rays of one camera, computed once per camera: per column the `x` and per row the
/// `y` of the z = 1 camera ray `(x, y, 1)` (a division per column and per row, where
/// [`Camera::pixel_ray`] takes two per pixel). [`FrameRays::with_camera_rays`] uses them; the
/// rays are bit for bit those of [`pixel_direction`] (the same arithmetic as `unit_ray`).
/// Nothing is kept per pixel: the norms were 16 bytes a pixel, 4.9 MB of a 640 x 480
/// projection's peak, and [`FrameRays::row`] computes a row's norms in one loop the compiler
/// vectorises, which costs no more than reading them back.
#[derive(Clone, Debug, Default)]
pub struct CameraRays {
    camera: Option<Camera>,
    /// Camera ray `x` per column and `y` per row (`z = 1`).
    xs: Vec<f64>,
    ys: Vec<f64>,
}

impl CameraRays {
    /// The rays of `camera`, recomputed only when it differs from the last one.
    pub fn update(&mut self, camera: &Camera) -> &Self {
        if self.camera.as_ref() != Some(camera) {
            let ray = |u, v| camera.pixel_ray(u as f64, v as f64);
            self.xs = (0..camera.width).map(|u| ray(u, 0).x).collect();
            self.ys = (0..camera.height).map(|v| ray(0, v).y).collect();
            self.camera = Some(*camera);
        }
        self
    }

    /// The unit ray of pixel `(u, v)`, its z = 1 norm and the ray's z component.
    #[inline(always)]
    fn get(&self, u: u32, v: u32) -> (Vector3<f64>, f64, f64) {
        unit_ray(self.xs[u as usize], self.ys[v as usize])
    }

    /// Per pixel of row `v`: the z = 1 norm and its reciprocal (as `unit_ray` computes them).
    fn row_norms(&self, v: u32) -> (Vec<f64>, Vec<f64>) {
        let y = self.ys[v as usize];
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the processor has AVX2, checked just above.
            return unsafe { norms_of_row_avx2(&self.xs, y) };
        }
        norms_of_row(&self.xs, y)
    }
}

/// [`norms_of_row`] in AVX2's four lanes where the processor has them. Computing the norms
/// instead of reading them back made a projected frame at 0.05 m 4% slower in SSE2's two
/// lanes (the binary's baseline) and 1% in these (BENCHMARKS.md, session 25). No FMA: the
/// results stay bit for bit those of `unit_ray` (tested).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn norms_of_row_avx2(xs: &[f64], y: f64) -> (Vec<f64>, Vec<f64>) {
    norms_of_row(xs, y)
}

/// The z = 1 norms of camera rays `(x, y, 1)` for each `x` of `xs`, and their reciprocals.
#[inline(always)]
fn norms_of_row(xs: &[f64], y: f64) -> (Vec<f64>, Vec<f64>) {
    let y2 = y * y;
    let norms: Vec<f64> = xs.iter().map(|&x| z1_norm(x, y2)).collect();
    let invs = norms.iter().map(|n| 1.0 / n).collect();
    (norms, invs)
}

/// Ray generator for one frame: precomputes the rotation once, then yields rays row by row
/// (rows are the unit of parallel work).
pub struct FrameRays<'a> {
    frame: &'a Frame,
    rotation: Matrix3<f64>,
    origin: [f64; 3],
    camera_rays: Option<&'a CameraRays>,
}

impl<'a> FrameRays<'a> {
    /// Rays of `frame`.
    pub fn new(frame: &'a Frame) -> Self {
        let (rotation, origin) = pose_parts(&frame.pose);
        FrameRays { frame, rotation, origin, camera_rays: None }
    }

    /// Rays of `frame`, taking the per-pixel camera rays from `camera_rays` (updated for the
    /// frame's camera).
    pub fn with_camera_rays(frame: &'a Frame, camera_rays: &'a mut CameraRays) -> Self {
        let rays = camera_rays.update(&frame.camera);
        FrameRays { camera_rays: Some(rays), ..FrameRays::new(frame) }
    }

    /// Number of image rows.
    pub fn rows(&self) -> u32 {
        self.frame.depth.height()
    }

    /// Image width and height.
    pub fn size(&self) -> (usize, usize) {
        (self.frame.depth.width() as usize, self.frame.depth.height() as usize)
    }

    /// Rays of the valid pixels of row `v`, left to right.
    pub fn row(&self, v: u32) -> RowRays<'_, 'a> {
        let cached = self.camera_rays.map(|c| {
            let (norm, inv) = c.row_norms(v);
            (c, norm, inv)
        });
        RowRays { rays: self, v, depth: self.frame.depth.row(v), u: 0, cached }
    }

    /// The ray of pixel `(u, v)`, `None` if its depth is not valid (zero, negative or not
    /// finite) or the pixel is outside the image.
    #[inline(always)] // (into the AVX2 copy of a brick's walk, with `for_each_crossing`: 0.94x)
    pub fn ray(&self, u: u32, v: u32) -> Option<PixelRay> {
        let depth = &self.frame.depth;
        if u >= depth.width() || v >= depth.height() {
            return None;
        }
        self.ray_of(u, v, depth.get(u, v)?)
    }

    #[inline(always)] // a call per pixel, returning 80 bytes, cost a tenth of the projection setup
    fn ray_of(&self, u: u32, v: u32, z: f32) -> Option<PixelRay> {
        if !DepthImage::is_valid(z) {
            return None;
        }
        Some(match self.camera_rays {
            Some(c) => {
                let (unit, norm, cz) = c.get(u, v);
                self.ray_along(u, v, z, unit, norm, cz)
            }
            None => {
                let (dir, norm) = pixel_direction(&self.frame.camera, &self.rotation, u, v);
                PixelRay { u, v, origin: self.origin, dir, range: z as f64 * norm, cz: 1.0 / norm, returned: true }
            }
        })
    }

    /// The ray of pixel `(u, v)` at depth `z` along camera-frame unit ray `unit`, whose z = 1
    /// norm is `norm` and z component `cz`.
    #[inline(always)]
    fn ray_along(&self, u: u32, v: u32, z: f32, unit: Vector3<f64>, norm: f64, cz: f64) -> PixelRay {
        let d = self.rotation * unit;
        PixelRay { u, v, origin: self.origin, dir: [d.x, d.y, d.z], range: z as f64 * norm, cz, returned: true }
    }

    /// The measured surface point of a ray in world coordinates.
    pub fn endpoint(ray: &PixelRay) -> [f64; 3] {
        [0, 1, 2].map(|a| ray.origin[a] + ray.range * ray.dir[a])
    }
}

/// Columns [`FrameRays::row_plain`] computes at a time (its buffers live on the stack).
pub(crate) const PLAIN_COLUMNS: usize = 64;

/// [`PLAIN_COLUMNS`] pixels of a row (fewer at its end), as [`FrameRays::row_plain`] gives
/// them: per column whether its depth is valid, whether it is plain (valid and within the max
/// range), the surface's camera z-depth (`-inf` unless plain), and for the plain ones the
/// voxel key (per axis) of its point multiplied by the scale. The other columns' keys are
/// meaningless.
pub(crate) struct PlainBlock {
    pub len: usize,
    pub valid: [bool; PLAIN_COLUMNS],
    pub plain: [bool; PLAIN_COLUMNS],
    pub z_end: [f32; PLAIN_COLUMNS],
    pub key: [[i32; PLAIN_COLUMNS]; 3],
}

impl FrameRays<'_> {
    /// Row `v` a block of pixels at a time, left to right, by `visit(first column, block)`
    /// ([`PlainBlock`]): a plain pixel's reading lies within `max_range` (infinite for none);
    /// the other valid ones' rays are [`FrameRays::ray`]. Each block is computed in loops the
    /// compiler vectorises, the same values bit for bit as from the pixels' rays (`range *
    /// cz`, and [`crate::map::floor_i32`] of `(origin + range dir) scale`, computed by
    /// [`floor_i32_lanes`], without fused operations; `FLOOR_INSTRUCTION` is its own). Does
    /// nothing and returns false without cached camera rays ([`FrameRays::with_camera_rays`]).
    #[inline(always)]
    pub(crate) fn row_plain<const FLOOR_INSTRUCTION: bool>(
        &self,
        v: u32,
        max_range: f64,
        scale: f64,
        mut visit: impl FnMut(usize, &PlainBlock),
    ) -> bool {
        let Some(c) = self.camera_rays else { return false };
        let (y, depth, origin) = (c.ys[v as usize], self.frame.depth.row(v), self.origin);
        let rotation = self.rotation_rows();
        let y2 = y * y;
        let mut b = PlainBlock {
            len: 0,
            valid: [false; PLAIN_COLUMNS],
            plain: [false; PLAIN_COLUMNS],
            z_end: [0.0; PLAIN_COLUMNS],
            key: [[0; PLAIN_COLUMNS]; 3],
        };
        row_blocks(
            depth,
            &c.xs,
            #[inline(always)]
            |start, len, zs, xs| {
                b.len = len;
                // Every column, valid or not (the invalid ones' values go unused): no branch.
                // The z = 1 norm computed here, not first into a row of norms of its own (two
                // allocations and a pass), and `rotation * unit` as nalgebra sums it.
                for (k, (&z, &x)) in zs.iter().zip(xs).enumerate() {
                    let norm = z1_norm(x, y2);
                    let inv = 1.0 / norm;
                    let r = z as f64 * norm;
                    b.valid[k] = DepthImage::is_valid(z);
                    b.plain[k] = b.valid[k] & (r <= max_range);
                    b.z_end[k] = if b.plain[k] { (r * inv) as f32 } else { f32::NEG_INFINITY };
                    let unit = [x * inv, y * inv, inv];
                    for (a, key) in b.key.iter_mut().enumerate() {
                        let d = row_times(&rotation[a], &unit);
                        key[k] = floor_i32_lanes::<FLOOR_INSTRUCTION>((origin[a] + r * d) * scale);
                    }
                }
                visit(start, &b);
            },
        );
        true
    }
}

impl FrameRays<'_> {
    /// The rotation's rows as plain arrays, for the lane loops of [`row_blocks`]' callers: a
    /// local copy, which their writes cannot overlap. Component `a` of `rotation * v` is then
    /// [`row_times`] of row `a`.
    #[inline(always)]
    fn rotation_rows(&self) -> [[f64; 3]; 3] {
        std::array::from_fn(|a| std::array::from_fn(|j| self.rotation[(a, j)]))
    }
}

/// A matrix row times a vector, summed in the order nalgebra sums `matrix * vector` (the lane
/// loops' values are the per-pixel rays' bit for bit).
#[inline(always)]
fn row_times(row: &[f64; 3], v: &[f64; 3]) -> f64 {
    row[0] * v[0] + row[1] * v[1] + row[2] * v[2]
}

/// A row's depths and its columns' camera x (`xs`, [`CameraRays`]) a block of
/// [`PLAIN_COLUMNS`] at a time, left to right, by `block(first column, columns, depths, xs)`,
/// each copied into an array of the block's full width (a short last block's arrays hold the
/// previous block's values past its columns). A loop over those arrays has a fixed length
/// and reads nothing that its writes to the caller's own arrays might overlap: over slices of
/// the row, the compiler checked at run time that they overlapped none, and kept the last 8
/// columns out of lanes so as to stop at the arrays' end (an eighth of the columns, a third
/// of [`FrameRays::row_plain`]'s time; 0.89x the time of an icl-livingroom1 frame at 0.05 m,
/// BENCHMARKS.md, session 47). Callers mark `block` `#[inline(always)]`: as a function of
/// its own it kept none of the processor features of the copy it was called from.
#[inline(always)]
fn row_blocks(
    depth: &[f32],
    xs: &[f64],
    mut block: impl FnMut(usize, usize, &[f32; PLAIN_COLUMNS], &[f64; PLAIN_COLUMNS]),
) {
    let (mut zs_block, mut xs_block) = ([0.0f32; PLAIN_COLUMNS], [0.0f64; PLAIN_COLUMNS]);
    for start in (0..depth.len()).step_by(PLAIN_COLUMNS) {
        let stop = (start + PLAIN_COLUMNS).min(depth.len());
        zs_block[..stop - start].copy_from_slice(&depth[start..stop]);
        xs_block[..stop - start].copy_from_slice(&xs[start..stop]);
        block(start, stop - start, &zs_block, &xs_block);
    }
}

/// Blocks of [`PLAIN_COLUMNS`] pixels with at least this many readings beyond the max range
/// have their cut segments computed in lanes by [`FrameRays::row_cut`]; fewer go one at a time
/// (the lanes compute every column of the block).
const CUT_IN_LANES: usize = 8;

impl FrameRays<'_> {
    /// Whether row `v` may hold a valid reading beyond `max_range`: its deepest reading along
    /// the row's longest camera ray reaches past it. Only a choice of the faster way to fill
    /// a row: [`FrameRays::row_cut`] is not needed for rows where this is false.
    pub(crate) fn row_may_cut(&self, v: u32, max_range: f64) -> bool {
        let Some(c) = self.camera_rays else { return false };
        // Eight running maxima side by side, by comparisons, not `f32::max` (whose NaN handling
        // and one running maximum kept this scan out of lanes): the same value, as a NaN never
        // compares greater.
        let greater = |m: f32, z: f32| if z > m { z } else { m };
        let row = self.frame.depth.row(v);
        let mut lanes = [0.0f32; 8];
        for chunk in row.chunks_exact(8) {
            for (m, &z) in lanes.iter_mut().zip(chunk) {
                *m = greater(*m, z);
            }
        }
        let deepest = lanes.into_iter().chain(row.chunks_exact(8).remainder().iter().copied()).fold(0.0, greater);
        let y = c.ys[v as usize];
        let (first, last) = (c.xs.first().copied().unwrap_or(0.0), c.xs.last().copied().unwrap_or(0.0));
        let longest = (first.abs().max(last.abs()).powi(2) + y * y + 1.0).sqrt();
        deepest as f64 * longest > max_range
    }

    /// Row `v`'s valid pixels whose readings lie beyond the max range of `limits` (which has
    /// no bounds): sets `ends[u]` to the camera z-depth where the segment of
    /// [`RayLimits::hit_miss_segment`] ends, for those it leaves a segment. The values are
    /// that function's bit for bit (the same operations in the same order, no fused ones),
    /// computed in lanes a block of [`PLAIN_COLUMNS`] at a time where at least
    /// [`CUT_IN_LANES`] of its pixels are beyond, per pixel otherwise. Does nothing without
    /// cached camera rays or a max range. The pixels within the max range are
    /// [`FrameRays::row_plain`]'s.
    #[inline(always)]
    pub(crate) fn row_cut(&self, v: u32, limits: &RayLimits, resolution: f64, ends: &mut [f32]) {
        debug_assert!(limits.bounds.is_none(), "a cut segment with bounds starts past the camera");
        let (Some(c), Some(max_range)) = (self.camera_rays, limits.max_range) else { return };
        let (y, depth, origin) = (c.ys[v as usize], self.frame.depth.row(v), self.origin);
        let rotation = self.rotation_rows();
        let y2 = y * y;
        let mut beyond = [false; PLAIN_COLUMNS];
        let mut inv = [0.0f64; PLAIN_COLUMNS];
        let mut z_cut = [0.0f32; PLAIN_COLUMNS];
        let mut kept = [false; PLAIN_COLUMNS];
        row_blocks(
            depth,
            &c.xs,
            #[inline(always)]
            |start, len, zs, xs| {
                // (The columns past `len` are not beyond.)
                for (k, (&z, &x)) in zs.iter().zip(xs).enumerate() {
                    let norm = z1_norm(x, y2);
                    inv[k] = 1.0 / norm;
                    beyond[k] = (k < len) & DepthImage::is_valid(z) & (z as f64 * norm > max_range);
                }
                let count = beyond.iter().filter(|&&b| b).count();
                if count == 0 {
                    return;
                }
                if count < CUT_IN_LANES {
                    for k in (0..len).filter(|&k| beyond[k]) {
                        let u = (start + k) as u32;
                        let seg = self
                            .ray_of(u, v, zs[k])
                            .and_then(|ray| Some((limits.hit_miss_segment(&ray, resolution)?, ray.cz)));
                        if let Some((seg, cz)) = seg {
                            ends[start + k] = (seg.end * cz) as f32;
                        }
                    }
                    return;
                }
                // Every column, beyond or not (the others' values go unused): no branch. The cut
                // end is `max_range` along the ray, pulled back to where the ray enters its voxel.
                for (k, &x) in xs.iter().enumerate() {
                    let unit = [x * inv[k], y * inv[k], inv[k]];
                    let mut enter = f64::NEG_INFINITY;
                    for a in 0..3 {
                        let d = row_times(&rotation[a], &unit);
                        let cell = ((origin[a] + max_range * d) / resolution).floor();
                        let face = if d > 0.0 { cell } else { cell + 1.0 };
                        let t = (face * resolution - origin[a]) / d;
                        enter = if d != 0.0 { enter.max(t) } else { enter };
                    }
                    let end = max_range.min(enter - 1e-4 * resolution);
                    z_cut[k] = (end * inv[k]) as f32;
                    kept[k] = end > 0.0;
                }
                for k in 0..len {
                    if beyond[k] && kept[k] {
                        ends[start + k] = z_cut[k];
                    }
                }
            },
        );
    }
}

/// The rays of one row's valid pixels, left to right ([`FrameRays::row`]). A named iterator
/// so that its `next` is inlined into the caller's loop: the closure of a `filter_map` was
/// called once per pixel and returned its 80-byte ray through memory, a third of a projected
/// frame's per-pixel setup (BENCHMARKS.md, session 27).
pub struct RowRays<'r, 'a> {
    rays: &'r FrameRays<'a>,
    v: u32,
    depth: &'a [f32],
    /// The next pixel's column.
    u: usize,
    /// With cached camera rays: those, and the row's z = 1 norms and their reciprocals.
    cached: Option<(&'a CameraRays, Vec<f64>, Vec<f64>)>,
}

impl Iterator for RowRays<'_, '_> {
    type Item = PixelRay;

    #[inline(always)]
    fn next(&mut self) -> Option<PixelRay> {
        while let Some(&z) = self.depth.get(self.u) {
            let u = self.u;
            self.u += 1;
            if !DepthImage::is_valid(z) {
                continue;
            }
            let rays = self.rays;
            return Some(match &self.cached {
                Some((c, norm, inv)) => {
                    let unit = unit_along(c.xs[u], c.ys[self.v as usize], inv[u]);
                    rays.ray_along(u as u32, self.v, z, unit, norm[u], inv[u])
                }
                None => match rays.ray_of(u as u32, self.v, z) {
                    Some(ray) => ray,
                    None => continue,
                },
            });
        }
        None
    }
}

/// Folds every valid pixel's segment within `limits` (the forward-model engines' segments, 3
/// std past the surface, when `forward_model` is true; the frame's noise model or the
/// default): rows in parallel, each into its own `empty()` with `visit`, then merged.
fn fold_segments<A: Send>(
    frame: &Frame,
    limits: &RayLimits,
    forward_model: bool,
    empty: impl Fn() -> A + Sync + Send,
    visit: impl Fn(&mut A, &PixelRay, &Segment) + Sync + Send,
    merge: impl Fn(A, A) -> A + Sync + Send,
) -> A {
    let default_noise;
    let noise = match &frame.noise {
        Some(n) => n.as_ref(),
        None => {
            default_noise = crate::frames::default_noise_model();
            &default_noise
        }
    };
    let rays = FrameRays::new(frame);
    (0..rays.rows())
        .into_par_iter()
        .map(|v| {
            let mut acc = empty();
            for ray in rays.row(v) {
                let seg =
                    if forward_model { limits.forward_model_segment(&ray, noise) } else { limits.segment(&ray, 0.0) };
                if let Some(seg) = seg {
                    visit(&mut acc, &ray, &seg);
                }
            }
            acc
        })
        .reduce(&empty, merge)
}

/// A box that every ray of `frame` stays inside within `limits`: the camera and each valid
/// pixel's segment end (the forward-model engines' segments, 3 std past the surface, when
/// `forward_model` is true), or `None` when no pixel has a segment.
/// Rays are straight lines from the camera, so a box holding the camera and every end holds
/// every ray: what decides which tiles of a tiled map a frame can touch.
pub fn frame_reach(frame: &Frame, limits: &RayLimits, forward_model: bool) -> Option<Aabb> {
    let (_, origin) = pose_parts(&frame.pose);
    let (lo, hi) = fold_segments(
        frame,
        limits,
        forward_model,
        || ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
        |acc, ray, seg| {
            for a in 0..3 {
                let end = ray.origin[a] + seg.end * ray.dir[a];
                acc.0[a] = acc.0[a].min(end);
                acc.1[a] = acc.1[a].max(end);
            }
        },
        |a, b| ([0, 1, 2].map(|k| a.0[k].min(b.0[k])), [0, 1, 2].map(|k| a.1[k].max(b.1[k]))),
    );
    if !lo[0].is_finite() {
        return None;
    }
    let lo = [0, 1, 2].map(|a| lo[a].min(origin[a]));
    let hi = [0, 1, 2].map(|a| hi[a].max(origin[a]));
    // A flat reach (a ray along an axis) still needs a box of positive volume.
    Aabb::new(lo, [0, 1, 2].map(|a| if hi[a] > lo[a] { hi[a] } else { lo[a] + 1e-9_f64.max(lo[a].abs() * 1e-12) })).ok()
}

/// Which of `boxes` some ray of `frame` crosses within `limits` ([`frame_reach`]'s segments):
/// the exact test behind the box one, for the boxes that box overlaps.
pub fn frame_crosses(frame: &Frame, limits: &RayLimits, forward_model: bool, boxes: &[Aabb]) -> Vec<bool> {
    fold_segments(
        frame,
        limits,
        forward_model,
        || vec![false; boxes.len()],
        |hit, ray, seg| {
            for (h, b) in hit.iter_mut().zip(boxes) {
                *h = *h || b.clip(ray.origin, ray.dir, seg.start, seg.end).is_some();
            }
        },
        |a, b| a.iter().zip(&b).map(|(x, y)| *x || *y).collect(),
    )
}

/// Ray generator for a range scan: beams in order, in rows of [`ScanRays::ROW`] beams (the
/// unit of parallel work).
pub struct ScanRays<'a> {
    scan: &'a RangeScan,
    rotation: Matrix3<f64>,
    origin: [f64; 3],
}

impl<'a> ScanRays<'a> {
    /// Beams per row.
    pub const ROW: usize = 64;

    /// Rays of `scan`.
    pub fn new(scan: &'a RangeScan) -> Self {
        let (rotation, origin) = pose_parts(&scan.pose);
        ScanRays { scan, rotation, origin }
    }

    /// Number of rows.
    pub fn rows(&self) -> u32 {
        self.scan.beams.len().div_ceil(Self::ROW) as u32
    }

    /// Rays of row `v`; beam `k` has `u = k`, `v = 0`.
    pub fn row(&self, v: u32) -> impl Iterator<Item = PixelRay> + '_ {
        let start = v as usize * Self::ROW;
        let end = (start + Self::ROW).min(self.scan.beams.len());
        self.scan.beams[start.min(end)..end].iter().enumerate().map(move |(k, b)| {
            let d = self.rotation * nalgebra::Vector3::from(b.dir);
            PixelRay {
                u: (start + k) as u32,
                v: 0,
                origin: self.origin,
                dir: [d.x, d.y, d.z],
                range: b.range.unwrap_or(self.scan.max_range),
                cz: 1.0,
                returned: b.range.is_some(),
            }
        })
    }
}

/// The rays of either kind of reading.
pub enum Rays<'a> {
    /// A depth image.
    Image(FrameRays<'a>),
    /// A range scan.
    Scan(ScanRays<'a>),
}

impl<'a> Rays<'a> {
    /// Rays of a depth frame.
    pub fn of_frame(frame: &'a Frame) -> Self {
        Rays::Image(FrameRays::new(frame))
    }

    /// Rays of a range scan.
    pub fn of_scan(scan: &'a RangeScan) -> Self {
        Rays::Scan(ScanRays::new(scan))
    }

    /// Number of rows (units of parallel work).
    pub fn rows(&self) -> u32 {
        match self {
            Rays::Image(r) => r.rows(),
            Rays::Scan(r) => r.rows(),
        }
    }

    /// Rays of row `v`, in order.
    pub fn row(&self, v: u32) -> impl Iterator<Item = PixelRay> + '_ {
        let (image, scan) = match self {
            Rays::Image(r) => (Some(r.row(v)), None),
            Rays::Scan(r) => (None, Some(r.row(v))),
        };
        image.into_iter().flatten().chain(scan.into_iter().flatten())
    }

    /// A number unique to each ray of the reading, increasing in ray order (pixel index,
    /// beam index): tie-breaks that must not depend on thread scheduling use it.
    pub fn ray_id(&self, ray: &PixelRay) -> u64 {
        match self {
            Rays::Image(r) => ray.v as u64 * r.frame.depth.width() as u64 + ray.u as u64,
            Rays::Scan(_) => ray.u as u64,
        }
    }
}

/// What part of each ray an engine may use: the user's max range and bounding box.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayLimits {
    /// Readings farther than this are cut here and carry no surface (OctoMap's `maxrange`).
    pub max_range: Option<f64>,
    /// Only this box is mapped.
    pub bounds: Option<Aabb>,
}

/// The usable part of a ray after [`RayLimits`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Start range.
    pub start: f64,
    /// End range.
    pub end: f64,
    /// True when the segment ends at the measured surface (not cut by max range or bounds).
    pub hits_surface: bool,
}

impl Segment {
    /// The forward model's final term for `ray` traced over this segment: the likelihood
    /// (density per metre, as [`RayLikelihood::over`]) of its reading if the surface lies past
    /// the segment's end. Where the segment ends 3 std past the reading, the forward model over
    /// one more voxel (`voxel` metres of range). Where the bounds or the max range cut it
    /// short, the surface may lie anywhere outside the map up to that point: the forward model
    /// averaged over the stretch cut off (with nothing there, a ray would force its surface
    /// into the last voxels inside). A beam with no return: 1, the light passed it all.
    pub fn beyond(&self, ray: &PixelRay, noise: &NoiseModel, likelihood: &mut RayLikelihood, voxel: f64) -> f64 {
        self.beyond_stretch(ray, noise, voxel).map_or(1.0, |(z0, z1)| likelihood.over(z0, z1))
    }

    /// The camera z-depths [`Segment::beyond`] takes the likelihood over, `None` for a beam
    /// with no return (whose term is 1): for a caller that computes it with others.
    #[inline]
    pub fn beyond_stretch(&self, ray: &PixelRay, noise: &NoiseModel, voxel: f64) -> Option<(f64, f64)> {
        let z_end = self.end * ray.cz;
        let next = z_end + voxel * ray.cz;
        if self.hits_surface {
            return Some((z_end, next));
        }
        ray.returned.then(|| (z_end, forward_model_end(ray, noise).max(next)))
    }
}

/// The z-depth where a forward-model ray ends when nothing cuts it: 3 std beyond the
/// bias-corrected reading.
#[inline]
fn forward_model_end(ray: &PixelRay, noise: &NoiseModel) -> f64 {
    let z = ray.range * ray.cz;
    let (bias, std) = noise.bias_std(ray.u, ray.v, z);
    (z - bias + 3.0 * std).max(0.5 * z)
}

impl RayLimits {
    /// Checks the limits themselves.
    pub fn validate(&self) -> crate::Result<()> {
        if let Some(m) = self.max_range
            && !(m > 0.0)
        {
            return Err(crate::Error::Invalid(format!("max range must be positive, got {m}")));
        }
        Ok(())
    }

    /// The keys of the voxels in the bounds (inclusive, as [`box_keys`] gives them), if there
    /// are bounds: the voxels an engine may touch. The rays are cut at the box's faces, but a
    /// ray that leaves or enters by a face lying on voxel faces reaches the voxel beyond it by
    /// a rounding error (about half such rays, walked or projected); the engines leave those
    /// voxels out, as OctoMap keeps only its bounding box's keys ("--bounds maps only that
    /// box").
    pub fn bounds_keys(&self, resolution: f64) -> Option<([i32; 3], [i32; 3])> {
        self.bounds.as_ref().map(|b| box_keys(b, resolution))
    }

    /// Range of the ray's measured surface, `None` when it lies beyond the max range (the
    /// reading then only says "free up to max range").
    #[inline]
    pub fn surface_range(&self, ray: &PixelRay) -> Option<f64> {
        (ray.returned && self.max_range.is_none_or(|m| ray.range <= m)).then_some(ray.range)
    }

    /// The segment the forward-model engines (MRF, CRM) use: from the camera to 3 std beyond
    /// the bias-corrected depth (where the sensor model stops carrying information), within
    /// the limits.
    pub fn forward_model_segment(&self, ray: &PixelRay, noise: &NoiseModel) -> Option<Segment> {
        self.segment(ray, forward_model_end(ray, noise) / ray.cz - ray.range)
    }

    /// The segment of `ray` from the camera to its surface (or `extra` metres past it, for
    /// engines that model the space behind a surface) that the limits allow.
    ///
    /// ```
    /// use mrfmap::rays::{RayLimits, PixelRay};
    /// let ray = PixelRay { u: 0, v: 0, origin: [0.0; 3], dir: [1.0, 0.0, 0.0], range: 5.0, cz: 1.0, returned: true };
    /// let limits = RayLimits { max_range: Some(3.0), bounds: None };
    /// let seg = limits.segment(&ray, 0.0).unwrap();
    /// assert_eq!((seg.start, seg.end, seg.hits_surface), (0.0, 3.0, false));
    /// ```
    #[inline]
    pub fn segment(&self, ray: &PixelRay, extra: f64) -> Option<Segment> {
        let mut seg = match (self.surface_range(ray), self.max_range) {
            (Some(z), m) => {
                Segment { start: 0.0, end: m.map_or(z + extra, |m| (z + extra).min(m.max(z))), hits_surface: true }
            }
            // Beyond the max range, or a beam with no return (free up to the sensor's range).
            (None, m) => Segment { start: 0.0, end: m.map_or(ray.range, |m| m.min(ray.range)), hits_surface: false },
        };
        if let Some(b) = &self.bounds {
            let (a, e) = b.clip(ray.origin, ray.dir, seg.start, seg.end)?;
            // A surface exactly on a face of the box (a floor at z = 0 with bounds from z = 0)
            // is inside; the slab arithmetic may put the exit a rounding error before it.
            if ray.range - e > 1e-9 * ray.range.max(1.0) {
                seg.hits_surface = false;
            }
            seg.start = a;
            seg.end = e;
        }
        Some(seg)
    }

    /// The segment OctoMap's `insertPointCloud` marks for `ray` in a grid of voxel edge
    /// `resolution`: [`RayLimits::segment`], except that a ray cut at the max range (or a beam
    /// without a return, which ends at the sensor's range) stops where it enters the voxel
    /// holding its cut end. OctoMap traces such a ray to the cut point with `computeRayKeys`,
    /// which leaves out the end point's voxel; a ray that reaches its surface marks every voxel
    /// up to and including the surface's. `None` when nothing is left (the cut end lies in
    /// the camera's voxel: OctoMap's ray is then empty). A segment that the bounds cut keeps
    /// its end voxel (bounds are mrfmap's, not OctoMap's).
    #[inline(always)] // (once per pixel of a projected frame: as a call, 5% of its time)
    pub fn hit_miss_segment(&self, ray: &PixelRay, resolution: f64) -> Option<Segment> {
        let mut seg = self.segment(ray, 0.0)?;
        let cut_end = self.max_range.map_or(ray.range, |m| m.min(ray.range));
        if seg.hits_surface || seg.end != cut_end {
            return Some(seg);
        }
        // Where the ray enters the end voxel: the last of the faces it crosses to get there.
        let mut enter = f64::NEG_INFINITY;
        for a in 0..3 {
            if ray.dir[a] != 0.0 {
                let k = ((ray.origin[a] + seg.end * ray.dir[a]) / resolution).floor();
                let face = if ray.dir[a] > 0.0 { k } else { k + 1.0 };
                enter = enter.max((face * resolution - ray.origin[a]) / ray.dir[a]);
            }
        }
        // A ten-thousandth of a voxel short of that face, so that rounding (the projection's
        // slab tests are in f32) never puts a sliver of the end voxel back.
        seg.end = seg.end.min(enter - 1e-4 * resolution);
        (seg.end > seg.start).then_some(seg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cached_camera_rays_are_bit_identical() {
        use crate::frames::{DepthImage, look_at};
        let camera = Camera::new(481.2, -480.0, 319.5, 239.5, 64, 48, 5000.0).unwrap();
        let mut depth = DepthImage::new(64, 48);
        for v in 0..48 {
            for u in 0..64 {
                depth.set(u, v, if (u + v) % 7 == 0 { 0.0 } else { 0.5 + (u * v) as f32 * 0.001 });
            }
        }
        let pose = look_at(nalgebra::Vector3::new(0.3, -1.2, 0.7), nalgebra::Vector3::new(2.0, 0.4, 0.1)).unwrap();
        let frame = Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None };
        let mut cache = CameraRays::default();
        let (plain, cached) = (FrameRays::new(&frame), FrameRays::with_camera_rays(&frame, &mut cache));
        let mut n = 0;
        for v in 0..48 {
            let (a, b): (Vec<_>, Vec<_>) = (plain.row(v).collect(), cached.row(v).collect());
            assert_eq!(a, b, "row {v}");
            for (u, ray) in (0..64).filter_map(|u| Some((u, plain.ray(u, v)?))) {
                assert_eq!(cached.ray(u, v), Some(ray));
                n += 1;
            }
        }
        assert!(n > 2500);
        assert_eq!(cached.ray(64, 0), None, "outside the image");
    }

    /// `row_plain` gives a row's pixels in order, says which are valid and which plain as
    /// their rays do, and its plain values are those of the rays bit for bit, either way of
    /// rounding: over block boundaries (a 150-pixel row), invalid depths, readings beyond the
    /// max range and several poses.
    #[test]
    fn plain_rows_are_their_rays_bit_for_bit() {
        use crate::frames::{DepthImage, look_at};
        use crate::map::floor_i32;
        let mut rng = crate::random::Rng::new(3);
        let camera = Camera::new(130.0, -131.5, 74.5, 19.5, 150, 40, 5000.0).unwrap();
        let (mut plain_seen, mut others) = (0, 0);
        for trial in 0..6 {
            let mut depth = DepthImage::new(150, 40);
            for v in 0..40 {
                for u in 0..150 {
                    let z = match (rng.uniform() * 20.0) as u32 {
                        0 => 0.0,
                        1 => f32::NAN,
                        2 => -1.0,
                        _ => rng.range(0.2, 8.0) as f32,
                    };
                    depth.set(u, v, z);
                }
            }
            let eye = [rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), rng.range(-1.0, 1.0)];
            let pose = look_at(eye.into(), nalgebra::Vector3::new(0.1, 0.2, 0.3)).unwrap();
            let frame = Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None };
            let mut cache = CameraRays::default();
            let rays = FrameRays::with_camera_rays(&frame, &mut cache);
            let (max_range, scale) = ([5.0, f64::INFINITY][trial % 2], rng.range(10.0, 100.0));
            assert!(
                !FrameRays::new(&frame).row_plain::<false>(0, max_range, scale, |_, _| ()),
                "no cached camera rays"
            );
            for (v, floor_instruction) in (0..40).flat_map(|v| [(v, false), (v, true)]) {
                let mut visited = Vec::new();
                let visit = |start: usize, b: &PlainBlock| {
                    for k in 0..b.len {
                        let plain = b.plain[k].then(|| (b.z_end[k], [0, 1, 2].map(|a| b.key[a][k])));
                        visited.push((start + k, b.valid[k], plain));
                    }
                };
                assert!(match floor_instruction {
                    false => rays.row_plain::<false>(v, max_range, scale, visit),
                    true => rays.row_plain::<true>(v, max_range, scale, visit),
                });
                assert_eq!(visited.iter().map(|p| p.0).collect::<Vec<_>>(), (0..150).collect::<Vec<_>>(), "row {v}");
                let mut rays_of_row = rays.row(v).peekable();
                for (u, valid, plain) in visited {
                    let ray = rays_of_row.next_if(|r| r.u as usize == u);
                    assert_eq!(valid, ray.is_some(), "pixel {u}, {v}");
                    let Some(ray) = ray else { continue };
                    match plain {
                        Some((z, key)) => {
                            assert!(ray.range <= max_range);
                            assert_eq!(z.to_bits(), ((ray.range * ray.cz) as f32).to_bits());
                            let q = [0, 1, 2].map(|a| floor_i32((ray.origin[a] + ray.range * ray.dir[a]) * scale));
                            assert_eq!(key, q, "pixel {u}, {v}");
                            plain_seen += 1;
                        }
                        None => {
                            assert!(ray.range > max_range);
                            others += 1;
                        }
                    }
                }
                assert!(rays_of_row.next().is_none(), "row {v}");
            }
        }
        assert!(plain_seen > 10_000 && others > 1_000, "{plain_seen} plain, {others} beyond the max range");
    }

    #[test]
    fn both_copies_of_the_row_norms_agree() {
        let camera = Camera::new(481.2, -480.0, 319.5, 239.5, 64, 48, 5000.0).unwrap();
        let mut rays = CameraRays::default();
        let rays = rays.update(&camera);
        for v in 0..48 {
            let y = rays.ys[v];
            let base = norms_of_row(&rays.xs, y);
            // The norms are those of `unit_ray`, bit for bit.
            for (u, &x) in rays.xs.iter().enumerate() {
                let (_, norm, inv) = unit_ray(x, y);
                assert_eq!((base.0[u].to_bits(), base.1[u].to_bits()), (norm.to_bits(), inv.to_bits()));
            }
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the processor has AVX2, checked just above.
                assert_eq!(unsafe { norms_of_row_avx2(&rays.xs, y) }, base, "row {v}");
            }
        }
    }

    #[test]
    fn bounds_clip_and_drop_surfaces_outside() {
        let b = Aabb::new([0.0, -1.0, -1.0], [2.0, 1.0, 1.0]).unwrap();
        let limits = RayLimits { max_range: None, bounds: Some(b) };
        let ray = |range| PixelRay {
            u: 0,
            v: 0,
            origin: [-1.0, 0.0, 0.0],
            dir: [1.0, 0.0, 0.0],
            range,
            cz: 1.0,
            returned: true,
        };
        let s = limits.segment(&ray(2.0), 0.0).unwrap();
        assert_eq!((s.start, s.end, s.hits_surface), (1.0, 2.0, true));
        let s = limits.segment(&ray(5.0), 0.0).unwrap();
        assert_eq!((s.start, s.end, s.hits_surface), (1.0, 3.0, false));
        assert!(limits.segment(&ray(0.5), 0.0).is_none());
        // A surface on the box face, reached along an oblique ray, is inside.
        let b = Aabb::new([-2.0, -2.0, 0.0], [2.0, 2.0, 3.0]).unwrap();
        let limits = RayLimits { max_range: None, bounds: Some(b) };
        let origin = [0.3, -0.7, 2.0];
        let dir = [0.3f64, 0.4, -0.7];
        let n = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        let dir = dir.map(|d| d / n);
        let range = 2.0 / -dir[2]; // reaches z = 0 (up to rounding)
        let ray = PixelRay { u: 0, v: 0, origin, dir, range, cz: 1.0, returned: true };
        assert!(limits.segment(&ray, 0.0).unwrap().hits_surface);
        assert!(Aabb::parse("0,0,0,1,1").is_err());
    }

    #[test]
    fn scan_rays_and_no_return_segments() {
        use crate::frames::{Pose, RangeScan};
        let pose = Pose::translation(1.0, 2.0, 0.5);
        let ranges: Vec<Option<f64>> = (0..100).map(|k| (k % 3 != 0).then_some(0.5 + k as f64 * 0.01)).collect();
        let scan = RangeScan::planar(0, pose, &ranges, 3.0, None).unwrap();
        let rays = Rays::of_scan(&scan);
        assert_eq!(rays.rows(), 2);
        let all: Vec<PixelRay> = (0..rays.rows()).flat_map(|v| rays.row(v).collect::<Vec<_>>()).collect();
        assert_eq!(all.len(), 100);
        for (k, ray) in all.iter().enumerate() {
            assert_eq!((ray.u as usize, rays.ray_id(ray)), (k, k as u64));
            assert_eq!(ray.origin, [1.0, 2.0, 0.5]);
            assert_eq!(ray.returned, ranges[k].is_some());
            let seg = RayLimits::default().segment(ray, 0.0).unwrap();
            assert_eq!(seg.hits_surface, ray.returned);
            assert_eq!(seg.end, ranges[k].unwrap_or(3.0));
            // A max range shorter than the sensor's cuts both kinds.
            let cut = RayLimits { max_range: Some(1.0), bounds: None }.segment(ray, 0.0).unwrap();
            assert_eq!(cut.end, seg.end.min(1.0));
        }
        assert!(Aabb::parse("0,0,0,-1,1,1").is_err());
    }

    /// The final term: one voxel past a segment that ends 3 std past its reading; the stretch
    /// cut off when the bounds end it before; 1 for a beam with no return.
    #[test]
    fn final_term_of_whole_cut_and_unreturned_rays() {
        use crate::frames::Poly;
        let noise = NoiseModel::aggregate(Poly([0.0; 3]), Poly([0.02, 0.0, 0.0]));
        let ray =
            |range, returned| PixelRay { u: 0, v: 0, origin: [0.0; 3], dir: [1.0, 0.0, 0.0], range, cz: 1.0, returned };
        let term = |limits: RayLimits, ray: PixelRay| {
            let seg = limits.forward_model_segment(&ray, &noise).unwrap();
            (seg, seg.beyond(&ray, &noise, &mut noise.along_ray(0, 0, ray.range), 0.05))
        };
        let (seg, whole) = term(RayLimits::default(), ray(2.0, true));
        assert!(seg.hits_surface && (seg.end - 2.06).abs() < 1e-12);
        assert_eq!(whole, noise.likelihood_over(0, 0, 2.06, 2.11, 2.0));
        // Bounds end at 1.9 m, 5 std before the reading: the surface lies in [1.9, 2.06].
        let bounded = RayLimits { max_range: None, bounds: Some(Aabb::new([-1.0; 3], [1.9, 1.0, 1.0]).unwrap()) };
        let (seg, cut) = term(bounded, ray(2.0, true));
        assert!(!seg.hits_surface && (seg.end - 1.9).abs() < 1e-12);
        let expected = noise.likelihood_over(0, 0, 1.9, 2.06, 2.0);
        assert!((cut - expected).abs() < 1e-12 * expected && (cut * 0.16 - 0.99865).abs() < 1e-4, "{cut}"); // mass from -5 to +3 std
        assert_eq!(term(RayLimits::default(), ray(3.0, false)).1, 1.0);
    }
}
