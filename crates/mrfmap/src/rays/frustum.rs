//! Which voxels the rays of a depth image cross, found by projecting boxes of voxels into the
//! image instead of walking every ray.
//!
//! Walking each ray ([`for_each_crossing`](super::for_each_crossing)) visits a voxel once for every ray that crosses
//! it, and near the camera a voxel is crossed by hundreds of rays of one frame.
//! [`Projector::crossed_voxels`] gives the same set of voxels with work that grows with the
//! number of voxels instead:
//!
//! 1. Every pixel's usable segment (after [`RayLimits`]) is turned into a start and end depth
//!    (camera z); min/max pyramids over those depths answer "what do the pixels in this
//!    rectangle see" with at most nine reads.
//! 2. The box around the view frustum is split recursively (bricks, then halves down to
//!    voxels). Each box is projected into the image and classified: no pixel that can see it
//!    reaches it ([`Seen::None`]: skip it); every pixel that can see it passes all the way
//!    through it and each voxel covers a pixel centre ([`Seen::All`]: all its voxels are
//!    crossed); or neither ([`Seen::Some`]: split it).
//! 3. A single voxel that stays undecided gets the exact test: does the segment of some pixel
//!    in its footprint pass through it (slab test)? Not if a segment ends at a measured
//!    surface inside it: it is then the frame's surface, crossed or not, and is set as
//!    crossed. The pixel nearest the voxel's middle is tried first, and two thirds of the
//!    voxels tested are settled by it ([`View::voxel_crossed`]); for the others the
//!    footprint is scanned. Pixels go in blocks of 4 x 4; a block is ruled out first by its
//!    depth bounds, then by one slab test of the box of its rays' directions
//!    ([`View::block_misses`]), and only then are its rows tested in lanes; a footprint
//!    many blocks across has its blocks ruled out 2 x 2 at a time first. An undecided box
//!    of 2 x 2 x 2 or 4 x 4 x 4 voxels without a surface gets the same test as a whole
//!    first: behind surfaces, where most tests say "not crossed", one test then settles
//!    all its voxels.
//! 4. Undecided bricks that few pixels see, or that lie where voxels are smaller than a pixel
//!    (so no box can be decided whole), have their rays walked within the brick instead;
//!    blocks of pixels and pixels whose depths or directions miss the brick are ruled out
//!    first by the same bounds, and the rays left are set up four at a time
//!    ([`View::walk_brick`]).
//!
//! A caller may leave voxels open ([`Projector::crossed_voxels`]'s `settled`: those whose
//! crossing would change nothing for it): they get no test, and a brick of them is skipped.
//!
//! The result equals the walk's set up to rays that graze an edge or a corner of a voxel
//! (tested against the walk on random scenes and on icl-livingroom-5). Where most of a frame
//! lies beyond the distance at which voxels shrink below a pixel, walking is faster, and
//! [`Projector::pays_off`] says so. Only whole depth images can be done this way; range scans
//! have no pixel lattice and are walked. BENCHMARKS.md has the measurements behind each step.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use std::ops::ControlFlow;

use super::traversal::mark_in_brick;
use super::{CameraRays, FrameRays, PLAIN_COLUMNS, PixelRay, PlainBlock, RayLimits};
use crate::frames::{Camera, DepthImage, Frame};
use crate::map::{Aabb, box_keys};
use crate::map::{BRICK_EDGE, BrickKey, SlotMask, VoxelKey, floor_i32, mask_has, mask_set, mask_slots};
use crate::placement::Step;
use rustc_hash::FxHashMap;

mod centres;

/// The voxels one depth image's rays cross, and the voxels holding the measured surfaces.
#[derive(Clone, Debug, Default)]
pub struct CrossedVoxels {
    /// Crossed voxels per brick; each brick appears once.
    pub crossed: Vec<(BrickKey, SlotMask)>,
    /// The voxels where segments end at their measured surface, per brick; each brick
    /// appears once.
    pub ends: Vec<(BrickKey, SlotMask)>,
}

impl CrossedVoxels {
    /// The voxels of [`CrossedVoxels::ends`] one by one.
    pub fn end_voxels(&self) -> impl Iterator<Item = VoxelKey> + '_ {
        self.ends.iter().flat_map(|(b, m)| mask_slots(m).map(|s| b.voxel(s)))
    }
}

/// Finds the voxels a depth image's rays cross by projection (see the module documentation).
/// It keeps its per-pixel buffers (about 5 bytes per pixel, 9 with bounds) from one frame to
/// the next: allocating them afresh cost a tenth of the time in page faults.
///
/// ```
/// use mrfmap::frames::{Camera, DepthImage, Frame, look_at};
/// use mrfmap::rays::{Projector, RayLimits};
/// use nalgebra::Vector3;
/// let camera = Camera::new(50.0, 50.0, 15.5, 15.5, 32, 32, 1000.0).unwrap();
/// let mut depth = DepthImage::new(32, 32);
/// for v in 0..32 { for u in 0..32 { depth.set(u, v, 1.0); } }
/// let pose = look_at(Vector3::new(0.01, 0.01, 0.01), Vector3::new(1.0, 0.01, 0.01)).unwrap();
/// let frame = Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None };
/// let c = Projector::default().crossed_voxels(&frame, &RayLimits::default(), 0.05, None, None);
/// // The wall z = 1 m ahead is at x = 1.01, in voxel column 20; no end falls elsewhere.
/// assert!(!c.ends.is_empty() && c.end_voxels().all(|k| k.0[0] == 20));
/// let count: u32 = c.crossed.iter().flat_map(|(_, m)| m.iter()).map(|w| w.count_ones()).sum();
/// assert!(count > 20); // at least the 21 voxels straight ahead
/// ```
#[derive(Clone, Debug, Default)]
pub struct Projector {
    segments: Segments,
    camera_rays: CameraRays,
}

impl Projector {
    /// Sizes the per-pixel buffers for the images of `camera`, with or without ray bounds
    /// ([`RayLimits::bounds`]), before the first frame: a mapper that knows its camera makes
    /// them at start-up instead of in its first frame's integration (as wavemap makes its
    /// range images when its integrator is made). Buffers for another size are made when a
    /// frame of that size comes.
    pub fn prepare(&mut self, camera: &Camera, bounds: bool) {
        self.camera_rays.update(camera);
        self.segments.shape((camera.width as usize, camera.height as usize), bounds);
    }

    /// Whether projection is expected to beat walking every ray for `frame`: not when most
    /// of its depths lie beyond the distance where voxels shrink below a pixel (there rays
    /// are sparser than voxels, and projection ends up walking them anyway, with overhead).
    /// coffin-world at 0.01 m (depths 3-6 m, voxels below a pixel beyond 2.5 m) walks in
    /// 485 ms per frame and projects in 575 ms; at 0.02 m, or icl-livingroom-5 at 0.01 m,
    /// projection is 1.4x and 2.8x faster.
    ///
    /// ```
    /// use mrfmap::frames::{Camera, DepthImage, Frame, Pose};
    /// use mrfmap::rays::Projector;
    /// let camera = Camera::new(400.0, 400.0, 15.5, 15.5, 32, 32, 1000.0).unwrap();
    /// let mut depth = DepthImage::new(32, 32);
    /// for v in 0..32 { for u in 0..32 { depth.set(u, v, 4.0); } }
    /// let frame = Frame { index: 0, timestamp: 0.0, depth, pose: Pose::identity(), camera, noise: None };
    /// assert!(Projector::pays_off(&frame, 0.02)); // 2 cm voxels cover 2.7 pixels at 4 m
    /// assert!(!Projector::pays_off(&frame, 0.01)); // 1 cm voxels: 1.3 pixels
    /// ```
    pub fn pays_off(frame: &Frame, resolution: f64) -> bool {
        let dense = dense_range(&frame.camera, resolution) as f32;
        // A sample of the pixels is plenty to see where most depths lie.
        let (mut near, mut far) = (0usize, 0usize);
        for z in frame.depth.data().iter().step_by(7).filter(|z| DepthImage::is_valid(**z)) {
            if *z <= dense { near += 1 } else { far += 1 }
        }
        near >= far
    }

    /// The voxels of grid resolution `resolution` that the valid pixels of `frame` cross
    /// within `limits` (OctoMap's segments, [`RayLimits::hit_miss_segment`], each from its
    /// start to its end, the end voxel included), and the voxels holding the segment ends that
    /// are measured surfaces.
    ///
    /// With `keep`, boxes of voxels outside it are not looked at (the voxels inside are the
    /// same: whether a box is crossed depends on the box alone), though some outside may be
    /// returned.
    ///
    /// With `settled`, which gives per brick the voxels whose crossing the caller does not
    /// need to know, those voxels are left open: each may or may not be in `crossed`. Voxels
    /// holding a measured surface are never left open. The log-odds engine leaves open the
    /// voxels already at its lower clamp, which a miss leaves as they are; skipping their
    /// tests made a 211-frame build 0.6x the time at 0.02 m (BENCHMARKS.md, session 39).
    pub fn crossed_voxels(
        &mut self,
        frame: &Frame,
        limits: &RayLimits,
        resolution: f64,
        keep: Option<&Aabb>,
        settled: Option<&(dyn Fn(BrickKey) -> SlotMask + Sync)>,
    ) -> CrossedVoxels {
        let rays = FrameRays::with_camera_rays(frame, &mut self.camera_rays);
        // (The two largest parallel steps are watched for a worker left waiting behind this
        // thread: `placement`.)
        let ends = self.segments.fill(&rays, limits, resolution, &Step::start());
        let Some((view, root)) = View::over(&rays, &self.segments, limits, resolution, keep) else {
            return CrossedVoxels::default();
        };
        // The split down to bricks takes its largest boxes in parallel; the voxel-level work
        // of each undecided brick is independent, so bricks go to the thread pool.
        let mut crossed = Vec::new();
        let mut undecided = Vec::new();
        view.split_bricks(root, &mut crossed, &mut undecided);
        // The surfaces' voxels by brick: an undecided voxel among them needs no exact test, as
        // a voxel both crossed and a surface in one frame counts as a surface.
        // (Gathered on the pool's threads, a map per task, then merged: a frame has about five
        // times as many ends as surface voxels, 131 k on coffin-world at 0.05 m, where copying
        // them into one list and gathering them serially made a frame 1.07x as long.)
        let ends_by_brick: FxHashMap<BrickKey, SlotMask> = ends
            .par_iter()
            .fold(FxHashMap::default, |mut by_brick: FxHashMap<BrickKey, SlotMask>, rows| {
                for key in rows {
                    mask_set(by_brick.entry(key.brick()).or_default(), key.slot());
                }
                by_brick
            })
            .reduce(FxHashMap::default, |a, b| {
                let (mut big, small) = if a.len() >= b.len() { (a, b) } else { (b, a) };
                for (key, m) in small {
                    let all = big.entry(key).or_default();
                    (0..8).for_each(|w| all[w] |= m[w]);
                }
                big
            });
        let step = Step::start();
        crossed.par_extend(undecided.into_par_iter().filter_map(|(brick, footprint)| {
            step.job();
            let mut mask = [0u64; 8];
            let surface = ends_by_brick.get(&brick).copied().unwrap_or_default();
            // (A surface is never left open: its voxel is a hit.)
            let open: SlotMask = settled.map_or([0; 8], |f| {
                let s = f(brick);
                std::array::from_fn(|w| s[w] & !surface[w])
            });
            if open == [u64::MAX; 8] {
                return None;
            }
            if footprint.rect.area() <= WALK_MAX_PIXELS || !footprint.dense {
                mask = view.walk_brick(brick, &footprint);
            } else {
                view.split_voxels(Box3::of_brick(brick), &surface, &open, &mut mask);
            }
            (mask != [0; 8]).then_some((brick, mask))
        }));
        CrossedVoxels { crossed, ends: ends_by_brick.into_iter().collect() }
    }
}

/// The distance within which every voxel's image holds a pixel centre: a voxel's image holds
/// the image of its inscribed ball, which holds a disc of radius `f (r / 2) / distance`, and
/// a disc of radius `1 / sqrt(2)` holds a pixel centre (0.75 keeps a margin).
fn dense_range(camera: &Camera, resolution: f64) -> f64 {
    camera.fx.abs().min(camera.fy.abs()) * 0.5 * resolution / 0.75
}

/// Undecided bricks seen by at most this many pixels, or too far for splitting to find whole
/// boxes crossed (see [`Footprint::dense`]), have their rays walked instead of being split:
/// where rays are sparser than voxels walking costs about a voxel per ray, while splitting
/// would test most voxels one by one. Chosen on icl-livingroom-5 and coffin-world at 0.05 to
/// 0.01 m (64 beat 256, 1024 and 4096 pixels).
const WALK_MAX_PIXELS: usize = 64;

/// The relative margin by which the walk's and the block tests' bounds are widened before
/// they rule anything out: far beyond the rounding of their f32 depths and products (2^-24),
/// so they never rule out what an exact computation would keep.
const WIDEN: f64 = 1e-5;

/// Boxes of more than this many voxels (256 bricks) are split down to bricks in parallel.
/// Chosen on two threads against 32 and 2,048 bricks (`mrfmap bench`, 4 rounds: medians
/// 13.2 / 13.7 / 13.1 ms a frame on coffin-world 0.05 m, 2.79 / 2.89 / 2.95 on
/// icl-livingroom-5 0.05 m, 9.4 / 9.5 / 10.0 at 0.02 m).
const PARALLEL_SPLIT_VOXELS: i64 = 256 * (BRICK_EDGE as i64).pow(3);

/// Whether each of `N` pixels' segments passes through the box `lo`..`hi` (relative to the
/// camera): the slab test in camera depth, lane by lane with no branch, so that a row of
/// pixels runs in SIMD lanes. `inv_dirs[a][j]` is the reciprocal of component `a` of lane `j`'s
/// world direction per metre of camera depth. A pixel without a segment (start after end)
/// never passes.
#[inline(always)]
fn slabs_cross<const N: usize>(
    depths: &[PixelDepths; N],
    inv_dirs: &[[f32; N]; 3],
    lo: &[f32; 3],
    hi: &[f32; 3],
) -> [bool; N] {
    let mut t0: [f32; N] = std::array::from_fn(|j| depths[j].0[0]);
    let mut t1: [f32; N] = std::array::from_fn(|j| depths[j].0[1]);
    for a in 0..3 {
        for j in 0..N {
            let (ta, tb) = (lo[a] * inv_dirs[a][j], hi[a] * inv_dirs[a][j]);
            t0[j] = t0[j].max(ta.min(tb));
            t1[j] = t1[j].min(ta.max(tb));
        }
    }
    std::array::from_fn(|j| t0[j] < t1[j])
}

/// The depth pyramid's first level is of blocks of `BLOCK x BLOCK` pixels. The exact tests
/// skip blocks that all miss a voxel's depths, and test the rest a block's row of pixels at a
/// time, in lanes. Blocks of 8 x 8 pixels (eight lanes) took 1.1x the time.
const BLOCK: usize = 4;

