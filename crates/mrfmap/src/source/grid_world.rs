//! Planar worlds for 2D experiments: a grid of square cells, each free or occupied, and a
//! simulated omnidirectional range sensor moving through it (the CRM paper's sec. 8.1 set-up).
//!
//! The world is one voxel layer of the 3D grid: cell `(i, j)` is voxel `(i, j, 0)` of the same
//! size, and scans are taken in the plane `z = cell / 2`, so the 3D engines map it unchanged
//! and their voxels compare cell for cell with the truth.

use std::ops::ControlFlow;
use std::sync::Arc;

use crate::error::{Error, Result};
use crate::frames::{NoiseModel, Pose, RangeScan};
use crate::map::VoxelKey;
use crate::random::Rng;
use crate::rays::for_each_crossing;

/// A `width x height` grid of `cell`-metre squares with its lower-left corner at the origin.
///
/// ```
/// use mrfmap::source::GridWorld;
/// let mut w = GridWorld::new(0.05, 40, 40).unwrap();
/// w.fill(30, 0, 31, 40); // a wall at x = 1.5 .. 1.55 m
/// let r = w.cast([0.5, 1.0], 0.0, 2.0).unwrap();
/// assert!((r - 1.0).abs() < 1e-9);
/// assert_eq!(w.cast([0.5, 1.0], std::f64::consts::PI, 0.4), None); // nothing within 0.4 m
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct GridWorld {
    /// Cell side in metres.
    pub cell: f64,
    /// Cells along x.
    pub width: usize,
    /// Cells along y.
    pub height: usize,
    occupied: Vec<bool>,
}

impl GridWorld {
    /// An empty world.
    pub fn new(cell: f64, width: usize, height: usize) -> Result<Self> {
        if !(cell > 0.0 && cell.is_finite()) || width == 0 || height == 0 {
            return Err(Error::Invalid(format!("a grid world needs cell > 0 and cells, got {cell}, {width}x{height}")));
        }
        Ok(GridWorld { cell, width, height, occupied: vec![false; width * height] })
    }

    /// Marks cells `x0..x1` by `y0..y1` occupied (clipped to the world).
    pub fn fill(&mut self, x0: usize, y0: usize, x1: usize, y1: usize) {
        for y in y0..y1.min(self.height) {
            for x in x0..x1.min(self.width) {
                self.occupied[y * self.width + x] = true;
            }
        }
    }

    /// Is cell `(x, y)` occupied? Cells outside the world are free.
    pub fn is_occupied(&self, x: i64, y: i64) -> bool {
        (0..self.width as i64).contains(&x)
            && (0..self.height as i64).contains(&y)
            && self.occupied[y as usize * self.width + x as usize]
    }

    /// Is the point `p` (metres) inside an occupied cell?
    pub fn contains(&self, p: [f64; 2]) -> bool {
        self.is_occupied((p[0] / self.cell).floor() as i64, (p[1] / self.cell).floor() as i64)
    }

    /// The voxel of cell `(x, y)`.
    pub fn key(&self, x: usize, y: usize) -> VoxelKey {
        VoxelKey([x as i32, y as i32, 0])
    }

