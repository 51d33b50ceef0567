//! Exact voxel traversal of a ray segment (Amanatides & Woo's 3D DDA).
//!
//! For the ray `p(s) = origin + s dir`, `s` in `[s_start, s_end]`, [`for_each_crossing`] visits every
//! voxel the segment passes through with positive length, in order, with the range where
//! the ray enters and leaves it. With a unit `dir`, ranges are metres along the ray.
//!
//! Exactness choices: when a ray passes exactly through an edge or corner, the voxels it
//! only touches (zero length) are skipped, so there are no zero-length crossings and no
//! duplicates; a ray starting on a face and moving away from the voxel that `floor` picks
//! starts in the voxel it actually enters. Boundaries are found by adding `t_delta` per
//! step (the classic form); the accumulated error is at most one rounding per step (about
//! 1e-7 m after 10 km at 5 cm), far below anything a depth sensor resolves, and the
//! property tests below check the result against brute force, including 10 km rays.
//!
//! Speed: the walk is a closure-driven loop ([`for_each_crossing`]) rather than an
//! `Iterator`: on icl-livingroom-5 the iterator form cost 13 ns per voxel and this loop
//! 4 ns (the iterator's state round-trips through memory each step). A branchless axis
//! choice measured 20% slower than the branchy one here, so the code stays plain.

use std::ops::ControlFlow;

use crate::map::{BRICK_EDGE, BrickKey, SlotMask, VoxelKey, floor_i32};

/// One voxel crossed by a ray: `s_out - s_in > 0` is the length inside it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crossing {
    /// The voxel.
    pub key: VoxelKey,
    /// Range where the ray enters the voxel (or the segment start).
    pub s_in: f64,
    /// Range where the ray leaves the voxel (or the segment end).
    pub s_out: f64,
}

impl Crossing {
    /// Length of the ray inside the voxel.
    #[inline]
    pub fn length(&self) -> f64 {
        self.s_out - self.s_in
    }
}

/// Calls `visit` for each voxel of size `resolution` crossed by `origin + s dir` for `s` in
/// `[s_start, s_end]`, in order along the ray, until `visit` returns `ControlFlow::Break`.
///
/// Visits nothing for non-finite input, a zero direction or `s_end <= s_start`.
///
/// ```
/// use std::ops::ControlFlow;
/// use mrfmap::rays::for_each_crossing;
/// let mut keys = Vec::new();
/// for_each_crossing([0.05, 0.05, 0.05], [1.0, 0.0, 0.0], 0.0, 0.25, 0.1, |c| {
///     keys.push(c.key.0);
///     ControlFlow::Continue(())
/// });
/// assert_eq!(keys, vec![[0, 0, 0], [1, 0, 0], [2, 0, 0]]);
/// ```
// Inlined for the walk's setup (its divisions and `floor`s), which then runs in the caller's
// copy; `Walk::crossings` stays a call: inlined into a brick's AVX2 walk it took 1.05x the time.
#[inline(always)]
pub fn for_each_crossing(
    origin: [f64; 3],
    dir: [f64; 3],
    s_start: f64,
    s_end: f64,
    resolution: f64,
    visit: impl FnMut(Crossing) -> ControlFlow<()>,
) {
    if let Some(walk) = Walk::new(origin, dir, resolution) {
        walk.crossings(s_start, s_end, visit);
    }
}

/// One ray through a grid of one resolution, prepared for walking several stretches of it
/// ([`Walk::crossings`]): what [`for_each_crossing`] computes per call that does not depend
/// on the stretch; or, for the MRF's trace, prepared for walking only through the bricks it
/// chooses ([`Walk::crossings_in_bricks`]).
#[derive(Clone, Copy, Debug)]
pub struct Walk {
    origin: [f64; 3],
    dir: [f64; 3],
    resolution: f64,
    step: [i32; 3],
    /// Range between voxel boundaries per axis (infinite along an axis the ray does not move).
    t_delta: [f64; 3],
}