/// The smaller of two numbers that are never NaN here: one instruction, where `f32::min`
/// spends several on NaN handling (the pyramid and the box tests are made of these).
#[inline]
fn min<T: PartialOrd>(a: T, b: T) -> T {
    if b < a { b } else { a }
}

/// The larger of two numbers that are never NaN here (see [`min`]).
#[inline]
fn max<T: PartialOrd>(a: T, b: T) -> T {
    if b > a { b } else { a }
}

/// What the pixels that can see a box do there.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Seen {
    /// No segment reaches into the box.
    None,
    /// Every voxel of the box is crossed by some segment.
    All,
    /// Undecided: split the box.
    Some,
}

/// Per-pixel segments and their depth pyramid.
#[derive(Clone, Debug, Default)]
struct Segments {
    width: usize,
    height: usize,
    /// Each pixel's segment end in camera depth, and its start: level 0 of the depth pyramid
    /// ([`Segments::pixel`]). Without bounds every segment starts at the camera, and `starts`
    /// is empty: 4 bytes a pixel less, which pays for the frame that a build reads ahead.
    ends: Vec<f32>,
    starts: Vec<f32>,
    /// Depth bounds per pyramid level 2, 3, ... (`levels[k - 2]`: blocks of `2^k x 2^k`; the
    /// first is of [`BLOCK`] x [`BLOCK`] pixels). Level 1 is not kept: its 4 bytes a pixel were
    /// a fifth of a small build's heap, and a rectangle of at most 3 x 3 pixels, which it
    /// served, is read from the pixels instead.
    levels: Vec<Level>,
}

/// One pixel's segment in camera z, `[start, end]`: the pyramid's level 0. Its [`Bounds`]
/// (one pixel's four bounds are two numbers twice) are made when read, so it takes at most 8
/// bytes a pixel in [`Segments`] where they took 16. A pixel with no segment and no start
/// stored reads as `[0, -inf]`: [`PixelDepths::miss`] and the slab test treat it as
/// [`PixelDepths::NONE`], and in [`Bounds`] it differs only in the start bounds of a set of
/// pixels that all have none, which every box misses by its end bounds first. (The slab tests
/// need the pixel's direction too, which [`View::inv_dirs`] makes from its column and row:
/// stored per pixel, it took 12 bytes more.)
#[derive(Clone, Copy, Debug)]
struct PixelDepths([f32; 2]);

impl PixelDepths {
    /// No segment: as bounds, [`Bounds::NO_SEGMENT`] exactly.
    const NONE: PixelDepths = PixelDepths([f32::INFINITY, f32::NEG_INFINITY]);

    /// [`Bounds::miss`] of this pixel alone.
    #[inline]
    fn miss(self, z_near: f32, z_far: f32) -> bool {
        let [start, end] = self.0;
        end <= z_near || start >= z_far
    }
}

impl From<PixelDepths> for Bounds {
    #[inline]
    fn from(d: PixelDepths) -> Bounds {
        Bounds::segment(d.0[0], d.0[1])
    }
}

/// One level of the depth pyramid: per cell the bounds of `2^k x 2^k` pixels.
#[derive(Clone, Debug, Default)]
struct Level {
    width: usize,
    cells: Vec<Bounds>,
}

/// Camera-z bounds of the segments of a set of pixels: `[end_min, -end_max, start_min,
/// -start_max]`, the larger bounds negated so that merging two sets is a minimum per lane,
/// which the compiler vectorises (the pyramid reads and builds are made of merges; with a
/// minimum or maximum per named field they took 4% more instructions per projected frame).
/// - `end_min`: smallest end depth; `-inf` if any pixel has no segment (such a set cannot
///   see a box whole).
/// - `end_max`: largest end depth (`-inf` if no pixel has a segment).
/// - `start_min`: smallest start depth (`+inf` if no pixel has a segment).
/// - `start_max`: largest start depth; `+inf` if any pixel has no segment.
#[derive(Clone, Copy, Debug)]
struct Bounds([f32; 4]);

impl Bounds {
    const NO_SEGMENT: Bounds = Bounds([f32::NEG_INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY]);
    /// The bounds of no pixels: merging it changes nothing.
    const EMPTY: Bounds = Bounds([f32::INFINITY; 4]);

    /// One pixel's segment from camera depth `start` to `end`.
    fn segment(start: f32, end: f32) -> Bounds {
        Bounds([end, -end, start, -start])
    }

    fn end_min(&self) -> f32 {
        self.0[0]
    }

    fn end_max(&self) -> f32 {
        -self.0[1]
    }

    fn start_min(&self) -> f32 {
        self.0[2]
    }

    fn start_max(&self) -> f32 {
        -self.0[3]
    }

    /// No segment of these pixels reaches into camera depths `(z_near, z_far)`: they all end
    /// before it or start behind it.
    #[inline]
    fn miss(&self, z_near: f32, z_far: f32) -> bool {
        self.end_max() <= z_near || self.start_min() >= z_far
    }

    #[inline]
    fn union(self, o: Bounds) -> Bounds {
        Bounds(std::array::from_fn(|i| min(self.0[i], o.0[i])))
    }
}

impl Segments {
    /// Fills the buffers for `frame`; returns the voxels of the segment ends that are
    /// measured surfaces, a list per block of rows ([`Segments::fill_with`]). Each row runs
    /// in [`segments_row_avx512`] on a processor with AVX-512, in [`segments_row_avx2`] on
    /// one with AVX2.
    fn fill(&mut self, rays: &FrameRays, limits: &RayLimits, resolution: f64, step: &Step) -> Vec<Vec<VoxelKey>> {
        #[cfg(target_arch = "x86_64")]
        let avx2 = std::is_x86_feature_detected!("avx2");
        #[cfg(target_arch = "x86_64")]
        let avx512 = has_avx512();
        self.fill_with(rays.size(), limits.bounds.is_some(), |v, pixels, ends, above| {
            step.job();
            let cut = limits.bounds.is_none() && limits.max_range.is_some_and(|m| rays.row_may_cut(v as u32, m));
            #[cfg(target_arch = "x86_64")]
            if avx512 {
                // SAFETY: the processor has AVX-512 (x86-64-v4), checked above.
                return unsafe {
                    match cut {
                        true => segments_row_avx512::<true>(rays, limits, resolution, v, pixels, ends, above),
                        false => segments_row_avx512::<false>(rays, limits, resolution, v, pixels, ends, above),
                    }
                };
            }
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the processor has AVX2, checked above.
                return unsafe {
                    match cut {
                        true => segments_row_avx2::<true>(rays, limits, resolution, v, pixels, ends, above),
                        false => segments_row_avx2::<false>(rays, limits, resolution, v, pixels, ends, above),
                    }
                };
            }
            match cut {
                true => segments_row_baseline::<true>(rays, limits, resolution, v, pixels, ends, above),
                false => segments_row_baseline::<false>(rays, limits, resolution, v, pixels, ends, above),
            }
        })
    }

    /// Fills the buffers for an image of `width x height` pixels, row `v` by
    /// `fill_row(v, pixels, ends, above)`: it sets the segments of the row's `pixels` (which
    /// start with none; with `starts` false every segment it sets must start at 0) and adds
    /// the voxels of their surface ends to `ends` with [`note_ends`] or [`note_end`] (`above`
    /// holds the row above's, kept from row to row by each task). Returns the ends, a list per
    /// block of [`BLOCK`] rows in order (each block's task makes one: gathering them needs no
    /// copy into one list).
    fn fill_with<F>(&mut self, (width, height): (usize, usize), starts: bool, fill_row: F) -> Vec<Vec<VoxelKey>>
    where
        F: Fn(usize, PixelRow<'_>, &mut Vec<VoxelKey>, &mut AboveEnds) + Sync,
    {
        self.shape((width, height), starts);
        let start_chunks: Vec<Option<&mut [f32]>> = if starts {
            self.starts.chunks_mut(BLOCK * width).map(Some).collect()
        } else {
            (0..height.div_ceil(BLOCK)).map(|_| None).collect()
        };
        let blocks = &mut self.levels[0];
        // `BLOCK` rows at a time, so each task also makes its row of blocks while the rows are
        // in cache (as a separate pass it cost as much as a tenth of the setup): two rows of
        // 2 x 2 blocks first (in a buffer of the task's), then the row of 4 x 4 ones.
        const { assert!(BLOCK == 4, "blocks are made from 2 x 2 ones in one step") };
        let half = width.div_ceil(2);
        let ends = self
            .ends
            .par_chunks_mut(BLOCK * width)
            .zip(start_chunks)
            .zip(blocks.cells.par_chunks_mut(blocks.width))
            .enumerate()
            .map_init(
                // (The end voxels of the row above, kept from row to row.)
                || (Vec::new(), AboveEnds::new(width)),
                |(pairs, above), (chunk, ((ends_of, mut starts_of), block_row))| {
                    let mut ends = Vec::new();
                    for (dv, e) in ends_of.chunks_mut(width).enumerate() {
                        // No segment unless the row's filler gives one (a fill the compiler
                        // vectorises, where filling the gaps between valid pixels took
                        // bookkeeping per pixel).
                        e.fill(f32::NEG_INFINITY);
                        let s = starts_of.as_deref_mut().map(|s| {
                            let s = &mut s[dv * width..(dv + 1) * width];
                            s.fill(f32::INFINITY);
                            s
                        });
                        fill_row(BLOCK * chunk + dv, PixelRow { ends: e, starts: s }, &mut ends, above);
                    }
                    // (The last chunk may have fewer rows: a missing row pairs with its
                    // neighbour, as in `reduce_rows`.)
                    let rows = ends_of.len() / width;
                    let pair = |dv: usize, out: &mut [Bounds]| {
                        let (upper, lower) = (dv * width, (dv + 1).min(rows - 1) * width);
                        match starts_of.as_deref() {
                            Some(s) => reduce_rows(
                                width,
                                |x| Bounds::segment(s[upper + x], ends_of[upper + x]),
                                |x| Bounds::segment(s[lower + x], ends_of[lower + x]),
                                out,
                            ),
                            None => reduce_rows(
                                width,
                                |x| Bounds::segment(0.0, ends_of[upper + x]),
                                |x| Bounds::segment(0.0, ends_of[lower + x]),
                                out,
                            ),
                        }
                    };
                    pairs.resize(2 * half, Bounds::NO_SEGMENT);
                    let (first, second) = pairs.split_at_mut(half);
                    pair(0, first);
                    if rows > 2 {
                        pair(2, second);
                        reduce_rows(half, |x| first[x], |x| second[x], block_row);
                    } else {
                        reduce_rows(half, |x| first[x], |x| first[x], block_row);
                    }
                    ends
                },
            )
            .collect();
        self.build_pyramid();
        ends
    }

    /// Pixel `i`'s segment (row by row).
    #[inline(always)]
    fn pixel(&self, i: usize) -> PixelDepths {
        PixelDepths([self.starts.get(i).copied().unwrap_or(0.0), self.ends[i]])
    }

    /// The segments of pixels `u0..u1` (at most [`BLOCK`]) of row `v` that may reach camera
    /// depths `(z_near, z_far)` ([`PixelDepths::miss`]), as lanes; the others, and the lanes
    /// past `u1`, [`PixelDepths::NONE`]. (A branch-free read of all four lanes took 1.006x
    /// the time of a coffin-world frame at 0.05 m, BENCHMARKS.md, session 50.)
    #[inline(always)]
    fn row_lanes(&self, (u0, u1): (usize, usize), v: usize, (z_near, z_far): (f32, f32)) -> [PixelDepths; BLOCK] {
        let mut lanes = [PixelDepths::NONE; BLOCK];
        for (j, lane) in lanes[..u1 - u0].iter_mut().enumerate() {
            let p = self.pixel(v * self.width + u0 + j);
            if !p.miss(z_near, z_far) {
                *lane = p;
            }
        }
        lanes
    }

    /// Largest end depth over all pixels (`None` without segments).
    fn deepest(&self) -> Option<f32> {
        let top = self.levels.last()?.cells.first()?.end_max();
        (top > 0.0).then_some(top)
    }

    /// Bounds of the pixels in `rect` (of a superset of them: the pyramid level is chosen
    /// so at most 3 x 3 cells cover the rectangle).
    /// (Inlined into [`View::judge`]: as a call returning its 16 bytes through memory it was a
    /// tenth of a projected frame, and inlined the frame took 0.96-0.98x the time.)
    #[inline(always)]
    fn bounds(&self, rect: &Rect) -> Bounds {
        let Rect { u0, u1, v0, v1 } = *rect;
        let span = (u1 - u0 + 1).max(v1 - v0 + 1);
        let k = ((usize::BITS - 1 - span.leading_zeros()) as usize).min(self.levels.len() + 1);
        let mut b = Bounds::EMPTY;
        if k < 2 {
            for v in v0..v1 + 1 {
                for u in u0..u1 + 1 {
                    b = b.union(self.pixel(v * self.width + u).into());
                }
            }
            return b;
        }
        let level = &self.levels[k - 2];
        // (Half-open ranges: the end checks of inclusive ones were 1% of a projected frame.)
        for cv in (v0 >> k)..(v1 >> k) + 1 {
            for cu in (u0 >> k)..(u1 >> k) + 1 {
                b = b.union(level.cells[cv * level.width + cu]);
            }
        }
        b
    }

    /// Levels 3, 4, ... of the min/max pyramid, down to one block (reusing the previous
    /// frame's buffers).
    fn build_pyramid(&mut self) {
        for k in 1..self.levels.len() {
            let (lower, upper) = self.levels.split_at_mut(k);
            let (prev, next) = (&lower[k - 1], &mut upper[0]);
            let w = prev.width;
            next.cells.par_chunks_mut(next.width).zip(prev.cells.par_chunks(2 * w)).for_each(|(row, pair)| {
                let (upper, lower) = pair.split_at(w);
                let lower = if lower.is_empty() { upper } else { lower };
                reduce_rows(w, |x| upper[x], |x| lower[x], row);
            });
        }
    }

    /// Sizes the buffers for an image of `width x height` pixels, with or without `starts`:
    /// the pixels' depths, and the pyramid's levels from blocks of [`BLOCK`] x [`BLOCK`]
    /// pixels halving down to one cell. Each frame's filling writes every value, so only a
    /// new size allocates (and the pages of a new buffer are first touched here, not in the
    /// middle of a frame: zeroing them on each page fault took a fifth of a first frame at
    /// 640 x 480, BENCHMARKS.md, session 48).
    fn shape(&mut self, (width, height): (usize, usize), starts: bool) {
        (self.width, self.height) = (width, height);
        self.ends.resize(width * height, f32::NEG_INFINITY);
        if starts {
            self.starts.resize(width * height, f32::INFINITY);
        } else {
            self.starts = Vec::new();
        }
        let (mut k, mut w, mut h) = (0, width.div_ceil(BLOCK), height.div_ceil(BLOCK));
        loop {
            if self.levels.len() == k {
                self.levels.push(Level::default());
            }
            let level = &mut self.levels[k];
            level.width = w;
            level.cells.resize(w * h, Bounds::NO_SEGMENT);
            if w <= 1 && h <= 1 {
                break;
            }
            (k, w, h) = (k + 1, w.div_ceil(2), h.div_ceil(2));
        }
        self.levels.truncate(k + 1);
    }
}