    /// Exact range from `origin` along `angle` (radians from +x) to the first occupied cell,
    /// `None` if there is none within `max_range`. Uses the engines' own voxel traversal.
    pub fn cast(&self, origin: [f64; 2], angle: f64, max_range: f64) -> Option<f64> {
        let o = [origin[0], origin[1], 0.5 * self.cell];
        let d = [angle.cos(), angle.sin(), 0.0];
        let mut hit = None;
        for_each_crossing(o, d, 0.0, max_range, self.cell, |c| {
            if self.is_occupied(c.key.0[0] as i64, c.key.0[1] as i64) {
                hit = Some(c.s_in);
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        });
        hit
    }

    /// A noisy planar scan from `position` with `beams` beams over 360 degrees: each true
    /// range plus Gaussian noise of `std` metres. Readings at or beyond `max_range` (truly or
    /// by noise) are "no return"; readings the noise pushes below 1 mm are clamped to 1 mm.
    /// The scan carries the matching noise model (no bias, constant std).
    pub fn scan(
        &self,
        index: usize,
        position: [f64; 2],
        beams: usize,
        max_range: f64,
        std: f64,
        rng: &mut Rng,
    ) -> Result<RangeScan> {
        let ranges: Vec<Option<f64>> = (0..beams)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / beams as f64;
                let noise = rng.normal(); // drawn for every beam so streams do not depend on hits
                let measured = self.cast(position, a, max_range)? + std * noise;
                (measured < max_range).then_some(measured.max(1e-3))
            })
            .collect();
        let pose = Pose::translation(position[0], position[1], 0.5 * self.cell);
        let noise = NoiseModel::aggregate(Default::default(), crate::frames::Poly([std, 0.0, 0.0]));
        RangeScan::planar(index, pose, &ranges, max_range, Some(Arc::new(noise)))
    }

    /// Our version of the CRM paper's simulated world (sec. 8.1), whose figure we do not have:
    /// 2 m x 2 m of 0.05 m cells (40 x 40) with a one-cell border wall, two interior walls
    /// forming three rooms with doorways, a 3 x 3 box, an L-shaped obstacle, and two one-cell
    /// pillars (the thin obstacles where log-odds is least consistent); and 23 waypoints
    /// (metres) through all rooms, each at least 0.1 m from any obstacle.
    pub fn crm_paper() -> (GridWorld, Vec<[f64; 2]>) {
        let mut w = GridWorld::new(0.05, 40, 40).expect("valid");
        w.fill(0, 0, 40, 1); // border
        w.fill(0, 39, 40, 40);
        w.fill(0, 0, 1, 40);
        w.fill(39, 0, 40, 40);
        w.fill(1, 20, 14, 21); // wall from the left, doorway x = 14..20
        w.fill(20, 20, 26, 21);
        w.fill(26, 1, 27, 14); // wall from the bottom, doorway y = 14..19
        w.fill(26, 19, 27, 21);
        w.fill(8, 8, 11, 11); // 3 x 3 box
        w.fill(30, 26, 36, 27); // L-shaped obstacle
        w.fill(30, 27, 31, 33);
        w.fill(17, 30, 18, 31); // pillars
        w.fill(33, 8, 34, 9);
        let waypoints = [
            [0.25, 0.25],
            [0.25, 0.65],
            [0.3, 0.85],
            [0.7, 0.3],
            [1.0, 0.3],
            [1.0, 0.7],
            [0.75, 0.85],
            [0.85, 1.2],
            [0.3, 1.3],
            [0.3, 1.7],
            [0.7, 1.75],
            [1.15, 1.6],
            [1.2, 1.25],
            [1.55, 1.15],
            [1.8, 1.15],
            [1.75, 1.55],
            [1.5, 1.8],
            [1.8, 1.8],
            [1.5, 0.85],
            [1.5, 0.55],
            [1.5, 0.2],
            [1.8, 0.25],
            [1.8, 0.7],
        ];
        (w, waypoints.to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_world_waypoints_are_clear_and_casts_agree_with_marching() {
        let (w, waypoints) = GridWorld::crm_paper();
        assert_eq!(waypoints.len(), 23);
        for p in &waypoints {
            for k in 0..16 {
                let a = std::f64::consts::TAU * k as f64 / 16.0;
                let q = [p[0] + 0.1 * a.cos(), p[1] + 0.1 * a.sin()];
                assert!(!w.contains(q), "waypoint {p:?} is within 0.1 m of an obstacle");
            }
        }
        let mut rng = Rng::new(3);
        for _ in 0..500 {
            let p = waypoints[(rng.next_u64() % 23) as usize];
            let a = rng.range(0.0, std::f64::consts::TAU);
            let cast = w.cast(p, a, 1.0);
            let mut marched = None;
            let mut s = 0.0;
            while s <= 1.0 {
                if w.contains([p[0] + s * a.cos(), p[1] + s * a.sin()]) {
                    marched = Some(s);
                    break;
                }
                s += 1e-4;
            }
            match (cast, marched) {
                (Some(c), Some(m)) => assert!((c - m).abs() < 2e-4, "{c} vs {m}"),
                (c, m) => assert!(c.is_none() && m.is_none_or(|m| m > 0.999), "{c:?} vs {m:?}"),
            }
        }
    }
}