impl Walk {
    /// The walk of `origin + s dir` through voxels of size `resolution`; `None` for non-finite
    /// input, a zero direction or a resolution that is not positive.
    #[inline]
    pub fn new(origin: [f64; 3], dir: [f64; 3], resolution: f64) -> Option<Walk> {
        let finite = origin.iter().chain(dir.iter()).all(|v| v.is_finite()) && resolution.is_finite();
        let moving = dir.iter().any(|d| *d != 0.0);
        if !(finite && moving && resolution > 0.0) {
            return None;
        }
        let step = dir.map(|d| {
            if d > 0.0 {
                1
            } else if d < 0.0 {
                -1
            } else {
                0
            }
        });
        let t_delta = dir.map(|d| if d != 0.0 { resolution / d.abs() } else { 0.0 });
        Some(Walk { origin, dir, resolution, step, t_delta })
    }

    /// [`for_each_crossing`] of the stretch `[s_start, s_end]` (nothing for a non-finite or
    /// empty stretch).
    #[inline]
    pub fn crossings(&self, s_start: f64, s_end: f64, mut visit: impl FnMut(Crossing) -> ControlFlow<()>) {
        if !(s_start.is_finite() && s_end.is_finite() && s_end > s_start) {
            return;
        }
        let Walk { origin, dir, resolution, step, t_delta } = *self;
        let mut key = [0i32; 3];
        let mut t_max = [f64::INFINITY; 3]; // range of the next boundary per axis
        for a in 0..3 {
            key[a] = floor_i32((origin[a] + s_start * dir[a]) / resolution);
            if dir[a] != 0.0 {
                let face = key[a] + (dir[a] > 0.0) as i32;
                t_max[a] = (face as f64 * resolution - origin[a]) / dir[a];
            }
        }
        let mut at = Cursor { key, faces: t_max, s: s_start };
        step_voxels(
            &mut at,
            step,
            t_delta,
            s_end,
            |_| true,
            |key, s_in, s_out| visit(Crossing { key: VoxelKey(key), s_in, s_out }),
        );
    }