/// Defines under `$name` the filling of row `v` of [`Segments`] (see [`Segments::fill`]): one
/// source for the copy built for the binary's baseline and the copy built for AVX2, whose
/// closures and lane loops (the plain pixels' ranges, depths and end voxels,
/// [`FrameRays::row_plain`], and which end voxels are new, [`note_ends`]) are compiled with its
/// features (closures in a shared inlined body would not be). The same values bit for bit: no
/// fused multiply-adds. `$floor` says whether the copy's features have `floor` as one
/// instruction ([`crate::map::floor_i32_lanes`]).
///
/// With `CUT` (only without bounds), the readings beyond the max range are cut in lanes too
/// ([`FrameRays::row_cut`]); without, one ray at a time. Two copies, not one with a test:
/// with the cut's code in it, the loop over rows that have no reading beyond the max range
/// took 2.5-5% longer (BENCHMARKS.md, session 34), so such rows keep the copy without it.
macro_rules! segments_row {
    ($(#[$attr:meta])* $name:ident, floor instruction: $floor:literal) => {
        $(#[$attr])*
        fn $name<const CUT: bool>(
            rays: &FrameRays,
            limits: &RayLimits,
            resolution: f64,
            v: usize,
            mut pixels: PixelRow<'_>,
            ends: &mut Vec<VoxelKey>,
            above: &mut AboveEnds,
        ) {
            let inv_r = 1.0 / resolution;
            // A ray's segment as the pixel's depths, with its end (voxel units) if that is a
            // measured surface.
            let segment = |ray: &PixelRay| {
                let seg = limits.hit_miss_segment(ray, resolution)?;
                let end = seg.hits_surface.then(|| [0, 1, 2].map(|a| (ray.origin[a] + seg.end * ray.dir[a]) * inv_r));
                Some((PixelDepths([(seg.start * ray.cz) as f32, (seg.end * ray.cz) as f32]), end))
            };
            // Without bounds, a reading within the max range is the segment from the camera
            // to it ([`RayLimits::hit_miss_segment`]): most pixels, computed in lanes (the
            // per-pixel rays were a third of a projected frame at 0.05 m). Every segment then
            // starts at the camera: only its end is kept.
            let max_range = limits.max_range.unwrap_or(f64::INFINITY);
            let v = v as u32;
            let plain = limits.bounds.is_none() && {
                let (row_ends, mut last_key) = (&mut *pixels.ends, None);
                let plain = rays.row_plain::<$floor>(v, max_range, inv_r, |start, b| {
                    // (The other pixels' ends are -inf, no segment: a copy where a branch per
                    // pixel was a sixth of a long sequence's row filling.)
                    row_ends[start..start + b.len].copy_from_slice(&b.z_end[..b.len]);
                    if !CUT && b.valid[..b.len] != b.plain[..b.len] {
                        // (Cut by the max range: no surface. With `CUT`, set by `row_cut`.)
                        for k in (0..b.len).filter(|k| b.valid[*k] & !b.plain[*k]) {
                            let ray = rays.ray((start + k) as u32, v);
                            if let Some((depths, _)) = ray.as_ref().and_then(segment) {
                                row_ends[start + k] = depths.0[1];
                            }
                        }
                    }
                    note_ends(start, b, &mut last_key, above, ends);
                });
                if CUT {
                    rays.row_cut(v, limits, resolution, row_ends);
                }
                plain
            };
            if !plain {
                let mut last = None;
                for ray in rays.row(v) {
                    if let Some((depths, end)) = segment(&ray) {
                        let u = ray.u as usize;
                        pixels.set(u, depths);
                        if let Some(q) = end {
                            note_end(u, q, &mut last, above, ends);
                        }
                    }
                }
            }
        }
    };
}

segments_row!(
    /// [`segments_row!`] for any processor.
    segments_row_baseline,
    floor instruction: false
);

segments_row!(
    /// [`segments_row!`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    segments_row_avx2,
    floor instruction: true
);

segments_row!(
    /// [`segments_row!`] compiled for AVX-512 (x86-64-v4's set, [`has_avx512`]): its lanes
    /// eight values wide where AVX2's are four. On this project's machines (AMD EPYC),
    /// icl-livingroom-5 frames at 0.05 m took 0.94x the time of the AVX2 copy's
    /// (BENCHMARKS.md, session 44). (The voxels' splitting compiled so took 1.03-1.06x the
    /// time: it stays with AVX2.)
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512bw,avx512cd,avx512dq,avx512vl")]
    segments_row_avx512,
    floor instruction: true
);

/// Whether the processor has AVX-512 as x86-64-v4 has it (F, BW, CD, DQ and VL), which
/// [`segments_row_avx512`] is compiled for.
#[cfg(target_arch = "x86_64")]
fn has_avx512() -> bool {
    std::is_x86_feature_detected!("avx512f")
        && std::is_x86_feature_detected!("avx512bw")
        && std::is_x86_feature_detected!("avx512cd")
        && std::is_x86_feature_detected!("avx512dq")
        && std::is_x86_feature_detected!("avx512vl")
}

/// Defines under `$name` the splitting of an undecided box inside one brick down to voxels,
/// setting the crossed ones in `mask`: those in `surface` (the brick's measured surfaces) as
/// they are, those in `settled` not at all (see [`Projector::crossed_voxels`]; a half made of
/// such voxels and surfaces is not judged), the others by
/// the exact test ([`View::voxel_crossed`]). A box's eight halves are judged together, unless
/// they are voxels: their corners are 27 points, not 64. A half holding a surface is split
/// unjudged: a segment ends in it, so it is seen and not seen through, and judging it cost
/// more than it told (a third of the halves judged on coffin-world at 0.05 m held a surface;
/// without their judging a frame took 0.973x the time, BENCHMARKS.md, session 50). A half the
/// pyramid leaves undecided
/// and that holds no surface gets the exact test as a whole before it is split: behind a
/// surface, most undecided voxels lie in halves no segment enters, and one test of the half
/// settles its eight voxels (or 64) at once. One source
/// for the copy built for the binary's baseline and the copy built for AVX2, picked at run
/// time by [`View::split_voxels`]; the recursion stays in its copy, and the exact test
/// is inlined into it (compiled with its features: its divisions and slab tests four lanes
/// wide). The AVX2 copy took 0.94-0.97x the time of a frame at 0.02 m (BENCHMARKS.md, "Log-odds
/// engine vs wavemap", session 35).
macro_rules! split_voxels {
    ($(#[$attr:meta])* $name:ident) => {
        impl View<'_> {
            $(#[$attr])*
            fn $name(&self, b: Box3, surface: &SlotMask, settled: &SlotMask, mask: &mut SlotMask) {
                let half = (b.hi[0] - b.lo[0]) / 2;
                let settled_or_surface: SlotMask = std::array::from_fn(|w| settled[w] | surface[w]);
                let origin = self.corner_at(b.lo);
                // (Loops, not `map` with a closure: the compiler may leave a closure a function
                // of its own, outside the processor copy, and did once, called per axis.)
                let mut step = self.step;
                for c in step.iter_mut().flatten() {
                    *c *= half as f64;
                }
                // Corner (i, j, k) of the 3 x 3 x 3 lattice is `lattice[i + 3 j + 9 k]` (nested loops:
                // the index arithmetic of one loop over 27 was a twentieth of a projected frame).
                let mut lattice = [Corner::default(); 27];
                for k in 0..3 {
                    for j in 0..3 {
                        for i in 0..3 {
                            let (fi, fj, fk) = (i as f64, j as f64, k as f64);
                            let p = |c: usize| origin[c] + fi * step[0][c] + fj * step[1][c] + fk * step[2][c];
                            lattice[i + 3 * j + 9 * k] = self.corner([p(0), p(1), p(2)]);
                        }
                    }
                }
                for (octant, first) in LOWER_CORNERS.into_iter().enumerate() {
                    let (i, j, k) = (octant & 1, octant >> 1 & 1, octant >> 2);
                    let lo = [b.lo[0] + i as i32 * half, b.lo[1] + j as i32 * half, b.lo[2] + k as i32 * half];
                    let corners = LOWER_CORNERS.iter().map(|c| &lattice[first + c]);
                    if half == 1 {
                        // A voxel is not judged: the exact test reads the same depth bounds block by
                        // block of its footprint first, and reading them for the whole footprint as
                        // well cost more than the voxels that decided (a frame took 0.92-0.96x the
                        // time without).
                        let slot = VoxelKey(lo).slot();
                        if mask_has(settled, slot) {
                            continue;
                        }
                        let voxel = Box3 { lo, hi: lo.map(|x| x + 1) };
                        let diagonal = (&lattice[first], &lattice[first + 13]);
                        if mask_has(surface, slot) || self.voxel_crossed(&voxel, diagonal, corners) {
                            mask_set(mask, slot);
                        }
                        continue;
                    }
                    let child = Box3 { lo, hi: lo.map(|x| x + half) };
                    // (A cube of open voxels and surfaces needs no test: its surfaces are set.)
                    if cube_within(&child, &settled_or_surface) {
                        cube_set(&child, surface, mask);
                        continue;
                    }
                    // (A half holding a surface: split unjudged, above.)
                    if cube_meets(&child, surface) {
                        self.$name(child, surface, settled, mask);
                        continue;
                    }
                    // (Inside a brick that `split_voxels` was called for, every box is dense.)
                    match self.judge(corners, true) {
                        (Seen::None, _) => {}
                        // (A seen box always has a footprint; without one, it is split untested.)
                        (Seen::Some, f) => {
                            if f.is_none_or(|f| self.box_crossed(&child, &f.rect, f.depths, f.centre)) {
                                self.$name(child, surface, settled, mask)
                            }
                        }
                        (Seen::All, _) => cube_set(&child, &[u64::MAX; 8], mask),
                    }
                }
            }
        }
    };
}

split_voxels!(
    /// [`split_voxels!`] for any processor.
    split_voxels_baseline
);

split_voxels!(
    /// [`split_voxels!`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    split_voxels_avx2
);

/// Defines under `$name` [`View::walk_brick`]'s work, in one source for the copy built for
/// the binary's baseline and the copy built for AVX2 (where a block's row of rays is set up
/// in four lanes, and `floor` is one instruction, not a call).
macro_rules! walk_brick {
    ($(#[$attr:meta])* $name:ident) => {
        impl View<'_> {
            $(#[$attr])*
            fn $name(&self, brick: BrickKey, fp: &Footprint) -> SlotMask {
                let (rect, mut mask, b) = (&fp.rect, [0u64; 8], Box3::of_brick(brick));
                let (lo, hi) = self.relative(&b);
                let ((z_near, z_far), widen) = (fp.depths, WIDEN as f32);
                let (z_near, z_far) = (z_near - z_near.abs() * widen, z_far + z_far.abs() * widen);
                let walk = self.brick_walk(&b);
                let _ = self.blocks_reaching(rect, (z_near, z_far), &lo, &hi, #[inline(always)] |(u0, u1), v| {
                    let lanes = self.seg.row_lanes((u0, u1), v, (z_near, z_far));
                    if lanes.iter().any(|p| p.0[0] <= p.0[1]) {
                        self.walk_pixels(&walk, (u0, v), &lanes, &mut mask);
                    }
                    ControlFlow::Continue(())
                });
                mask
            }
        }
    };
}

walk_brick!(
    /// [`walk_brick!`] for any processor.
    walk_brick_baseline
);

walk_brick!(
    /// [`walk_brick!`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    walk_brick_avx2
);

/// The voxels of `b`, a cube inside one brick, as a mask per z-layer: `(bits, z range)`, the
/// same `bits` (its rows of voxels) in each of the brick's layers (mask words) in the range.
#[inline(always)]
fn cube_layers(b: &Box3) -> (u64, std::ops::Range<usize>) {
    let edge = (b.hi[0] - b.lo[0]) as u32;
    let l = b.lo.map(|x| (x & (BRICK_EDGE - 1)) as u32);
    let row = ((1u64 << edge) - 1) << l[0];
    let bits = (0..edge).fold(0u64, |m, y| m | row << (8 * (l[1] + y)));
    (bits, l[2] as usize..(l[2] + edge) as usize)
}

/// Whether some voxel of `b`, a cube inside one brick, is in `mask`.
#[inline(always)]
fn cube_meets(b: &Box3, mask: &SlotMask) -> bool {
    let (bits, layers) = cube_layers(b);
    mask[layers].iter().any(|w| w & bits != 0)
}

/// Sets the voxels of `b`, a cube inside one brick, that are in `of`, in `mask`.
#[inline(always)]
fn cube_set(b: &Box3, of: &SlotMask, mask: &mut SlotMask) {
    let (bits, layers) = cube_layers(b);
    mask[layers.clone()].iter_mut().zip(&of[layers]).for_each(|(w, o)| *w |= bits & o);
}

/// Whether every voxel of `b`, a cube inside one brick, is in `mask`.
#[inline(always)]
fn cube_within(b: &Box3, mask: &SlotMask) -> bool {
    let (bits, layers) = cube_layers(b);
    mask[layers].iter().all(|w| w & bits == bits)
}

/// One row of the next pyramid level from two rows of this one, `w` wide, read by `upper(x)`
/// and `lower(x)` (`lower` is `upper` again for an odd last row; an odd last column pairs with
/// itself).
#[inline(always)]
fn reduce_rows(w: usize, upper: impl Fn(usize) -> Bounds, lower: impl Fn(usize) -> Bounds, out: &mut [Bounds]) {
    for (x, cell) in out.iter_mut().enumerate() {
        let x1 = (2 * x + 1).min(w - 1);
        *cell = upper(2 * x).union(upper(x1)).union(lower(2 * x)).union(lower(x1));
    }
}

/// One row of [`Segments`]' pixels, as [`Segments::fill_with`] hands it to be filled.
struct PixelRow<'a> {
    ends: &'a mut [f32],
    /// `None` where every segment starts at the camera.
    starts: Option<&'a mut [f32]>,
}

impl PixelRow<'_> {
    /// Sets pixel `u`'s segment.
    #[inline(always)]
    fn set(&mut self, u: usize, depths: PixelDepths) {
        self.ends[u] = depths.0[1];
        match &mut self.starts {
            Some(s) => s[u] = depths.0[0],
            None => debug_assert_eq!(depths.0[0], 0.0, "a segment not from the camera, with no starts kept"),
        }
    }
}

/// Per column, the end voxel of the nearest row above with a surface there, as a filling
/// task keeps them from row to row (by axis, so that a block of columns reads as lanes).
#[derive(Clone, Debug, Default)]
struct AboveEnds {
    key: [Vec<i32>; 3],
    has: Vec<bool>,
}

impl AboveEnds {
    fn new(width: usize) -> Self {
        AboveEnds { key: std::array::from_fn(|_| vec![0; width]), has: vec![false; width] }
    }

    fn get(&self, u: usize) -> Option<[i32; 3]> {
        self.has[u].then(|| self.key.each_ref().map(|k| k[u]))
    }

    fn set(&mut self, u: usize, key: [i32; 3]) {
        for (k, x) in self.key.iter_mut().zip(key) {
            k[u] = x;
        }
        self.has[u] = true;
    }
}

/// Adds to `ends` the voxel holding the segment end at `q` (voxel units) of column `u`,
/// unless it is `last`'s (the end voxel of the pixel to the left: its key and its lower
/// corner) or the column's in [`AboveEnds`], and makes it both. Neighbouring pixels mostly end
/// in the same voxel, so each voxel goes into `ends` about once, not once a pixel (skipping
/// one is right: `last` and the one above went in, or were skipped for the same reason,
/// earlier); and mostly in the voxel to their left, which is cheaper to check than three
/// floors (`floor(q) == e` exactly when `e <= q < e + 1`).
#[inline(always)]
fn note_end(
    u: usize,
    q: [f64; 3],
    last: &mut Option<([i32; 3], [f64; 3])>,
    above: &mut AboveEnds,
    ends: &mut Vec<VoxelKey>,
) {
    if let Some((_, e)) = last
        && (0..3).all(|a| q[a] >= e[a] && q[a] < e[a] + 1.0)
    {
        return;
    }
    let key = q.map(floor_i32);
    if above.get(u) != Some(key) {
        ends.push(VoxelKey(key));
    }
    *last = Some((key, key.map(|k| k as f64)));
    above.set(u, key);
}

/// [`note_end`] for the plain pixels of a block of a row from column `start` (the others
/// have no surface), with `last` the end voxel of the block's left neighbour: whether each is
/// new is decided in lanes, against the pixel just to its left and the row above (a branch
/// per pixel on those comparisons was most of the setup's time).
#[inline(always)]
fn note_ends(
    start: usize,
    b: &PlainBlock,
    last: &mut Option<[i32; 3]>,
    above: &mut AboveEnds,
    ends: &mut Vec<VoxelKey>,
) {
    let n = b.len;
    let mut left = [[0i32; PLAIN_COLUMNS]; 3];
    let mut left_has = [false; PLAIN_COLUMNS];
    for (a, l) in left.iter_mut().enumerate() {
        l[0] = last.map_or(0, |k| k[a]);
        l[1..n].copy_from_slice(&b.key[a][..n - 1]);
    }
    left_has[0] = last.is_some();
    left_has[1..n].copy_from_slice(&b.plain[..n - 1]);
    let up = above.key.each_ref().map(|k| &k[start..start + n]);
    let up_has = &above.has[start..start + n];
    let mut new = [false; PLAIN_COLUMNS];
    for k in 0..n {
        let (x, y, z) = (b.key[0][k], b.key[1][k], b.key[2][k]);
        let same_left = left_has[k] & (x == left[0][k]) & (y == left[1][k]) & (z == left[2][k]);
        let same_up = up_has[k] & (x == up[0][k]) & (y == up[1][k]) & (z == up[2][k]);
        new[k] = b.plain[k] & !same_left & !same_up;
    }
    // The new ones' columns as the set bits of a mask, eight flags (bytes of 0 or 1) at a
    // time by a product that gathers their low bits into its top byte: a branch per column
    // on the flags themselves mispredicted (it was an eighth of the row filling).
    const { assert!(PLAIN_COLUMNS == 64, "one bit per column of a u64") };
    let mut columns = 0u64;
    for (i, flags) in new.chunks_exact(8).enumerate() {
        let bytes = u64::from_le_bytes(std::array::from_fn(|j| flags[j] as u8));
        columns |= (bytes.wrapping_mul(0x0102_0408_1020_4080) >> 56) << (8 * i);
    }
    while columns != 0 {
        let k = columns.trailing_zeros() as usize;
        columns &= columns - 1;
        ends.push(VoxelKey([b.key[0][k], b.key[1][k], b.key[2][k]]));
    }
    for (a, k) in above.key.iter_mut().enumerate() {
        k[start..start + n].copy_from_slice(&b.key[a][..n]);
    }
    above.has[start..start + n].copy_from_slice(&b.plain[..n]);
    *last = b.plain[n - 1].then(|| [b.key[0][n - 1], b.key[1][n - 1], b.key[2][n - 1]]);
}

/// Pixels `u0..=u1` by `v0..=v1`.
#[derive(Clone, Copy, Debug)]
struct Rect {
    u0: usize,
    u1: usize,
    v0: usize,
    v1: usize,
}

impl Rect {
    fn area(&self) -> usize {
        (self.u1 - self.u0 + 1) * (self.v1 - self.v0 + 1)
    }

    /// The pixel centres (integer coordinates up to `u_last`, `v_last`) in the ranges
    /// `u = (min, max)`, `v = (min, max)`; `None` if there are none.
    #[inline]
    fn of_pixel_centres(u: (f64, f64), v: (f64, f64), u_last: f64, v_last: f64) -> Option<Rect> {
        // Both ends are clamped into `[0, last + 1]` first, so truncation is floor (a call to
        // libm's floor/ceil here cost 4% of the whole) and the casts are to `u32` (a cast to
        // `usize` spends a dozen instructions on values past 2^63; this one was 3% of a
        // projected frame). A lower end clamped to `last + 1` leaves no pixel, as before.
        let ceil = |x: f64, last: f64| {
            let x = max(x, 0.0).min(last + 1.0);
            let t = x as u32;
            (if (t as f64) < x { t + 1 } else { t }) as usize
        };
        let floor = |x: f64, last: f64| min(x, last).max(0.0) as u32 as usize;
        let (u0, u1) = (ceil(u.0, u_last), floor(u.1, u_last));
        let (v0, v1) = (ceil(v.0, v_last), floor(v.1, v_last));
        (u.1 >= 0.0 && v.1 >= 0.0 && u0 <= u1 && v0 <= v1).then_some(Rect { u0, u1, v0, v1 })
    }
}

/// A box corner in camera coordinates, with the values [`View::judge`] takes extremes of.
#[derive(Clone, Copy, Debug, Default)]
struct Corner {
    x: f64,
    y: f64,
    z: f64,
    /// Pixel coordinates (meaningless unless `z > 0`).
    u: f64,
    v: f64,
}

/// What [`View::footprint`] finds of a box: the rectangle of pixels that may see it, its
/// camera-depth range, whether its image lies wholly inside the image, and the middle of its
/// corners' image if it lies in front of the camera.
type BoxImage = (Rect, (f32, f32), bool, Option<[f32; 2]>);

/// Where a box appears in the image: the pixels that may see it.
#[derive(Clone, Copy, Debug)]
struct Footprint {
    rect: Rect,
    /// The box's camera-depth range.
    depths: (f32, f32),
    /// Near enough that every voxel's image holds a pixel centre.
    dense: bool,
    /// The middle of the box's image, if it lies in front of the camera.
    centre: Option<[f32; 2]>,
}

/// A brick as [`View::walk_pixels`] walks rays through it (see [`View::brick_walk`]).
struct BrickWalk {
    /// The camera relative to the brick's lower corner.
    origin: [f64; 3],
    /// The box the walks are clipped to, relative to the camera.
    lo: [f64; 3],
    hi: [f64; 3],
}

/// A box of voxels: keys `lo..hi` per axis (half-open).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Box3 {
    lo: [i32; 3],
    hi: [i32; 3],
}

