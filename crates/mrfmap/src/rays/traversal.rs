//! Exact voxel traversal of a ray segment (Amanatides & Woo's 3D DDA).
//!
//! For the ray `p(s) = origin + s dir`, `s` in `[s_start, s_end]`, [`traverse`] yields every
//! voxel the segment passes through with positive length, in order, with the range where
//! the ray enters and leaves it. With a unit `dir`, ranges are metres along the ray.
//!
//! Exactness choices: the next boundary of each axis is recomputed from the integer voxel
//! index (no accumulated `t_delta` drift, so 10 km rays stay exact); when a ray passes
//! exactly through an edge or corner, the voxels it only touches (zero length) are skipped,
//! so there are no zero-length crossings and no duplicates; a ray starting on a face and
//! moving away from the voxel that `floor` picks starts in the voxel it actually enters.

use crate::map::VoxelKey;

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

/// Iterator over the voxels crossed by a ray segment; see [`traverse`].
#[derive(Clone, Debug)]
pub struct Traversal {
    origin: [f64; 3],
    inv_dir: [f64; 3],
    step: [i32; 3],
    key: [i32; 3],
    t_max: [f64; 3],
    s: f64,
    s_end: f64,
    resolution: f64,
    done: bool,
}

/// Voxels of size `resolution` crossed by `origin + s dir` for `s` in `[s_start, s_end]`.
///
/// Returns an empty traversal for non-finite input, a zero direction or `s_end <= s_start`.
///
/// ```
/// use mrfmap::rays::traverse;
/// use mrfmap::map::VoxelKey;
/// let hits: Vec<_> = traverse([0.05, 0.05, 0.05], [1.0, 0.0, 0.0], 0.0, 0.25, 0.1).collect();
/// let keys: Vec<_> = hits.iter().map(|c| c.key).collect();
/// assert_eq!(keys, vec![VoxelKey([0, 0, 0]), VoxelKey([1, 0, 0]), VoxelKey([2, 0, 0])]);
/// assert!((hits[0].length() - 0.05).abs() < 1e-12);
/// assert!((hits[2].s_out - 0.25).abs() < 1e-12);
/// ```
pub fn traverse(origin: [f64; 3], dir: [f64; 3], s_start: f64, s_end: f64, resolution: f64) -> Traversal {
    let finite = origin.iter().chain(dir.iter()).chain([s_start, s_end, resolution].iter()).all(|v| v.is_finite());
    let moving = dir.iter().any(|d| *d != 0.0);
    let mut t = Traversal {
        origin,
        inv_dir: [0.0; 3],
        step: [0; 3],
        key: [0; 3],
        t_max: [f64::INFINITY; 3],
        s: s_start,
        s_end,
        resolution,
        done: !(finite && moving && s_end > s_start && resolution > 0.0),
    };
    if t.done {
        return t;
    }
    for a in 0..3 {
        let start = origin[a] + s_start * dir[a];
        t.key[a] = (start / resolution).floor() as i32;
        if dir[a] != 0.0 {
            t.inv_dir[a] = 1.0 / dir[a];
            t.step[a] = if dir[a] > 0.0 { 1 } else { -1 };
            t.t_max[a] = t.boundary(a);
        }
    }
    t
}

impl Traversal {
    /// Range at which the ray leaves the current voxel through its face on axis `a`.
    #[inline]
    fn boundary(&self, a: usize) -> f64 {
        let face = self.key[a] + (self.step[a] > 0) as i32;
        (face as f64 * self.resolution - self.origin[a]) * self.inv_dir[a]
    }
}

impl Iterator for Traversal {
    type Item = Crossing;

    #[inline]
    fn next(&mut self) -> Option<Crossing> {
        while !self.done {
            let t = &self.t_max;
            let a = if t[0] <= t[1] {
                if t[0] <= t[2] { 0 } else { 2 }
            } else if t[1] <= t[2] {
                1
            } else {
                2
            };
            let exit = self.t_max[a];
            let key = VoxelKey(self.key);
            let s_in = self.s;
            if exit >= self.s_end {
                self.done = true;
                return (self.s_end > s_in).then_some(Crossing { key, s_in, s_out: self.s_end });
            }
            self.key[a] += self.step[a];
            self.t_max[a] = self.boundary(a);
            if exit > s_in {
                self.s = exit;
                return Some(Crossing { key, s_in, s_out: exit });
            }
            // Zero length (edge/corner touch, or a start on a face): skip the voxel.
        }
        None
    }
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
        let got: Vec<Crossing> = traverse(origin, dir, s0, s1, r).collect();
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
            for a in keep_on..3 {
                origin[a] += rng.range(0.0, r);
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
        let first = traverse([0.0, 0.05, 0.05], [-1.0, 0.0, 0.0], 0.0, 0.15, 0.1).next().unwrap();
        assert_eq!(first.key, VoxelKey([-1, 0, 0]));
        assert_eq!(first.s_in, 0.0);
        let keys: Vec<_> =
            traverse([-0.25, -0.25, -0.25], [1.0, 0.0, 0.0], 0.0, 0.3, 0.1).map(|c| c.key.0[0]).collect();
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
            let v = [0.3, -0.5, 0.81];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) as f64;
            v.map(|x: f64| x / n.sqrt())
        };
        let s1 = 10_000.0;
        let r = 0.05;
        let n = traverse(origin, dir, 0.0, s1, r).count();
        let end = [0, 1, 2].map(|a| origin[a] + s1 * dir[a]);
        let expected: i64 =
            (0..3).map(|a| ((end[a] / r).floor() as i64 - (origin[a] / r).floor() as i64).abs()).sum::<i64>() + 1;
        assert_eq!(n as i64, expected);
    }

    #[test]
    fn degenerate_input_is_empty() {
        assert_eq!(traverse([0.0; 3], [0.0; 3], 0.0, 1.0, 0.1).count(), 0);
        assert_eq!(traverse([0.0; 3], [1.0, 0.0, 0.0], 1.0, 1.0, 0.1).count(), 0);
        assert_eq!(traverse([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0, 1.0, 0.1).count(), 0);
        assert_eq!(traverse([0.0; 3], [1.0, 0.0, 0.0], 0.0, f64::NAN, 0.1).count(), 0);
    }
}