    /// The crossings of `[s_start, s_end]` that lie in the bricks (cubes of [`BRICK_EDGE`]
    /// voxels) that `enter` accepts, in order along the ray, with no step through the voxels
    /// of the other bricks. The MRF's trace walks its rays this way: most bricks a ray
    /// crosses are empty space, and a walk set up again in each brick (two walks, one per
    /// level) cost more than the steps inside it.
    ///
    /// `enter(ctx, brick, s)` is asked for each brick the stretch reaches, in order, with the
    /// range `s` where the ray enters it (or `s_start`); `None` skips the brick, `Some(handle)`
    /// walks it: `visit(ctx, handle, slot, s_in, s_out)` for each of its voxels crossed with
    /// positive length (`slot` as [`VoxelKey::slot`]). Through a run of accepted bricks the
    /// walk is one voxel walk, as [`Walk::crossings`]; where it enters an accepted brick after
    /// skipped ones (or at the start), the voxel `floor` finds is kept inside that brick, so
    /// rounding at its face cannot start the walk in a neighbour. Bricks are stepped through
    /// at their own scale while skipped. (`ctx` is passed to both, which may each need it
    /// mutably.)
    #[inline(always)] // (so that the MRF's AVX2 trace has its closures in its own copy)
    pub fn crossings_in_bricks<C, H: Copy>(
        &self,
        s_start: f64,
        s_end: f64,
        ctx: &mut C,
        mut enter: impl FnMut(&mut C, BrickKey, f64) -> Option<H>,
        mut visit: impl FnMut(&mut C, H, usize, f64, f64),
    ) {
        if !(s_start.is_finite() && s_end.is_finite() && s_end > s_start) {
            return;
        }
        let Walk { origin, dir, resolution: r, step, t_delta } = *self;
        const EDGE: i32 = BRICK_EDGE;
        let e = r * EDGE as f64;
        let b_delta = [t_delta[0] * EDGE as f64, t_delta[1] * EDGE as f64, t_delta[2] * EDGE as f64];
        let mut s = s_start;
        // (Arrays written out, not `[0, 1, 2].map(..)`: in the MRF's AVX2 copy that map was a
        // call of its own, which cannot inline a closure compiled for AVX2.)
        let floor = |a: usize, size: f64| floor_i32((origin[a] + s * dir[a]) / size);
        let mut bk = [floor(0, e), floor(1, e), floor(2, e)];
        // The range of the next face of the voxel (or brick) `k` along axis `a`.
        let face = |k: i32, a: usize, size: f64| {
            if dir[a] != 0.0 { ((k + (dir[a] > 0.0) as i32) as f64 * size - origin[a]) / dir[a] } else { f64::INFINITY }
        };
        // `bk` was asked already (and refused) when the voxel walk left for it.
        let mut asked = false;
        loop {
            // Bricks, until one is accepted.
            let mut bt = [face(bk[0], 0, e), face(bk[1], 1, e), face(bk[2], 2, e)];
            let handle = loop {
                if !asked && let Some(h) = enter(ctx, BrickKey(bk), s) {
                    break h;
                }
                asked = false;
                let a = if bt[0] <= bt[1] && bt[0] <= bt[2] {
                    0
                } else if bt[1] <= bt[2] {
                    1
                } else {
                    2
                };
                if bt[a] >= s_end {
                    return;
                }
                s = s.max(bt[a]);
                bk[a] += step[a];
                bt[a] += b_delta[a];
            };
            // Its voxels, and on through the accepted bricks that follow.
            let mut h = handle;
            let base = [bk[0] * EDGE, bk[1] * EDGE, bk[2] * EDGE];
            let local = |a: usize| (floor_i32((origin[a] + s * dir[a]) / r) - base[a]).clamp(0, EDGE - 1);
            let first = [local(0), local(1), local(2)];
            let faces =
                [face(base[0] + first[0], 0, r), face(base[1] + first[1], 1, r), face(base[2] + first[2], 2, r)];
            let mut at = Cursor { key: first, faces, s };
            loop {
                // (One call of `visit`, for the last voxel too: the MRF's trace inlines it.)
                let within = |l: i32| (l as u32) < EDGE as u32;
                let left = step_voxels(&mut at, step, t_delta, s_end, within, |[lx, ly, lz], s_in, s_out| {
                    visit(ctx, h, (lx | ly << 3 | lz << 6) as usize, s_in, s_out);
                    ControlFlow::Continue(())
                });
                // Past the brick's side, the walk is in the next brick.
                let Some(a) = left else { return };
                at.key[a] -= step[a] * EDGE;
                bk[a] += step[a];
                s = at.s;
                match enter(ctx, BrickKey(bk), s) {
                    Some(next) => h = next,
                    None => {
                        asked = true;
                        break;
                    }
                }
            }
        }
    }
}

/// The voxels of one brick that the ray `p(t) = origin + t d` crosses with positive length
/// for `t` in `[t0, t1]`, a stretch that lies inside the brick (clipped to its faces by the
/// caller), set in `mask` (slots as [`VoxelKey::slot`]). Points are relative to the brick's
/// lower corner; `inv` holds the reciprocals of `d` (infinite for a zero component), which
/// the caller found for several rays at once. The voxels are [`Walk::crossings`]' for that
/// stretch, up to rounding where the ray grazes an edge or a corner: the same walk, with the
/// faces found by multiplying with the reciprocals where it divides, and the first voxel kept
/// inside the brick (at the face it enters by, `floor` may round to the neighbour's). A ray
/// set up this way costs three divisions for four rays, where [`for_each_crossing`] costs a
/// dozen per ray; log-odds mapping walks a few hundred thousand such stretches a frame
/// (bricks where voxels are smaller than pixels, [`crate::rays::Projector`]).
// Inlined into the projection's AVX2 copy of a brick's walk, where its `floor` is an
// instruction (as a call of its own it was a baseline function: 1.01x the time).
#[inline(always)]
pub(crate) fn mark_in_brick(
    origin: [f64; 3],
    d: [f64; 3],
    inv: [f64; 3],
    (t0, t1): (f64, f64),
    resolution: f64,
    mask: &mut SlotMask,
) {
    const LAST: i32 = BRICK_EDGE - 1;
    let r = resolution;
    let inv_r = 1.0 / r;
    // The first voxel, and per axis the range of its next face.
    let local = |a: usize| floor_i32((origin[a] + t0 * d[a]) * inv_r).clamp(0, LAST);
    let face = |k: i32, a: usize| {
        if d[a] != 0.0 { ((k + (d[a] > 0.0) as i32) as f64 * r - origin[a]) * inv[a] } else { f64::INFINITY }
    };
    let first = [local(0), local(1), local(2)];
    let faces = [face(first[0], 0), face(first[1], 1), face(first[2], 2)];
    let (delta, step) = (inv.map(|i| r * i.abs()), d.map(|x| if x > 0.0 { 1 } else { -1 }));
    // Past the brick's side (rounding at its far face), the walk ends.
    step_voxels(
        &mut Cursor { key: first, faces, s: t0 },
        step,
        delta,
        t1,
        |l| l as u32 <= LAST as u32,
        |[lx, ly, lz], _, _| {
            mask[lz as usize] |= 1 << (lx | ly << 3);
            ControlFlow::Continue(())
        },
    );
}