impl Box3 {
    fn of_brick(b: BrickKey) -> Self {
        let lo = b.0.map(|i| i * BRICK_EDGE);
        Box3 { lo, hi: lo.map(|i| i + BRICK_EDGE) }
    }

    /// The box in world coordinates, in a grid of voxel edge `resolution`.
    fn aabb(&self, resolution: f64) -> Aabb {
        Aabb { min: self.lo.map(|k| k as f64 * resolution), max: self.hi.map(|k| k as f64 * resolution) }
    }

    /// The two to eight halves of the box; splits stay on brick boundaries while the box is
    /// larger than a brick.
    fn split(&self) -> impl Iterator<Item = Box3> + '_ {
        // Above brick size only the axes longer than a brick are split, at a brick boundary.
        let unit = if self.within_one_brick() { 1 } else { BRICK_EDGE };
        let mid = [0, 1, 2].map(|a| {
            let n = (self.hi[a] - self.lo[a]) / unit;
            (n > 1).then_some(self.lo[a] + unit * (n / 2))
        });
        (0..8).filter_map(move |octant: usize| {
            let mut b = *self;
            for a in 0..3 {
                let upper = octant >> a & 1 == 1;
                let Some(mid) = mid[a] else {
                    if upper {
                        return None;
                    }
                    continue;
                };
                if upper {
                    b.lo[a] = mid;
                } else {
                    b.hi[a] = mid;
                }
            }
            Some(b)
        })
    }

    /// Number of voxels.
    fn volume(&self) -> i64 {
        (0..3).map(|a| (self.hi[a] - self.lo[a]) as i64).product()
    }

    fn within_one_brick(&self) -> bool {
        (0..3).all(|a| self.hi[a] - self.lo[a] <= BRICK_EDGE)
    }

    /// The bricks of a brick-aligned box.
    fn bricks(&self) -> impl Iterator<Item = BrickKey> + '_ {
        let range = |a: usize| self.lo[a] / BRICK_EDGE..self.hi[a] / BRICK_EDGE;
        range(2).flat_map(move |z| range(1).flat_map(move |y| range(0).map(move |x| BrickKey([x, y, z]))))
    }
}

/// Indices `i + 3 j + 9 k` (`i`, `j`, `k` in {0, 1}, in octant order) in the 3 x 3 x 3 corner
/// lattice of [`View::split_voxels`]: each octant's first corner, and each corner of a box
/// relative to its first.
const LOWER_CORNERS: [usize; 8] = [0, 1, 3, 4, 9, 10, 12, 13];

/// The camera and the segments, ready to classify boxes.
struct View<'a> {
    seg: &'a Segments,
    /// Camera-frame position of grid corner `k` (integer voxel coordinates) is
    /// `base + k[0] step[0] + k[1] step[1] + k[2] step[2]`.
    base: [f64; 3],
    step: [[f64; 3]; 3],
    /// Camera to world rotation, world position of the camera, and the grid resolution.
    r_wc: Matrix3<f64>,
    origin: [f64; 3],
    resolution: f64,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    /// Largest pixel-centre column and row.
    u_last: f64,
    v_last: f64,
    /// Boxes whose corners are all within this distance have a pixel centre inside every
    /// voxel's image, so "every pixel passes through" means "every voxel is crossed".
    dense_range2: f64,
    /// Voxels (keys, upper end exclusive) outside which no box is looked at.
    keep: Option<Box3>,
    /// The ray limits' bounds, to which walks are clipped ([`View::brick_walk`]).
    bounds: Option<Aabb>,
    /// A pixel's world direction per metre of camera depth is `R (x_u, y_v, 1)`, the sum of a
    /// part per column, `x_u R e_x` (per axis, so that a row of pixels loads as lanes), and a
    /// part per row, `y_v R e_y + R e_z`: see [`View::inv_dirs`].
    col_dirs: [Vec<f64>; 3],
    row_dirs: Vec<[f64; 3]>,
    /// The least and greatest of those parts per block of [`BLOCK`] columns (per axis), and
    /// per block of rows: the directions of a block's pixels lie between their sums (see
    /// [`View::block_misses`]).
    col_block_dirs: [Vec<[f64; 2]>; 3],
    row_block_dirs: Vec<[[f64; 2]; 3]>,
}

impl<'a> View<'a> {
    /// The view of `rays` (made with their camera rays cached, whose columns' `x` and rows'
    /// `y` the slab tests' directions are made of) over the segments `seg`.
    fn new(rays: &FrameRays, seg: &'a Segments, resolution: f64) -> Self {
        let (frame, r_wc, origin) = (rays.frame, rays.rotation, rays.origin);
        let camera = rays.camera_rays.expect("the projection's rays cache their camera rays");
        let r_cw: Matrix3<f64> = r_wc.transpose();
        let base = r_cw * -Vector3::from(origin);
        let step = [0, 1, 2].map(|a| {
            let col = r_cw.column(a) * resolution;
            [col.x, col.y, col.z]
        });
        let c = &frame.camera;
        let dense_range = dense_range(&frame.camera, resolution);
        let col_dirs = [0, 1, 2].map(|a| camera.xs.iter().map(|x| x * r_wc[(a, 0)]).chain([0.0; BLOCK]).collect());
        let row_dirs: Vec<[f64; 3]> =
            camera.ys.iter().map(|y| [0, 1, 2].map(|a| y * r_wc[(a, 1)] + r_wc[(a, 2)])).collect();
        let extremes = |parts: &mut dyn Iterator<Item = f64>| {
            parts.fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], d| [lo.min(d), hi.max(d)])
        };
        let col_block_dirs = [0, 1, 2].map(|a: usize| {
            let cols: &Vec<f64> = &col_dirs[a];
            cols[..seg.width].chunks(BLOCK).map(|c| extremes(&mut c.iter().copied())).collect()
        });
        let row_block_dirs =
            row_dirs.chunks(BLOCK).map(|rows| [0, 1, 2].map(|a| extremes(&mut rows.iter().map(|r| r[a])))).collect();
        View {
            seg,
            r_wc,
            base: [base.x, base.y, base.z],
            step,
            origin,
            resolution,
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            u_last: (seg.width - 1) as f64,
            v_last: (seg.height - 1) as f64,
            dense_range2: dense_range * dense_range,
            keep: None,
            bounds: None,
            col_dirs,
            row_dirs,
            col_block_dirs,
            row_block_dirs,
        }
    }

    /// The view of `rays` over the filled segments `seg`, looking only at boxes in `keep`, and
    /// the box to split ([`View::root_box`]); `None` if no pixel has a segment.
    fn over(
        rays: &FrameRays,
        seg: &'a Segments,
        limits: &RayLimits,
        resolution: f64,
        keep: Option<&Aabb>,
    ) -> Option<(Self, Box3)> {
        let deepest = seg.deepest()?;
        let mut view = View::new(rays, seg, resolution);
        view.bounds = limits.bounds;
        view.keep = keep.map(|k| {
            let (lo, hi) = box_keys(k, resolution);
            Box3 { lo, hi: hi.map(|h| h + 1) }
        });
        let root = view.root_box(deepest as f64, limits);
        Some((view, root))
    }

    /// Whether box `b` lies wholly outside [`View::keep`].
    fn outside_keep(&self, b: &Box3) -> bool {
        self.keep.as_ref().is_some_and(|k| (0..3).any(|a| b.hi[a] <= k.lo[a] || b.lo[a] >= k.hi[a]))
    }

    /// A brick-aligned box holding every segment: the box around the camera and the image
    /// corners at the deepest segment end (the view frustum), cut to the bounds.
    fn root_box(&self, deepest: f64, limits: &RayLimits) -> Box3 {
        let (mut lo, mut hi) = (self.origin, self.origin);
        for (u, v) in [(0.0, 0.0), (self.u_last, 0.0), (0.0, self.v_last), (self.u_last, self.v_last)] {
            let cam = Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0) * deepest;
            let p = self.r_wc * cam;
            for a in 0..3 {
                lo[a] = lo[a].min(p[a] + self.origin[a]);
                hi[a] = hi[a].max(p[a] + self.origin[a]);
            }
        }
        if let Some(b) = &limits.bounds {
            for a in 0..3 {
                lo[a] = lo[a].max(b.min[a]);
                hi[a] = hi[a].min(b.max[a]).max(lo[a]);
            }
        }
        let r = self.resolution;
        let lo = VoxelKey::from_point(lo, r).brick().0.map(|b| b * BRICK_EDGE);
        let hi = VoxelKey::from_point(hi, r).brick().0.map(|b| (b + 1) * BRICK_EDGE);
        Box3 { lo, hi }
    }

    /// Splits `b` down to bricks: bricks seen whole go to `crossed`, undecided ones to
    /// `undecided`.
    fn split_bricks(
        &self,
        b: Box3,
        crossed: &mut Vec<(BrickKey, SlotMask)>,
        undecided: &mut Vec<(BrickKey, Footprint)>,
    ) {
        if self.outside_keep(&b) {
            return;
        }
        let (seen, footprint) = self.judge(self.corners(&b).iter(), false);
        match seen {
            Seen::None => {}
            Seen::All => crossed.extend(b.bricks().map(|k| (k, [u64::MAX; 8]))),
            Seen::Some if b.within_one_brick() => {
                undecided.push((VoxelKey(b.lo).brick(), footprint.expect("a seen box has a footprint")))
            }
            // The top of the tree, a few dozen boxes of hundreds of bricks, in parallel: on
            // two threads the split down to bricks was the largest serial part of a frame
            // (4.7% of a coffin-world 0.05 m build's instructions). Each child's bricks are
            // gathered apart and appended in order, so the lists are as the serial split's.
            Seen::Some if b.volume() > PARALLEL_SPLIT_VOXELS => {
                let children: Vec<Box3> = b.split().collect();
                let parts: Vec<_> = children
                    .into_par_iter()
                    .map(|c| {
                        let (mut crossed, mut undecided) = (Vec::new(), Vec::new());
                        self.split_bricks(c, &mut crossed, &mut undecided);
                        (crossed, undecided)
                    })
                    .collect();
                for (c, u) in parts {
                    crossed.extend(c);
                    undecided.extend(u);
                }
            }
            Seen::Some => b.split().for_each(|c| self.split_bricks(c, crossed, undecided)),
        }
    }

    /// The corners of box `b` relative to the camera (world axes), as the slab tests take them.
    #[inline(always)]
    fn relative(&self, b: &Box3) -> ([f32; 3], [f32; 3]) {
        let at = |k: [i32; 3]| std::array::from_fn(|a| (k[a] as f64 * self.resolution - self.origin[a]) as f32);
        (at(b.lo), at(b.hi))
    }

    /// The voxels of `brick` crossed by the segments of the pixels of its footprint `fp`, found
    /// by walking each ray through the brick. Most of a footprint's pixels do not
    /// reach the brick (a rectangle around its hexagon, surfaces in front of it): blocks of
    /// them are ruled out first by their depth bounds and [`View::block_misses`], and pixels
    /// by their own depths, so that only a ray that may enter the brick is set up. Those
    /// tests only rule out what the walk would not visit: their depths are widened by a
    /// relative 1e-5, far beyond the rounding of the f32 depths (2^-24), and
    /// [`View::block_misses`] is conservative. (On coffin-world at 0.02 m only 37% of the
    /// footprints' pixels entered their brick.) The rays left are set up a block's row at a
    /// time ([`View::walk_pixels`]) from the segments' depths, not as [`PixelRay`]s: a
    /// coffin-world frame at 0.02 m took 0.87x the time (BENCHMARKS.md, session 49).
    fn walk_brick(&self, brick: BrickKey, fp: &Footprint) -> SlotMask {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the processor has AVX2, checked just above.
            return unsafe { self.walk_brick_avx2(brick, fp) };
        }
        self.walk_brick_baseline(brick, fp)
    }

    /// What the walks of [`View::walk_pixels`] through brick `b` share: the camera relative to
    /// the brick's lower corner, and the box the walks are clipped to (the brick, cut to the
    /// bounds), relative to the camera.
    #[inline(always)]
    fn brick_walk(&self, b: &Box3) -> BrickWalk {
        let cell = b.aabb(self.resolution);
        let (corner, mut lo, mut hi) = (cell.min, cell.min, cell.max);
        if let Some(bounds) = &self.bounds {
            for a in 0..3 {
                (lo[a], hi[a]) = (max(lo[a], bounds.min[a]), min(hi[a], bounds.max[a]));
            }
        }
        BrickWalk {
            origin: std::array::from_fn(|a| self.origin[a] - corner[a]),
            lo: std::array::from_fn(|a| lo[a] - self.origin[a]),
            hi: std::array::from_fn(|a| hi[a] - self.origin[a]),
        }
    }

    /// Walks the rays of pixels `u..u + BLOCK` of row `v` with the segments `lanes` (the
    /// others [`PixelDepths::NONE`]) through the brick of `walk`, setting the voxels they
    /// cross in `mask`. A ray is parametrised by camera depth (its direction per metre of
    /// depth from [`View::dirs`], as [`View::inv_dirs`]'s), the lanes' directions
    /// inverted and clipped to the box side by side, then each ray that enters walked by
    /// [`mark_in_brick`]. The voxels are those of walking the pixel's ray as [`PixelRay`]
    /// over its segment ([`super::for_each_crossing`]), up to rounding where a ray grazes an
    /// edge or a corner (tested).
    #[inline(always)]
    fn walk_pixels(&self, walk: &BrickWalk, (u, v): (usize, usize), lanes: &[PixelDepths; BLOCK], mask: &mut SlotMask) {
        let (dirs, mut inv) = (self.dirs::<BLOCK>(u, v), [[0.0; BLOCK]; 3]);
        let (mut t0, mut t1): ([f64; BLOCK], [f64; BLOCK]) =
            (std::array::from_fn(|j| lanes[j].0[0] as f64), std::array::from_fn(|j| lanes[j].0[1] as f64));
        // (Loops, not `array::from_fn`, which may stay a baseline function of its own.)
        for a in 0..3 {
            for j in 0..BLOCK {
                inv[a][j] = 1.0 / dirs[a][j];
                let (ta, tb) = (walk.lo[a] * inv[a][j], walk.hi[a] * inv[a][j]);
                // (A zero direction gives a NaN for a box side through the camera, which the
                // comparisons of `min` and `max` leave out.)
                t0[j] = max(t0[j], min(ta, tb));
                t1[j] = min(t1[j], max(ta, tb));
            }
        }
        for j in 0..BLOCK {
            if t0[j] < t1[j] {
                let d = [dirs[0][j], dirs[1][j], dirs[2][j]];
                mark_in_brick(walk.origin, d, [inv[0][j], inv[1][j], inv[2][j]], (t0[j], t1[j]), self.resolution, mask);
            }
        }
    }

    /// [`split_voxels!`] in the copy for this processor.
    fn split_voxels(&self, b: Box3, surface: &SlotMask, settled: &SlotMask, mask: &mut SlotMask) {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the processor has AVX2, checked just above.
            return unsafe { self.split_voxels_avx2(b, surface, settled, mask) };
        }
        self.split_voxels_baseline(b, surface, settled, mask)
    }

    /// Camera-frame position of grid corner `key`.
    fn corner_at(&self, key: [i32; 3]) -> [f64; 3] {
        self.point_at(key.map(|k| k as f64))
    }

    /// Camera-frame position of the point at `[x, y, z]` in voxel units.
    fn point_at(&self, [x, y, z]: [f64; 3]) -> [f64; 3] {
        let p = |k: usize| self.base[k] + x * self.step[0][k] + y * self.step[1][k] + z * self.step[2][k];
        [p(0), p(1), p(2)]
    }

    /// What [`View::judge`] needs of a camera-frame point.
    #[inline]
    fn corner(&self, [x, y, z]: [f64; 3]) -> Corner {
        let inv_z = 1.0 / z; // only used when z > 0
        Corner { x, y, z, u: self.fx * x * inv_z + self.cx, v: self.fy * y * inv_z + self.cy }
    }

    /// The eight corners of box `b`.
    fn corners(&self, b: &Box3) -> [Corner; 8] {
        std::array::from_fn(|i| {
            self.corner(self.corner_at(std::array::from_fn(|a| if i >> a & 1 == 1 { b.hi[a] } else { b.lo[a] })))
        })
    }

    /// Classifies the box with these eight corners by projecting them ([`View::footprint`])
    /// and reading the depth pyramid; also gives the rectangle of pixels whose rays can meet
    /// it. `known_dense` when the box is known to lie within the dense range (inside a brick
    /// found dense), which skips that test.
    #[inline]
    fn judge<'c>(
        &self,
        corners: impl Iterator<Item = &'c Corner> + Clone,
        known_dense: bool,
    ) -> (Seen, Option<Footprint>) {
        let Some((rect, depths @ (z_near, z_far), inside_image, centre)) = self.footprint(corners.clone()) else {
            return (Seen::None, None);
        };
        let d = self.seg.bounds(&rect);
        if d.miss(z_near, z_far) {
            return (Seen::None, None);
        }
        // Every pixel that sees the box starts before it and ends behind it.
        let through = d.start_max() <= z_near && d.end_min() >= z_far;
        let dense = known_dense || corners.map(|c| c.x * c.x + c.y * c.y + c.z * c.z).all(|d2| d2 <= self.dense_range2);
        let seen = if inside_image && through && dense { Seen::All } else { Seen::Some };
        (seen, Some(Footprint { rect, depths, dense, centre }))
    }

    /// The rectangle of pixels whose rays can meet the box with these eight corners, the
    /// box's camera-depth range, whether its image lies wholly inside the image, and its
    /// middle ([`BoxImage`]); `None` when no pixel can see it (behind the camera, outside the
    /// view frustum, or between pixel centres). (Inlined into its callers: as a call it was
    /// 8% of a projected frame, and inlined the frame took 0.97-0.98x the time.)
    #[inline(always)]
    fn footprint<'c>(&self, corners: impl Iterator<Item = &'c Corner> + Clone) -> Option<BoxImage> {
        let (mut z_near, mut z_far) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut u_min, mut u_max, mut v_min, mut v_max) =
            (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for c in corners.clone() {
            z_near = min(z_near, c.z);
            z_far = max(z_far, c.z);
            (u_min, u_max, v_min, v_max) = (min(u_min, c.u), max(u_max, c.u), min(v_min, c.v), max(v_max, c.v));
        }
        if z_far <= 0.0 {
            return None; // behind the camera
        }
        let (mut inside_image, mut centre) = (false, None);
        if z_near > 0.0 {
            centre = Some([((u_min + u_max) * 0.5) as f32, ((v_min + v_max) * 0.5) as f32]);
            // In front of the camera: the image of the box is where its corners project (it
            // misses the view frustum exactly when it holds no pixel centre, below).
            inside_image = u_min >= 0.0 && u_max <= self.u_last && v_min >= 0.0 && v_max <= self.v_last;
        } else {
            // Reaching behind the camera plane: any pixel may see it, unless it lies wholly
            // outside the frustum.
            if self.outside_frustum(corners) {
                return None;
            }
            (u_min, u_max, v_min, v_max) = (0.0, self.u_last, 0.0, self.v_last);
        }
        let rect = Rect::of_pixel_centres((u_min, u_max), (v_min, v_max), self.u_last, self.v_last)?;
        Some((rect, (z_near as f32, z_far as f32), inside_image, centre))
    }

    /// Whether a box with these corners lies wholly outside one of the view frustum's side
    /// planes through the camera, fx x + cx z = 0 (u = 0), fx x + (cx - u_last) z = 0
    /// (u = u_last), and the same for rows.
    fn outside_frustum<'c>(&self, corners: impl Iterator<Item = &'c Corner> + Clone) -> bool {
        let outside = |f: &dyn Fn(&Corner) -> f64| corners.clone().all(|c| f(c) < 0.0);
        outside(&|c| self.fx * c.x + self.cx * c.z)
            || outside(&|c| -(self.fx * c.x + (self.cx - self.u_last) * c.z))
            || outside(&|c| self.fy * c.y + self.cy * c.z)
            || outside(&|c| -(self.fy * c.y + (self.cy - self.v_last) * c.z))
    }

    /// The reciprocals of the world directions per metre of camera depth of pixels `u..u + N`
    /// of row `v`, as lanes per axis (`N` at most [`BLOCK`]; the columns past the image's last
    /// have their row's part only, and no segment). Summed and inverted in f64 and rounded
    /// once, as the per-pixel values were when they were stored: with an f32 sum and
    /// division, a row of pixels whose rays pass exactly through voxel corners (a symmetric
    /// simulated scene) lost 60 voxels the walk keeps.
    #[inline(always)]
    fn inv_dirs<const N: usize>(&self, u: usize, v: usize) -> [[f32; N]; 3] {
        let (dirs, mut inv) = (self.dirs::<N>(u, v), [[0.0; N]; 3]);
        for (inv, dirs) in inv.iter_mut().zip(&dirs) {
            for (i, d) in inv.iter_mut().zip(dirs) {
                *i = (1.0 / d) as f32;
            }
        }
        inv
    }

    /// The world directions per metre of camera depth of pixels `u..u + N` of row `v`, as
    /// lanes per axis: each the sum of its column's part and its row's, in f64.
    #[inline(always)]
    fn dirs<const N: usize>(&self, u: usize, v: usize) -> [[f64; N]; 3] {
        // (Loops, not `array::from_fn`, which may stay a baseline function of its own.)
        let (row, mut dirs) = (self.row_dirs[v], [[0.0; N]; 3]);
        for (a, dirs) in dirs.iter_mut().enumerate() {
            for (d, c) in dirs.iter_mut().zip(&self.col_dirs[a][u..u + N]) {
                *d = c + row[a];
            }
        }
        dirs
    }

    /// Whether no pixel of the blocks `bu.0..=bu.1` x `bv.0..=bv.1` of the pyramid's first
    /// level, whose segments lie within `bounds`, can pass through the box `lo..hi` (world
    /// axes, relative to the camera): the slab test of [`slabs_cross`] for the whole box of
    /// directions the blocks' rays lie in, one test where their pixels take one per row.
    /// Behind a surface seen at a slant, a voxel's nearest corner is far in front of where the
    /// rays meet it, so most blocks that pass [`Bounds::miss`] are stopped here.
    ///
    /// It never says "miss" for a block with a pixel that passes: a ray with direction `d`
    /// (per metre of camera depth) is inside slab `a` at depth `t > 0` only where
    /// `t dmin <= hi` and `t dmax >= lo` for any `dmin <= d_a <= dmax`, and the blocks' `d_a`
    /// (sums of a column's part and a row's, rounded) lie between the rounded sums of the
    /// least parts and of the greatest. A column's part is `x_u R e_x` with `x_u = (u - cx) /
    /// fx`, monotonic in `u` (rounding keeps it so), and a row's likewise: over a run of
    /// blocks the least and greatest parts are those of its first or its last block. The
    /// lanes' values are within a relative 2^-23 of those depths (an f32 reciprocal and an
    /// f32 product), so the bounds are widened by a relative 1e-5 first.
    #[inline(always)] // (into the copies of `split_voxels!`, as `box_crossed`)
    fn block_misses(
        &self,
        bu: (usize, usize),
        bv: (usize, usize),
        bounds: &Bounds,
        lo: &[f32; 3],
        hi: &[f32; 3],
    ) -> bool {
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        let (first_row, last_row) = (&self.row_block_dirs[bv.0], &self.row_block_dirs[bv.1]);
        for a in 0..3 {
            let (first, last) = (self.col_block_dirs[a][bu.0], self.col_block_dirs[a][bu.1]);
            let d_min = min(first[0], last[0]) + min(first_row[a][0], last_row[a][0]);
            let d_max = max(first[1], last[1]) + max(first_row[a][1], last_row[a][1]);
            let (l, h) = (lo[a] as f64, hi[a] as f64);
            // t d_min <= h
            if d_min > 0.0 {
                t1 = t1.min(h / d_min);
            } else if d_min < 0.0 {
                t0 = t0.max(h / d_min);
            } else if h < 0.0 {
                return true;
            }
            // t d_max >= l
            if d_max > 0.0 {
                t0 = t0.max(l / d_max);
            } else if d_max < 0.0 {
                t1 = t1.min(l / d_max);
            } else if l > 0.0 {
                return true;
            }
        }
        let (t0, t1) = (t0 - t0.abs() * WIDEN, t1 + t1.abs() * WIDEN);
        t0 >= t1 || bounds.end_max() as f64 <= t0 || bounds.start_min() as f64 >= t1
    }

    /// The exact test for a box of voxels, seen by the pixels of `rect` and lying between
    /// camera depths `z_near` and `z_far`: does the segment of some pixel in `rect` pass
    /// through it? For a single voxel, this is the test of whether it is crossed. For a larger
    /// box, "no" means no voxel in it is crossed: the box's faces are its outer voxels' faces,
    /// computed the same way, and the slab test's products and extremes are monotonic, so
    /// each voxel's interval along a pixel's ray lies within the box's, rounding included.
    /// (Only a pixel whose centre lies on the box's outline, where rounding may put it inside
    /// a voxel's footprint but outside the box's, could differ: a ray that grazes the box.)
    #[inline(always)] // (into both copies of `split_voxels!`: as a call it stayed a baseline one)
    fn box_crossed(&self, b: &Box3, rect: &Rect, depths: (f32, f32), centre: Option<[f32; 2]>) -> bool {
        let (lo, hi) = self.relative(b);
        // Most undecided voxels hold a surface, and the ray through the middle of their image
        // ends inside them: try it first. (In front of the camera, the middle of the box's
        // corners' image, which `footprint` found without a division of its own; a box
        // reaching behind the camera plane has its centre projected.)
        let centre = centre.or_else(|| {
            let c = self.corner(self.point_at(std::array::from_fn(|a| (b.lo[a] + b.hi[a]) as f64 * 0.5)));
            (c.z > 0.0).then_some([c.u as f32, c.v as f32])
        });
        if let Some([cu, cv]) = centre {
            // The nearest pixel centre, clamped to the footprint: a truncating cast of
            // `x + 1/2`, non-negative (`round` is a libm call on baseline x86-64, 1% of a frame;
            // a cast to `u32` is a few instructions where one to `usize` is a dozen).
            let nearest = |x: f32, lo: usize| ((x + 0.5).max(0.0) as u32 as usize).max(lo);
            let (u, v) = (nearest(cu, rect.u0).min(rect.u1), nearest(cv, rect.v0).min(rect.v1));
            if self.pixel_crosses((u, v), &lo, &hi) {
                return true;
            }
        }
        self.pixels_cross(rect, depths, &lo, &hi)
    }

    /// The exact test of one voxel, `voxel`, whose corners (in camera coordinates) are
    /// `corners`, of which `near` and `far` are opposite: [`View::box_crossed`], but with the
    /// pixel nearest the middle of those two corners' images tried before the voxel's
    /// footprint is found. Two thirds of the voxels tested are crossed by that pixel, and
    /// need no footprint (coffin-world at 0.05 m: 0.956x the time of a frame, BENCHMARKS.md,
    /// session 45). A pixel whose segment passes through the voxel lies in its footprint (up
    /// to rounding where its ray grazes the voxel's outline, as for [`View::box_crossed`]'s
    /// boxes).
    #[inline(always)] // (as `box_crossed`)
    fn voxel_crossed<'c>(
        &self,
        voxel: &Box3,
        (near, far): (&Corner, &Corner),
        corners: impl Iterator<Item = &'c Corner> + Clone,
    ) -> bool {
        let Some(pixel) = self.first_pixel(near, far) else {
            return self
                .footprint(corners)
                .is_some_and(|(rect, depths, _, centre)| self.box_crossed(voxel, &rect, depths, centre));
        };
        let (lo, hi) = self.relative(voxel);
        self.pixel_crosses(pixel, &lo, &hi)
            || self.footprint(corners).is_some_and(|(rect, depths, _, _)| self.pixels_cross(&rect, depths, &lo, &hi))
    }

    /// The pixel [`View::voxel_crossed`] tries first: the one nearest the middle of the images
    /// of a voxel's opposite corners `near` and `far`. None when a corner is not in front of
    /// the camera (the images mean nothing) or the middle is more than half a pixel outside
    /// the image (no pixel; within half a pixel, the casts round to one inside it).
    #[inline(always)]
    fn first_pixel(&self, near: &Corner, far: &Corner) -> Option<(usize, usize)> {
        let (cu, cv) = ((near.u + far.u) * 0.5, (near.v + far.v) * 0.5);
        let in_image = cu >= -0.5 && cu < self.u_last + 0.5 && cv >= -0.5 && cv < self.v_last + 0.5;
        (near.z > 0.0 && far.z > 0.0 && in_image).then_some(((cu + 0.5) as u32 as usize, (cv + 0.5) as u32 as usize))
    }

    /// Whether the segment of pixel `(u, v)` passes through the box `lo..hi` (relative to the
    /// camera): [`slabs_cross`] of one lane.
    #[inline(always)]
    fn pixel_crosses(&self, (u, v): (usize, usize), lo: &[f32; 3], hi: &[f32; 3]) -> bool {
        slabs_cross(&[self.seg.pixel(v * self.seg.width + u)], &self.inv_dirs(u, v), lo, hi)[0]
    }

    /// Whether the segment of some pixel of `rect` passes through the box `lo..hi` (relative
    /// to the camera) lying between camera depths `z_near` and `z_far`, pixel by pixel,
    /// skipping blocks of pixels whose segments all miss it. A block's row of pixels at once,
    /// in lanes: each pixel's depths first (two compares where the slab test is a dozen
    /// operations, and most pixels here end in front of the voxel), then the slab tests of
    /// those left, side by side. (Without the attribute the closure stayed a baseline
    /// function of its own, called from the AVX2 copy.)
    #[inline(always)]
    fn pixels_cross(&self, rect: &Rect, (z_near, z_far): (f32, f32), lo: &[f32; 3], hi: &[f32; 3]) -> bool {
        self.blocks_reaching(
            rect,
            (z_near, z_far),
            lo,
            hi,
            #[inline(always)]
            |(u0, u1), v| {
                let lanes = self.seg.row_lanes((u0, u1), v, (z_near, z_far));
                let crossed = lanes.iter().any(|p| p.0[0] <= p.0[1])
                    && slabs_cross(&lanes, &self.inv_dirs(u0, v), lo, hi).contains(&true);
                if crossed { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
            },
        )
        .is_break()
    }

    /// Calls `row` with each row of pixels (columns `u0..u1`, row `v`) of the blocks of the
    /// pyramid's first level that `rect` meets and that may reach the box `lo..hi` lying
    /// between camera depths `z_near` and `z_far`: blocks whose depth bounds or directions
    /// miss it ([`Bounds::miss`], [`View::block_misses`]) are skipped; a break stops the scan.
    ///
    /// A rectangle [`COARSE_BLOCKS`] blocks or more across is looked at 2 x 2 blocks at a
    /// time first, by the same two tests on the pyramid's second level: a box seen near the
    /// camera, or behind a surface it is close to, has a large footprint most of whose blocks
    /// both tests rule out, and one test then rules out four (icl-livingroom-5 at 0.05 m:
    /// 0.93x the time of a frame, BENCHMARKS.md, session 44). Smaller rectangles, most at
    /// finer resolutions, go block by block, where the extra test would seldom pay.
    #[inline(always)]
    fn blocks_reaching(
        &self,
        rect: &Rect,
        depths: (f32, f32),
        lo: &[f32; 3],
        hi: &[f32; 3],
        mut row: impl FnMut((usize, usize), usize) -> ControlFlow<()>,
    ) -> ControlFlow<()> {
        let k = BLOCK.trailing_zeros() as usize;
        let (bu, bv) = ((rect.u0 >> k, rect.u1 >> k), (rect.v0 >> k, rect.v1 >> k));
        let levels = &self.seg.levels;
        if (bu.1 - bu.0 + 1).max(bv.1 - bv.0 + 1) < COARSE_BLOCKS || levels.len() < 2 {
            return self.blocks_within(rect, bu, bv, depths, lo, hi, &mut row);
        }
        let pairs = &levels[1];
        for cv in bv.0 >> 1..(bv.1 >> 1) + 1 {
            let pair_v = ((2 * cv).max(bv.0), (2 * cv + 1).min(bv.1));
            for cu in bu.0 >> 1..(bu.1 >> 1) + 1 {
                let pair_u = ((2 * cu).max(bu.0), (2 * cu + 1).min(bu.1));
                let cell = &pairs.cells[cv * pairs.width + cu];
                if self.may_reach(cell, pair_u, pair_v, depths, lo, hi) {
                    self.blocks_within(rect, pair_u, pair_v, depths, lo, hi, &mut row)?;
                }
            }
        }
        ControlFlow::Continue(())
    }

    /// [`View::blocks_reaching`] for the blocks `bu.0..=bu.1` x `bv.0..=bv.1`, one by one.
    /// (Plain loops, not iterator adaptors: those compiled to functions of their own, outside
    /// the AVX2 copies this is inlined into.)
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn blocks_within(
        &self,
        rect: &Rect,
        bu: (usize, usize),
        bv: (usize, usize),
        depths: (f32, f32),
        lo: &[f32; 3],
        hi: &[f32; 3],
        row: &mut impl FnMut((usize, usize), usize) -> ControlFlow<()>,
    ) -> ControlFlow<()> {
        let (k, blocks) = (BLOCK.trailing_zeros() as usize, &self.seg.levels[0]);
        for bv in bv.0..bv.1 + 1 {
            for bu in bu.0..bu.1 + 1 {
                let cell = &blocks.cells[bv * blocks.width + bu];
                if !self.may_reach(cell, (bu, bu), (bv, bv), depths, lo, hi) {
                    continue;
                }
                let (u0, u1) = ((bu << k).max(rect.u0), ((bu + 1) << k).min(rect.u1 + 1));
                for v in (bv << k).max(rect.v0)..((bv + 1) << k).min(rect.v1 + 1) {
                    row((u0, u1), v)?;
                }
            }
        }
        ControlFlow::Continue(())
    }

    /// Whether the blocks `bu.0..=bu.1` x `bv.0..=bv.1`, with depth bounds `cell`, may reach
    /// the box `lo..hi` lying between camera depths `depths`: neither [`Bounds::miss`] nor
    /// [`View::block_misses`] rules them out.
    #[inline(always)]
    fn may_reach(
        &self,
        cell: &Bounds,
        bu: (usize, usize),
        bv: (usize, usize),
        (z_near, z_far): (f32, f32),
        lo: &[f32; 3],
        hi: &[f32; 3],
    ) -> bool {
        !cell.miss(z_near, z_far) && !self.block_misses(bu, bv, cell, lo, hi)
    }
}