/// Where a voxel walk stands: its voxel, the range of its next face per axis, and the range
/// it has reached.
struct Cursor {
    key: [i32; 3],
    faces: [f64; 3],
    s: f64,
}

/// The voxel walk from `at`, one voxel `step` per axis every `delta`: calls `visit(voxel,
/// s_in, s_out)` for each voxel crossed with positive length up to `s_end`, until it breaks
/// (`None`), or until a step takes a coordinate where `within` refuses it: then `Some(axis)`,
/// with `at` past that step. Exactly one axis steps at a time: x on ties with x, else y on
/// ties with y. A voxel touched with zero length (an edge or a corner, or a start on a face)
/// is skipped. The walks of [`Walk::crossings`], [`Walk::crossings_in_bricks`] (which goes on
/// in the next brick where `within` refuses a step) and [`mark_in_brick`].
#[inline(always)]
fn step_voxels(
    at: &mut Cursor,
    step: [i32; 3],
    delta: [f64; 3],
    s_end: f64,
    within: impl Fn(i32) -> bool,
    mut visit: impl FnMut([i32; 3], f64, f64) -> ControlFlow<()>,
) -> Option<usize> {
    // Scalars, not arrays indexed by axis: indexed arrays live on the stack and every step
    // then waits on a store-to-load round trip (measured 7.5 -> 4 ns per voxel).
    let [mut tx, mut ty, mut tz] = at.faces;
    let [mut kx, mut ky, mut kz] = at.key;
    let mut s = at.s;
    loop {
        let step_x = tx <= ty && tx <= tz;
        let step_y = !step_x && ty <= tz;
        let exit = if step_x {
            tx
        } else if step_y {
            ty
        } else {
            tz
        };
        // (One call of `visit`, for the last voxel too.)
        let last = exit >= s_end;
        let end = if last { s_end } else { exit };
        if end > s {
            if visit([kx, ky, kz], s, end).is_break() {
                return None;
            }
            s = end;
        }
        if last {
            return None;
        }
        let (a, k) = if step_x {
            kx += step[0];
            tx += delta[0];
            (0, kx)
        } else if step_y {
            ky += step[1];
            ty += delta[1];
            (1, ky)
        } else {
            kz += step[2];
            tz += delta[2];
            (2, kz)
        };
        if !within(k) {
            *at = Cursor { key: [kx, ky, kz], faces: [tx, ty, tz], s };
            return Some(a);
        }
    }
}