/// Rectangles of pixels at least this many blocks across are scanned 2 x 2 blocks at a time
/// first ([`View::blocks_reaching`]). (From 3, coffin-world at 0.05 m took 1.02x the time of
/// a frame; from 4, 0.97x; from 5, 0.98x. Going on down from the pyramid's further levels
/// for rectangles of 8 blocks and more changed nothing measurable.)
const COARSE_BLOCKS: usize = 4;

#[cfg(test)]
pub(super) mod tests {
    use std::collections::BTreeSet;

    use super::*;
    use crate::frames::{Camera, DepthImage, look_at};
    use crate::map::mask_slots;
    use crate::random::Rng;
    use crate::rays::{CUT_IN_LANES, for_each_crossing};

    /// The slab test in four lanes gives each lane's own answer (no lane leaks into another),
    /// which is the brute-force answer: the segment's depths overlap the box's along all three
    /// axes. (The projection's tests against walked rays check it in place.)
    #[test]
    fn slab_tests_in_lanes_are_each_pixels_own() {
        let mut rng = Rng::new(7);
        let (lo, hi) = ([0.1f32, -0.2, 1.0], [0.3f32, 0.0, 1.2]);
        let (mut crossing, mut missing) = (0, 0);
        for _ in 0..2000 {
            // Rays through (x, y, 1) per metre of depth: inverse directions (1/x, 1/y, 1).
            let mut inv = [[0.0f32; 4], [0.0; 4], [1.0; 4]];
            let depths: [PixelDepths; 4] = std::array::from_fn(|j| {
                let (x, y) = (rng.range(-0.1, 0.4) as f32, rng.range(-0.3, 0.1) as f32);
                (inv[0][j], inv[1][j]) = (1.0 / x, 1.0 / y);
                if rng.uniform() < 0.2 {
                    return PixelDepths::NONE;
                }
                let (a, b) = (rng.range(0.0, 1.5) as f32, rng.range(0.0, 1.5) as f32);
                PixelDepths([a.min(b), a.max(b)])
            });
            let lanes = slabs_cross(&depths, &inv, &lo, &hi);
            for (j, crossed) in lanes.into_iter().enumerate() {
                let lane = inv.map(|d| [d[j]]);
                assert_eq!(crossed, slabs_cross(&[depths[j]], &lane, &lo, &hi)[0]);
                let [start, end] = depths[j].0;
                // Brute force: depths where the point (x z, y z, z) lies in the box, sampled finely.
                // (Inside by `margin`; samples 0.5 mm of depth apart.)
                let brute = |margin: f32| {
                    (0..=3000).map(|i| start + (end - start) * i as f32 / 3000.0).any(|z| {
                        (0..3).all(|a| {
                            let p = z / lane[a][0];
                            p > lo[a] + margin && p < hi[a] - margin
                        })
                    })
                };
                if brute(1e-4) {
                    assert!(crossed, "{:?} {lane:?}", depths[j]);
                }
                if crossed {
                    assert!(brute(-1e-3), "{:?} {lane:?}", depths[j]);
                }
                if crossed { crossing += 1 } else { missing += 1 }
            }
        }
        assert!(crossing > 100 && missing > 100, "{crossing} {missing}");
    }

    /// A random small camera somewhere in a box, looking at random surfaces, with holes.
    pub(super) fn random_frame(rng: &mut Rng) -> Frame {
        let (w, h) = (rng.range(8.0, 48.0) as u32, rng.range(6.0, 36.0) as u32);
        random_frame_of(rng, w, h)
    }

    /// [`random_frame`] of `w x h` pixels.
    fn random_frame_of(rng: &mut Rng, w: u32, h: u32) -> Frame {
        let f = rng.range(15.0, 60.0);
        let fy = if rng.uniform() < 0.3 { -f * rng.range(0.9, 1.1) } else { f * rng.range(0.9, 1.1) };
        let camera =
            Camera::new(f, fy, rng.range(0.3, 0.7) * w as f64, rng.range(0.3, 0.7) * h as f64, w, h, 1000.0).unwrap();
        let mut depth = DepthImage::new(w, h);
        let (base, tilt_u, tilt_v) = (rng.range(0.3, 3.0), rng.range(-0.05, 0.05), rng.range(-0.05, 0.05));
        for v in 0..h {
            for u in 0..w {
                let z = if rng.uniform() < 0.1 {
                    0.0 // no return
                } else if rng.uniform() < 0.1 {
                    rng.range(0.1, 5.0) as f32 // speckle
                } else {
                    (base + tilt_u * u as f64 + tilt_v * v as f64).max(0.05) as f32
                };
                depth.set(u, v, z);
            }
        }
        let eye = nalgebra::Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
        let target = eye + nalgebra::Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
        let pose = look_at(eye, target).unwrap();
        Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None }
    }

    /// Calls `f(case, rays, limits, resolution)` for 30 cases of [`random_frame`] and
    /// [`random_limits`] from seed `seed`, at resolutions drawn from `(lo, hi)`.
    pub(super) fn for_random_cases(
        seed: u64,
        (lo, hi): (f64, f64),
        mut f: impl FnMut(usize, &FrameRays, &RayLimits, f64),
    ) {
        let mut rng = Rng::new(seed);
        for case in 0..30 {
            let frame = random_frame(&mut rng);
            let r = rng.range(lo, hi);
            let limits = random_limits(case, &mut rng);
            let mut cache = CameraRays::default();
            f(case, &FrameRays::with_camera_rays(&frame, &mut cache), &limits, r);
        }
    }

    /// Limits by `case % 3`: none, a random max range, or random bounds around the cameras of
    /// [`random_frame`].
    pub(super) fn random_limits(case: usize, rng: &mut Rng) -> RayLimits {
        match case % 3 {
            0 => RayLimits::default(),
            1 => RayLimits { max_range: Some(rng.range(0.5, 3.0)), bounds: None },
            _ => RayLimits {
                max_range: None,
                bounds: Some(Aabb::new([-1.0, -1.5, -0.7], [rng.range(0.0, 2.0), 1.2, rng.range(0.0, 2.0)]).unwrap()),
            },
        }
    }

    /// Calls `f` with the view of each of `cases` random frames' segments at a random
    /// resolution (no limits), with the frame's rays and the generator for the case's own draws.
    fn for_random_views(seed: u64, cases: usize, mut f: impl FnMut(&mut Rng, &FrameRays, &View, f64)) {
        let mut rng = Rng::new(seed);
        for _ in 0..cases {
            let frame = random_frame(&mut rng);
            let r = rng.range(0.03, 0.25);
            let limits = RayLimits::default();
            let mut p = Projector::default();
            let rays = FrameRays::with_camera_rays(&frame, &mut p.camera_rays);
            p.segments.fill(&rays, &limits, r, &Step::start());
            if let Some((view, _)) = View::over(&rays, &p.segments, &limits, r, None) {
                f(&mut rng, &rays, &view, r);
            }
        }
    }

    fn walked(frame: &Frame, limits: &RayLimits, r: f64) -> (BTreeSet<VoxelKey>, BTreeSet<VoxelKey>) {
        let rays = FrameRays::new(frame);
        let (mut set, mut ends) = (BTreeSet::new(), BTreeSet::new());
        for v in 0..rays.rows() {
            for ray in rays.row(v) {
                let Some(seg) = limits.hit_miss_segment(&ray, r) else { continue };
                let mut last = None;
                for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, r, |c| {
                    set.insert(c.key);
                    last = Some(c.key);
                    ControlFlow::Continue(())
                });
                if let (true, Some(k)) = (seg.hits_surface, last) {
                    ends.insert(k);
                }
            }
        }
        (set, ends)
    }

    pub(super) fn projected(frame: &Frame, limits: &RayLimits, r: f64) -> (BTreeSet<VoxelKey>, BTreeSet<VoxelKey>) {
        let c = Projector::default().crossed_voxels(frame, limits, r, None, None);
        voxel_sets(&c)
    }

    /// The crossed voxels and the surface voxels of `c`, checking that each brick appears at
    /// most once in either list, and never with an empty mask.
    pub(super) fn voxel_sets(c: &CrossedVoxels) -> (BTreeSet<VoxelKey>, BTreeSet<VoxelKey>) {
        for list in [&c.crossed, &c.ends] {
            let mut bricks = BTreeSet::new();
            for (b, m) in list {
                assert!(bricks.insert(*b), "brick {b:?} twice");
                assert_ne!(*m, [0; 8], "brick {b:?} with no voxel");
            }
        }
        let crossed = c.crossed.iter().flat_map(|(b, m)| mask_slots(m).map(|s| b.voxel(s))).collect();
        (crossed, c.end_voxels().collect())
    }

    /// Calls `f` with the view of `rays`' segments and the bricks the split down to bricks
    /// leaves undecided (nothing if no pixel has a segment).
    fn with_undecided(rays: &FrameRays, limits: &RayLimits, r: f64, f: impl FnOnce(&View, Vec<(BrickKey, Footprint)>)) {
        let mut seg = Segments::default();
        seg.fill(rays, limits, r, &Step::start());
        let Some((view, root)) = View::over(rays, &seg, limits, r, None) else { return };
        let (mut crossed, mut undecided) = (Vec::new(), Vec::new());
        view.split_bricks(root, &mut crossed, &mut undecided);
        f(&view, undecided);
    }

    /// The AVX2 copy of the box splitting marks the baseline copy's voxels, brick by brick, on
    /// random frames with and without limits. (Every other test runs the copy this machine
    /// picks; this one runs both.)
    #[test]
    fn both_copies_of_the_box_splitting_agree() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            let (mut split, mut tested) = (0, 0);
            for_random_cases(17, (0.02, 0.2), |case, rays, limits, r| {
                with_undecided(rays, limits, r, |view, undecided| {
                    for (brick, footprint) in undecided.into_iter().filter(|(_, f)| f.dense) {
                        let surface = [0x5555_5555_5555_5555u64; 8];
                        // (Some voxels and cubes of voxels left open, two layers of eight.)
                        let settled = [0, 0x0f0f_0f0f_0000_0000, 0, 0, u64::MAX, u64::MAX, 0, 0x8000];
                        let (mut base, mut fast) = ([0u64; 8], [0u64; 8]);
                        view.split_voxels_baseline(Box3::of_brick(brick), &surface, &settled, &mut base);
                        // SAFETY: the processor has AVX2, checked above.
                        unsafe { view.split_voxels_avx2(Box3::of_brick(brick), &surface, &settled, &mut fast) };
                        assert_eq!(base, fast, "case {case}, brick {brick:?}, {:?}", footprint.rect);
                        split += 1;
                        tested += base.iter().zip(&surface).any(|(b, s)| b & !s != 0) as usize;
                    }
                });
            });
            // (Bricks with voxels set beyond the surfaces: the exact test passed there.)
            assert!(split >= 50 && tested >= 20, "{split} bricks split, {tested} with crossed voxels");
            return;
        }
        eprintln!("skipped: this processor has no AVX2, only the baseline copy runs");
    }

    /// A brick's walk visits the voxels that walking every pixel of its footprint visits:
    /// the blocks and pixels it rules out first never hold one (both copies, on random frames
    /// with and without limits, every undecided brick). And those are the voxels of walking
    /// each pixel's ray in metres over its segment within the brick ([`for_each_crossing`]),
    /// up to rays that graze an edge or a corner.
    #[test]
    fn a_bricks_walk_rules_out_only_pixels_that_miss_it() {
        let (mut bricks, mut ruled_out, mut differ, mut total) = (0, 0usize, 0u32, 0u32);
        for_random_cases(23, (0.02, 0.2), |case, rays, limits, r| {
            with_undecided(rays, limits, r, |view, undecided| {
                for (brick, footprint) in undecided {
                    let (b, rect) = (Box3::of_brick(brick), &footprint.rect);
                    let (walk, cell) = (view.brick_walk(&b), b.aabb(r));
                    let (mut all, mut metres) = ([0u64; 8], [0u64; 8]);
                    for v in rect.v0..rect.v1 + 1 {
                        for u in rect.u0..rect.u1 + 1 {
                            let mut lanes = [PixelDepths::NONE; BLOCK];
                            lanes[0] = view.seg.pixel(v * view.seg.width + u);
                            let before = all;
                            view.walk_pixels(&walk, (u, v), &lanes, &mut all);
                            ruled_out += (before == all) as usize;
                            let Some(ray) = rays.ray(u as u32, v as u32) else { continue };
                            let Some(seg) = limits.hit_miss_segment(&ray, r) else { continue };
                            let Some((a, b)) = cell.clip(ray.origin, ray.dir, seg.start, seg.end) else { continue };
                            for_each_crossing(ray.origin, ray.dir, a, b, r, |c| {
                                if c.key.brick() == brick {
                                    mask_set(&mut metres, c.key.slot());
                                }
                                ControlFlow::Continue(())
                            });
                        }
                    }
                    assert_eq!(
                        view.walk_brick_baseline(brick, &footprint),
                        all,
                        "case {case}, brick {brick:?}, {rect:?}"
                    );
                    #[cfg(target_arch = "x86_64")]
                    if std::is_x86_feature_detected!("avx2") {
                        // SAFETY: the processor has AVX2, checked just above.
                        let fast = unsafe { view.walk_brick_avx2(brick, &footprint) };
                        assert_eq!(fast, all, "case {case}, brick {brick:?}, {rect:?} (AVX2)");
                    }
                    differ += (0..8).map(|w| (all[w] ^ metres[w]).count_ones()).sum::<u32>();
                    total += metres.iter().map(|w| w.count_ones()).sum::<u32>();
                    bricks += 1;
                }
            });
        });
        eprintln!("{differ} of {total} voxels differ from walking in metres");
        assert!(bricks >= 100 && ruled_out >= 1000, "{bricks} bricks, {ruled_out} pixels missing theirs");
        assert!(total >= 10_000 && differ * 10_000 <= total, "{differ} of {total} voxels differ");
    }

    /// The AVX2 and AVX-512 copies of a row's filling give the baseline copy's segments and
    /// ends bit for bit, with and without a max range and bounds. (Every other test runs the
    /// copy this machine picks; this one runs each it can.)
    #[test]
    fn every_copy_of_a_segments_row_agrees() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            let mut with_segments = 0;
            for_random_cases(5, (0.03, 0.25), |case, rays, limits, r| {
                let starts = limits.bounds.is_some();
                let fill = |row: &RowFill| {
                    let mut seg = Segments::default();
                    let ends = seg.fill_with(rays.size(), starts, |v, p, e, a| row(v, p, e, a));
                    let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    (bits(&seg.ends), bits(&seg.starts), ends)
                };
                let base = fill(&|v, p, e, a| segments_row_baseline::<false>(rays, limits, r, v, p, e, a));
                // SAFETY: the processor has AVX2, checked above.
                let fast = fill(&|v, p, e, a| unsafe { segments_row_avx2::<false>(rays, limits, r, v, p, e, a) });
                assert_eq!(base, fast, "case {case}");
                if has_avx512() {
                    // SAFETY: the processor has AVX-512, checked just above.
                    let wide = fill(&|v, p, e, a| unsafe { segments_row_avx512::<false>(rays, limits, r, v, p, e, a) });
                    assert_eq!(base, wide, "case {case} (AVX-512)");
                }
                with_segments += base.0.iter().any(|e| f32::from_bits(*e).is_finite()) as usize;
            });
            assert!(with_segments >= 20, "{with_segments} of 30 frames have segments");
            if !has_avx512() {
                eprintln!("this processor has no AVX-512: its copy was not run");
            }
            return;
        }
        eprintln!("skipped: this processor has no AVX2, only the baseline copy runs");
    }

    /// A projector readied for a frame's camera ([`Projector::prepare`]), or for another
    /// camera, finds what a fresh one finds, and readying gives its buffers the shapes the
    /// frame's filling gives them (so that the filling allocates nothing).
    #[test]
    fn a_prepared_projector_finds_what_a_fresh_one_finds() {
        let mut rng = Rng::new(23);
        let sorted = |mut c: CrossedVoxels| {
            c.crossed.sort_by_key(|(k, _)| k.0);
            c.ends.sort_by_key(|(k, _)| k.0);
            (c.crossed, c.ends)
        };
        let shapes = |p: &Projector| {
            let seg = &p.segments;
            let levels: Vec<(usize, usize)> = seg.levels.iter().map(|l| (l.width, l.cells.len())).collect();
            (seg.width, seg.height, seg.ends.len(), seg.starts.len(), levels)
        };
        for case in 0..30 {
            let frame = random_frame(&mut rng);
            let (limits, r) = (random_limits(case, &mut rng), rng.range(0.03, 0.25));
            let bounds = limits.bounds.is_some();
            let fresh = || Projector::default();
            let mut found = fresh();
            let expected = sorted(found.crossed_voxels(&frame, &limits, r, None, None));
            let mut ready = fresh();
            ready.prepare(&frame.camera, bounds);
            assert_eq!(shapes(&ready), shapes(&found), "case {case}: readied as the frame leaves them");
            assert_eq!(sorted(ready.crossed_voxels(&frame, &limits, r, None, None)), expected, "case {case}");
            let c = &frame.camera;
            let other = Camera::new(c.fx, c.fy, c.cx, c.cy, c.width + 5, c.height + 3, c.depth_scale).unwrap();
            let mut elsewhere = fresh();
            elsewhere.prepare(&other, !bounds);
            assert_eq!(sorted(elsewhere.crossed_voxels(&frame, &limits, r, None, None)), expected, "case {case}");
        }
    }

    /// A row's filling, as [`Segments::fill_with`] takes it.
    type RowFill<'r> = dyn Fn(usize, PixelRow<'_>, &mut Vec<VoxelKey>, &mut AboveEnds) + Sync + 'r;

    /// Readings beyond the max range cut in lanes ([`FrameRays::row_cut`], the copies with
    /// `CUT`) give the segments of [`RayLimits::hit_miss_segment`] one ray at a time (the
    /// copies without) bit for bit, in both the lanes and the per-pixel branch, and in every
    /// processor copy the processor can run.
    #[test]
    fn readings_beyond_the_max_range_cut_in_lanes_are_each_rays_own() {
        let (mut rng, mut rows_in_lanes, mut rows_per_pixel) = (Rng::new(11), 0, 0);
        // 40 frames narrower than a block of lanes, then 8 of several blocks whose last is
        // short (its arrays hold the block before's values past its columns: `row_blocks`).
        for case in 0..48 {
            let frame = match case {
                0..40 => random_frame(&mut rng),
                _ => random_frame_of(&mut rng, 2 * PLAIN_COLUMNS as u32 + 1 + case, 6),
            };
            let r = rng.range(0.01, 0.25);
            let limits = RayLimits { max_range: Some(rng.range(0.2, 3.0)), bounds: None };
            let mut cache = CameraRays::default();
            let rays = FrameRays::with_camera_rays(&frame, &mut cache);
            let size = rays.size();
            for v in 0..size.1 {
                let beyond = rays.row(v as u32).filter(|ray| ray.range > limits.max_range.unwrap()).count();
                rows_in_lanes += (beyond >= CUT_IN_LANES) as usize;
                rows_per_pixel += (beyond > 0 && beyond < CUT_IN_LANES) as usize;
            }
            let fill = |row: &RowFill| {
                let mut seg = Segments::default();
                let ends = seg.fill_with(size, false, |v, p, e, a| row(v, p, e, a));
                (seg.ends.iter().map(|z| z.to_bits()).collect::<Vec<_>>(), ends)
            };
            let one_by_one = fill(&|v, p, e, a| segments_row_baseline::<false>(&rays, &limits, r, v, p, e, a));
            let in_lanes = fill(&|v, p, e, a| segments_row_baseline::<true>(&rays, &limits, r, v, p, e, a));
            assert_eq!(one_by_one, in_lanes, "case {case}");
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the processor has AVX2, checked just above.
                let fast = fill(&|v, p, e, a| unsafe { segments_row_avx2::<true>(&rays, &limits, r, v, p, e, a) });
                assert_eq!(one_by_one, fast, "case {case}");
            }
            #[cfg(target_arch = "x86_64")]
            if has_avx512() {
                // SAFETY: the processor has AVX-512, checked just above.
                let wide = fill(&|v, p, e, a| unsafe { segments_row_avx512::<true>(&rays, &limits, r, v, p, e, a) });
                assert_eq!(one_by_one, wide, "case {case} (AVX-512)");
            }
        }
        assert!(
            rows_in_lanes >= 50 && rows_per_pixel >= 50,
            "{rows_in_lanes} rows in lanes, {rows_per_pixel} per pixel"
        );
    }

    /// A voxel's exact test that tries its first pixel before its footprint
    /// ([`View::voxel_crossed`]) says what the box test of the voxel alone says
    /// ([`View::box_crossed`]), for voxels around the frames' surfaces and in front of them; and
    /// the first pixel settles a third of those crossed or more.
    #[test]
    fn a_voxels_first_pixel_changes_no_verdict() {
        let (mut verdicts, mut by_first) = ([0usize; 2], 0usize);
        for_random_views(29, 40, |rng, rays, view, r| {
            for _ in 0..200 {
                // A voxel on a random pixel's ray: in front of its end, or up to three voxels
                // behind it.
                let (u, v) = (rng.uniform() * view.seg.width as f64, rng.uniform() * view.seg.height as f64);
                let Some(ray) = rays.ray(u as u32, v as u32) else { continue };
                let t = if rng.uniform() < 0.5 {
                    rng.range(0.2, 1.0) * ray.range
                } else {
                    ray.range + rng.range(0.0, 3.0) * r
                };
                let key: [i32; 3] = std::array::from_fn(|a| floor_i32((ray.origin[a] + t * ray.dir[a]) / r));
                let voxel = Box3 { lo: key, hi: key.map(|k| k + 1) };
                let c = view.corners(&voxel);
                let new = view.voxel_crossed(&voxel, (&c[0], &c[7]), c.iter());
                let old = view
                    .footprint(c.iter())
                    .is_some_and(|(rect, depths, _, centre)| view.box_crossed(&voxel, &rect, depths, centre));
                assert_eq!(new, old, "voxel {key:?} at {r} m");
                verdicts[new as usize] += 1;
                let (lo, hi) = view.relative(&voxel);
                by_first += view.first_pixel(&c[0], &c[7]).is_some_and(|p| view.pixel_crosses(p, &lo, &hi)) as usize;
            }
        });
        assert!(verdicts[0] > 1000 && verdicts[1] > 1000 && by_first * 3 > verdicts[1], "{verdicts:?} {by_first}");
    }

    /// A block, or a run of 2 x 2 blocks with the bounds of the pyramid's second level, that
    /// [`View::block_misses`] rules out has no pixel whose slab test passes, for voxels around
    /// the frames' surfaces (where the exact tests run); and it rules out many.
    #[test]
    fn block_tests_keep_every_pixel_that_crosses() {
        let (mut kept_crossing, mut ruled_out, mut case) = ([0usize; 2], [0usize; 2], 0);
        for_random_views(11, 60, |rng, rays, view, r| {
            case += 1;
            let seg = view.seg;
            let (blocks_wide, blocks_high) = (seg.levels[0].width, seg.height.div_ceil(BLOCK));
            for _ in 0..40 {
                // A voxel near the end of a random pixel's segment.
                let (u, v) = ((rng.uniform() * seg.width as f64) as u32, (rng.uniform() * seg.height as f64) as u32);
                let Some(ray) = rays.ray(u, v) else { continue };
                let end = FrameRays::endpoint(&ray);
                let key: [i32; 3] =
                    std::array::from_fn(|a| floor_i32(end[a] / r) + rng.range(-2.0, 3.0).floor() as i32);
                let lo: [f32; 3] = std::array::from_fn(|a| (key[a] as f64 * r - view.origin[a]) as f32);
                let hi: [f32; 3] = std::array::from_fn(|a| ((key[a] + 1) as f64 * r - view.origin[a]) as f32);
                // Level 0, block by block; level 1 (when there is one), its cells' runs of blocks.
                for (l, level) in seg.levels.iter().enumerate().take(2) {
                    for cv in 0..blocks_high.div_ceil(1 << l) {
                        for cu in 0..level.width {
                            let bu = (cu << l, (((cu + 1) << l) - 1).min(blocks_wide - 1));
                            let bv = (cv << l, (((cv + 1) << l) - 1).min(blocks_high - 1));
                            let crossing = (bv.0 * BLOCK..((bv.1 + 1) * BLOCK).min(seg.height)).any(|v| {
                                (bu.0 * BLOCK..((bu.1 + 1) * BLOCK).min(seg.width)).any(|u| {
                                    slabs_cross(&[seg.pixel(v * seg.width + u)], &view.inv_dirs(u, v), &lo, &hi)[0]
                                })
                            });
                            let out = view.block_misses(bu, bv, &level.cells[cv * level.width + cu], &lo, &hi);
                            assert!(
                                !(out && crossing),
                                "case {case}: blocks {bu:?} x {bv:?} ruled out of voxel {key:?}"
                            );
                            kept_crossing[l] += crossing as usize;
                            ruled_out[l] += out as usize;
                        }
                    }
                }
            }
        });
        assert!(kept_crossing[0] > 1000 && ruled_out[0] > 10 * kept_crossing[0], "{kept_crossing:?} {ruled_out:?}");
        assert!(kept_crossing[1] > 500 && ruled_out[1] > 5 * kept_crossing[1], "{kept_crossing:?} {ruled_out:?}");
    }

    /// Voxels left open change nothing else: with random voxels and whole bricks settled,
    /// every other voxel is crossed or not as without, and the surfaces are the same.
    #[test]
    fn settled_voxels_are_left_open_and_nothing_else() {
        let (mut open_in_view, mut compared) = (0usize, 0usize);
        for_random_cases(23, (0.03, 0.2), |case, rays, limits, r| {
            // Per brick, from its key: a quarter wholly settled, a quarter half, the rest not.
            let settled = |b: BrickKey| -> SlotMask {
                let h = (b.0[0].wrapping_mul(73_856_093)
                    ^ b.0[1].wrapping_mul(19_349_663)
                    ^ b.0[2].wrapping_mul(83_492_791)) as u32;
                match h % 4 {
                    0 => [u64::MAX; 8],
                    1 => std::array::from_fn(|w| 0x9e37_79b9_7f4a_7c15u64.rotate_left(w as u32 * 7 + h % 64)),
                    _ => [0; 8],
                }
            };
            let frame = rays.frame;
            let all = Projector::default().crossed_voxels(frame, limits, r, None, None);
            let some = Projector::default().crossed_voxels(frame, limits, r, None, Some(&settled));
            let ((crossed, ends), (crossed_open, ends_open)) = (voxel_sets(&all), voxel_sets(&some));
            assert_eq!(ends, ends_open, "case {case}");
            let open = |k: &VoxelKey| mask_has(&settled(k.brick()), k.slot()) && !ends.contains(k);
            for k in crossed.union(&crossed_open) {
                if open(k) {
                    open_in_view += 1;
                } else {
                    assert_eq!(crossed.contains(k), crossed_open.contains(k), "case {case}, voxel {k:?}");
                    compared += 1;
                }
            }
        });
        assert!(open_in_view > 10_000 && compared > 10_000, "{open_in_view} open, {compared} compared");
    }

    /// A cube of 2 x 2 x 2 or 4 x 4 x 4 voxels that the exact test says no segment enters
    /// holds no voxel the exact test says is crossed (what lets [`split_voxels!`] skip it).
    #[test]
    fn a_cube_no_segment_enters_holds_no_crossed_voxel() {
        let (mut empty, mut entered) = (0usize, 0usize);
        for_random_cases(29, (0.02, 0.15), |case, rays, limits, r| {
            with_undecided(rays, limits, r, |view, undecided| {
                let exact = |b: &Box3| {
                    view.footprint(view.corners(b).iter())
                        .is_some_and(|(rect, depths, _, centre)| view.box_crossed(b, &rect, depths, centre))
                };
                for (brick, _) in undecided {
                    let base = Box3::of_brick(brick).lo;
                    for edge in [2, 4] {
                        for cube in 0..(BRICK_EDGE / edge).pow(3) {
                            let n = BRICK_EDGE / edge;
                            let lo = [0, 1, 2].map(|a| base[a] + edge * (cube / n.pow(a as u32) % n));
                            let b = Box3 { lo, hi: lo.map(|x| x + edge) };
                            if exact(&b) {
                                entered += 1;
                                continue;
                            }
                            empty += 1;
                            for z in lo[2]..lo[2] + edge {
                                for y in lo[1]..lo[1] + edge {
                                    for x in lo[0]..lo[0] + edge {
                                        let voxel = Box3 { lo: [x, y, z], hi: [x + 1, y + 1, z + 1] };
                                        assert!(!exact(&voxel), "case {case}: voxel {:?} crossed in {b:?}", voxel.lo);
                                    }
                                }
                            }
                        }
                    }
                }
            });
        });
        assert!(empty > 1000 && entered > 1000, "{empty} cubes not entered, {entered} entered");
    }

    /// [`cube_meets`], [`cube_within`] and [`cube_set`] against the voxels one by one.
    #[test]
    fn cube_masks_are_their_voxels() {
        let mut rng = Rng::new(3);
        for _ in 0..300 {
            let mask: SlotMask = std::array::from_fn(|_| {
                let (a, b) = ((rng.uniform() * u32::MAX as f64) as u64, (rng.uniform() * u32::MAX as f64) as u64);
                (a << 32 | b) & if rng.uniform() < 0.5 { u64::MAX } else { !0xff00_ff00 }
            });
            let edge = [1, 2, 4, 8][(rng.uniform() * 4.0) as usize];
            let lo = [0, 1, 2].map(|_| -16 + edge * (rng.uniform() * (BRICK_EDGE / edge) as f64) as i32);
            let b = Box3 { lo, hi: lo.map(|x| x + edge) };
            let slots: Vec<bool> = (lo[2]..b.hi[2])
                .flat_map(|z| (lo[1]..b.hi[1]).flat_map(move |y| (lo[0]..b.hi[0]).map(move |x| VoxelKey([x, y, z]))))
                .map(|k| mask_has(&mask, k.slot()))
                .collect();
            assert_eq!(cube_meets(&b, &mask), slots.iter().any(|s| *s), "{b:?}");
            assert_eq!(cube_within(&b, &mask), slots.iter().all(|s| *s), "{b:?}");
            // Setting the cube's voxels of `of` (all, or a random half) in another mask.
            let half: SlotMask = std::array::from_fn(|w| mask[w].rotate_left(17 + w as u32));
            for of in [[u64::MAX; 8], half] {
                let other: SlotMask = std::array::from_fn(|w| mask[w].rotate_left(5));
                let (mut set, mut each) = (other, other);
                cube_set(&b, &of, &mut set);
                for z in lo[2]..b.hi[2] {
                    for y in lo[1]..b.hi[1] {
                        for x in lo[0]..b.hi[0] {
                            let slot = VoxelKey([x, y, z]).slot();
                            if mask_has(&of, slot) {
                                mask_set(&mut each, slot);
                            }
                        }
                    }
                }
                assert_eq!(set, each, "{b:?}");
            }
        }
    }

    #[test]
    fn same_voxels_as_walking_every_ray() {
        let mut rng = Rng::new(7);
        let (mut total, mut differ) = (0usize, 0usize);
        for case in 0..120 {
            let frame = random_frame(&mut rng);
            let r = rng.range(0.03, 0.25);
            let limits = random_limits(case, &mut rng);
            let (walk, walk_ends) = walked(&frame, &limits, r);
            let (proj, proj_ends) = projected(&frame, &limits, r);
            let diff = walk.symmetric_difference(&proj).count();
            total += walk.len();
            differ += diff;
            assert!(diff <= 2 + walk.len() / 1000, "case {case}: {diff} of {} voxels differ", walk.len());
            let end_diff = walk_ends.symmetric_difference(&proj_ends).count();
            assert!(!walk_ends.is_empty() || case % 3 != 0, "case {case}: no surfaces");
            assert!(end_diff <= 2, "case {case}: {end_diff} end voxels differ");
        }
        eprintln!("{differ} of {total} voxels differ");
        assert!(total > 100_000 && differ * 10_000 <= total, "{differ} of {total}");
    }
}