/// All crossings of a segment as a vector (see [`for_each_crossing`]).
///
/// ```
/// let c = mrfmap::rays::crossings([0.05, 0.05, 0.05], [1.0, 0.0, 0.0], 0.0, 0.25, 0.1);
/// assert_eq!(c.len(), 3);
/// assert!((c[0].length() - 0.05).abs() < 1e-12);
/// assert!((c[2].s_out - 0.25).abs() < 1e-12);
/// ```
pub fn crossings(origin: [f64; 3], dir: [f64; 3], s_start: f64, s_end: f64, resolution: f64) -> Vec<Crossing> {
    let mut out = Vec::new();
    for_each_crossing(origin, dir, s_start, s_end, resolution, |c| {
        out.push(c);
        ControlFlow::Continue(())
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// Brute force: sample the segment finely and list the distinct voxels in order.
    fn sampled(origin: [f64; 3], dir: [f64; 3], s0: f64, s1: f64, r: f64, n: usize) -> Vec<VoxelKey> {
        let mut out: Vec<VoxelKey> = Vec::new();
        for k in 0..n {
            let s = s0 + (s1 - s0) * (k as f64 + 0.5) / n as f64;
            let p = [0, 1, 2].map(|a| origin[a] + s * dir[a]);
            let key = VoxelKey::from_point(p, r);
            if out.last() != Some(&key) {
                out.push(key);
            }
        }
        out
    }

    /// Checks one ray against the brute-force reference and the traversal's own invariants.
    fn check(origin: [f64; 3], dir: [f64; 3], s0: f64, s1: f64, r: f64) {
        let got = crossings(origin, dir, s0, s1, r);
        let len = s1 - s0;
        let dir_norm = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
        let voxels_along = len * dir_norm / r;
        let n = ((voxels_along * 200.0) as usize).clamp(2000, 2_000_000);
        let h = len / n as f64;
        let reference = sampled(origin, dir, s0, s1, r, n);
        let ctx = format!("origin {origin:?} dir {dir:?} s [{s0}, {s1}] r {r}");
        assert!(!got.is_empty(), "{ctx}: no voxels");
        // Contiguous, positive, covering [s0, s1].
        assert!((got[0].s_in - s0).abs() <= 1e-9 * s1.abs().max(1.0), "{ctx}: starts at {}", got[0].s_in);
        assert_eq!(got.last().unwrap().s_out, s1, "{ctx}");
        for w in got.windows(2) {
            assert_eq!(w[0].s_out, w[1].s_in, "{ctx}: gap");
            let d = [0, 1, 2].map(|a| (w[0].key.0[a] - w[1].key.0[a]).abs());
            assert!(
                d.iter().all(|x| *x <= 1) && d.iter().sum::<i32>() >= 1,
                "{ctx}: jump {:?} -> {:?}",
                w[0].key,
                w[1].key
            );
        }
        let mut seen = std::collections::HashSet::new();
        for c in &got {
            assert!(c.length() > 0.0, "{ctx}: zero-length crossing");
            assert!(seen.insert(c.key), "{ctx}: duplicate {:?}", c.key);
            // The middle of the crossing lies in the voxel (to rounding).
            let m = 0.5 * (c.s_in + c.s_out);
            for a in 0..3 {
                let x = origin[a] + m * dir[a];
                let lo = c.key.0[a] as f64 * r;
                let tol = 1e-9 * (1.0 + x.abs());
                assert!(x >= lo - tol && x <= lo + r + tol, "{ctx}: midpoint off voxel {:?}", c.key);
            }
        }
        // Every sampled voxel was traversed; every traversed voxel longer than two samples was sampled.
        for k in &reference {
            assert!(seen.contains(k), "{ctx}: missed {k:?}");
        }
        let sampled_set: std::collections::HashSet<_> = reference.iter().collect();
        for c in &got {
            if c.length() > 2.0 * h {
                assert!(sampled_set.contains(&c.key), "{ctx}: extra {:?} of length {}", c.key, c.length());
            }
        }
    }

    fn unit(rng: &mut Rng) -> [f64; 3] {
        loop {
            let v = [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 0.1 && n <= 1.0 {
                return v.map(|x| x / n);
            }
        }
    }

    /// A resolution from 1 to 10 cm, an origin in a 6 m cube and a unit direction.
    fn random_ray(rng: &mut Rng) -> (f64, [f64; 3], [f64; 3]) {
        let r = [0.01, 0.02, 0.05, 0.1][(rng.next_u64() % 4) as usize];
        let origin = [0; 3].map(|_| rng.range(-3.0, 3.0));
        (r, origin, unit(rng))
    }

    #[test]
    fn random_rays_match_brute_force() {
        let mut rng = Rng::new(42);
        for _ in 0..400 {
            let r = [0.01, 0.02, 0.05, 0.1, 1.0][(rng.next_u64() % 5) as usize];
            let origin = [0; 3].map(|_| rng.range(-3.0, 3.0));
            let dir = unit(&mut rng);
            let s0 = if rng.uniform() < 0.3 { rng.range(0.0, 1.0) } else { 0.0 };
            let s1 = s0 + rng.range(1e-3, 60.0 * r);
            check(origin, dir, s0, s1, r);
        }
    }

    /// A prepared walk over consecutive stretches (here brick by brick) crosses the same
    /// voxels, with the same total length, as one walk over their union.
    #[test]
    fn a_walk_in_stretches_crosses_what_one_walk_does() {
        let mut rng = Rng::new(43);
        for _ in 0..300 {
            let r = [0.01, 0.02, 0.05][(rng.next_u64() % 3) as usize];
            let (origin, dir) = ([0; 3].map(|_| rng.range(-3.0, 3.0)), unit(&mut rng));
            let end = rng.range(0.1, 200.0 * r);
            let walk = Walk::new(origin, dir, r).unwrap();
            let mut pieces = Vec::new();
            for_each_crossing(origin, dir, 0.0, end, 8.0 * r, |b| {
                walk.crossings(b.s_in, b.s_out, |c| {
                    pieces.push(c);
                    ControlFlow::Continue(())
                });
                ControlFlow::Continue(())
            });
            let whole = crossings(origin, dir, 0.0, end, r);
            let keys = |v: &[Crossing]| {
                let mut k: Vec<VoxelKey> = v.iter().filter(|c| c.length() > 1e-9).map(|c| c.key).collect();
                k.dedup();
                k
            };
            assert_eq!(keys(&pieces), keys(&whole));
            let total = |v: &[Crossing]| v.iter().map(Crossing::length).sum::<f64>();
            assert!((total(&pieces) - total(&whole)).abs() < 1e-9, "{} vs {}", total(&pieces), total(&whole));
        }
        assert!(Walk::new([0.0; 3], [0.0; 3], 0.1).is_none() && Walk::new([0.0; 3], [1.0, 0.0, 0.0], 0.0).is_none());
    }

    /// A brick's walk from reciprocals crosses the voxels of that brick that one walk of the
    /// whole ray crosses, on random rays (along axes too) through random bricks, parametrised
    /// by a scaled direction as the projection's walks are (camera depth, not metres).
    #[test]
    fn a_walk_inside_one_brick_crosses_what_one_walk_does_there() {
        let mut rng = Rng::new(46);
        let (mut differ, mut total) = (0, 0);
        for trial in 0..3000 {
            let (r, origin, mut dir) = random_ray(&mut rng);
            if trial % 10 == 0 {
                dir[(rng.next_u64() % 3) as usize] = 0.0;
            }
            let end = rng.range(0.01, 100.0 * r);
            // The whole walk, and the bricks it passes through.
            let mut by_brick: std::collections::BTreeMap<[i32; 3], SlotMask> = Default::default();
            for_each_crossing(origin, dir, 0.0, end, r, |c| {
                crate::map::mask_set(by_brick.entry(c.key.brick().0).or_default(), c.key.slot());
                ControlFlow::Continue(())
            });
            // Each brick walked alone, with the direction scaled by 1 / 0.9 (as per metre of
            // camera depth) and the range likewise.
            let d = dir.map(|x| x / 0.9);
            let inv = d.map(|x| 1.0 / x);
            for (b, whole) in &by_brick {
                let corner = b.map(|k| (k * BRICK_EDGE) as f64 * r);
                let rel: [f64; 3] = std::array::from_fn(|a| origin[a] - corner[a]);
                let (mut t0, mut t1) = (0.0f64, end * 0.9);
                for a in 0..3 {
                    let (ta, tb) = (-rel[a] * inv[a], (BRICK_EDGE as f64 * r - rel[a]) * inv[a]);
                    if d[a] != 0.0 {
                        (t0, t1) = (t0.max(ta.min(tb)), t1.min(ta.max(tb)));
                    }
                }
                let mut mask = [0u64; 8];
                if t0 < t1 {
                    mark_in_brick(rel, d, inv, (t0, t1), r, &mut mask);
                }
                differ += (0..8).map(|w| (mask[w] ^ whole[w]).count_ones()).sum::<u32>();
                total += whole.iter().map(|w| w.count_ones()).sum::<u32>();
            }
        }
        // (Random rays graze no edge: they agree voxel for voxel.)
        assert!(total > 100_000 && differ == 0, "{differ} of {total} voxels differ");
    }

    /// A walk through chosen bricks crosses what one walk over the whole stretch crosses in
    /// those bricks, in order, with the same lengths (to rounding), and asks for every brick
    /// that walk passes through.
    #[test]
    fn a_walk_through_chosen_bricks_crosses_what_one_walk_does_in_them() {
        let mut rng = Rng::new(44);
        let (mut skipped, mut kept) = (0, 0);
        for trial in 0..600 {
            let (r, mut origin, mut dir) = random_ray(&mut rng);
            match trial % 5 {
                // From a voxel corner along an axis or a lattice diagonal: through faces,
                // edges and corners of voxels and bricks.
                0 => {
                    origin = origin.map(|o| (o / r).round() * r);
                    dir = [0; 3].map(|_| [-1.0, 0.0, 1.0][(rng.next_u64() % 3) as usize]);
                    if dir == [0.0; 3] {
                        dir[0] = 1.0;
                    }
                    let n = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
                    dir = dir.map(|d| d / n);
                }
                1 => dir[(rng.next_u64() % 3) as usize] = 0.0,
                _ => {}
            }
            let s0 = if rng.uniform() < 0.5 { rng.range(0.0, 40.0 * r) } else { 0.0 };
            let s1 = s0 + rng.range(1e-3, 300.0 * r);
            // About a third, two thirds, none or all of the bricks accepted.
            let share = [3, 1, 0, 100][trial % 4];
            let accept = |b: BrickKey| {
                let [x, y, z] = b.0.map(|c| c as u64);
                let h = x.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ y.wrapping_mul(0xC2B2_AE3D_27D4_EB4F) ^ z;
                (h >> 7) % 3 < share
            };
            let Some(walk) = Walk::new(origin, dir, r) else { continue };
            let mut out = (Vec::new(), std::collections::HashSet::new());
            walk.crossings_in_bricks(
                s0,
                s1,
                &mut out,
                |(_, asked), b, _| {
                    asked.insert(b);
                    accept(b).then_some(b)
                },
                |(got, _), b, slot, s_in, s_out| got.push(Crossing { key: b.voxel(slot), s_in, s_out }),
            );
            let (got, asked) = out;
            let ctx = format!("trial {trial}: origin {origin:?} dir {dir:?} s [{s0}, {s1}] r {r}");
            let whole = crossings(origin, dir, s0, s1, r);
            let long = |c: &&Crossing| c.length() > 1e-7 * r;
            let expected: Vec<&Crossing> = whole.iter().filter(|c| accept(c.key.brick())).filter(long).collect();
            let found: Vec<&Crossing> = got.iter().filter(long).collect();
            let keys = |v: &[&Crossing]| v.iter().map(|c| c.key).collect::<Vec<_>>();
            assert_eq!(keys(&found), keys(&expected), "{ctx}");
            for (a, b) in found.iter().zip(&expected) {
                assert!((a.length() - b.length()).abs() < 1e-9, "{ctx}: {a:?} vs {b:?}");
            }
            for (i, c) in got.iter().enumerate() {
                assert!(c.length() > 0.0 && c.s_in >= s0 && c.s_out <= s1, "{ctx}: {c:?}");
                assert!(i == 0 || got[i - 1].s_out <= c.s_in, "{ctx}: out of order at {i}");
                assert!(accept(c.key.brick()), "{ctx}: {c:?} in a skipped brick");
            }
            for c in &whole {
                assert!(
                    c.length() <= 1e-7 * r || asked.contains(&c.key.brick()),
                    "{ctx}: {:?} not asked",
                    c.key.brick()
                );
            }
            skipped += whole.iter().filter(|c| !accept(c.key.brick())).count();
            kept += expected.len();
        }
        assert!(skipped > 10_000 && kept > 10_000, "{skipped} crossings skipped, {kept} kept");
    }

    #[test]
    fn axis_parallel_and_planar_rays() {
        let mut rng = Rng::new(5);
        let r = 0.05;
        for _ in 0..200 {
            let origin = [0; 3].map(|_| rng.range(-2.0, 2.0));
            let mut dir = [0.0; 3];
            let axis = (rng.next_u64() % 3) as usize;
            dir[axis] = if rng.uniform() < 0.5 { 1.0 } else { -1.0 };
            if rng.uniform() < 0.5 {
                // In a coordinate plane: two non-zero components.
                let other = (axis + 1) % 3;
                dir[other] = rng.range(-1.0, 1.0);
                let n = (dir[axis] * dir[axis] + dir[other] * dir[other]).sqrt();
                dir = dir.map(|d| d / n);
            }
            check(origin, dir, 0.0, rng.range(0.01, 3.0), r);
        }
    }

    #[test]
    fn rays_starting_on_faces_edges_and_corners() {
        let mut rng = Rng::new(9);
        let r = 0.1;
        for _ in 0..400 {
            let mut origin = [0; 3].map(|_| (rng.next_u64() % 40) as f64 * r - 2.0);
            // Keep 0-3 coordinates off the lattice: corner, edge, face or interior starts.
            let keep_on = (rng.next_u64() % 4) as usize;
            for o in &mut origin[keep_on..] {
                *o += rng.range(0.0, r);
            }
            let mut dir = unit(&mut rng);
            if rng.uniform() < 0.4 {
                // Along a lattice diagonal: passes exactly through edges and corners.
                dir = [0; 3].map(|_| if rng.uniform() < 0.5 { 1.0 } else { -1.0 });
                let n = 3f64.sqrt();
                dir = dir.map(|d| d / n);
            }
            check(origin, dir, 0.0, rng.range(0.05, 2.0), r);
        }
    }

    #[test]
    fn negative_coordinates_and_face_starts_pick_the_entered_voxel() {
        // Start exactly on the face x = 0 moving -x: the first voxel is -1, not 0.
        let first = crossings([0.0, 0.05, 0.05], [-1.0, 0.0, 0.0], 0.0, 0.15, 0.1)[0];
        assert_eq!(first.key, VoxelKey([-1, 0, 0]));
        assert_eq!(first.s_in, 0.0);
        let keys: Vec<_> =
            crossings([-0.25, -0.25, -0.25], [1.0, 0.0, 0.0], 0.0, 0.3, 0.1).iter().map(|c| c.key.0[0]).collect();
        assert_eq!(keys, vec![-3, -2, -1, 0]);
    }

    #[test]
    fn very_long_rays_stay_exact() {
        let mut rng = Rng::new(77);
        for _ in 0..6 {
            let origin = [0; 3].map(|_| rng.range(-1000.0, 1000.0));
            let dir = unit(&mut rng);
            check(origin, dir, 0.0, rng.range(2000.0, 5000.0), 1.0);
        }
        // 10 km at 5 cm: count matches the sum of per-axis boundary crossings.
        let origin = [0.013, -0.021, 0.007];
        let dir = {
            let v: [f64; 3] = [0.3, -0.5, 0.81];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            v.map(|x| x / n)
        };
        let s1 = 10_000.0;
        let r = 0.05;
        let n = crossings(origin, dir, 0.0, s1, r).len();
        let end = [0, 1, 2].map(|a| origin[a] + s1 * dir[a]);
        let expected: i64 =
            (0..3).map(|a| ((end[a] / r).floor() as i64 - (origin[a] / r).floor() as i64).abs()).sum::<i64>() + 1;
        assert_eq!(n as i64, expected);
    }

    #[test]
    fn degenerate_input_is_empty() {
        assert_eq!(crossings([0.0; 3], [0.0; 3], 0.0, 1.0, 0.1).len(), 0);
        assert_eq!(crossings([0.0; 3], [1.0, 0.0, 0.0], 1.0, 1.0, 0.1).len(), 0);
        assert_eq!(crossings([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0, 1.0, 0.1).len(), 0);
        assert_eq!(crossings([0.0; 3], [1.0, 0.0, 0.0], 0.0, f64::NAN, 0.1).len(), 0);
    }
}
