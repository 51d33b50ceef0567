//! Range scans: readings of a sensor that measures range along known beam directions (planar
//! laser scanners, spinning lidars, omnidirectional range sensors), with "no return" beams.
//!
//! A depth camera's reading is a [`super::Frame`]; everything else is a [`RangeScan`]. Both
//! become the same world-space rays (`crate::rays::Rays`), so the log-odds and CRM engines
//! integrate either. The noise model of a scan is a polynomial in *range* (z-depth = range
//! along a beam), with no per-patch table.

use std::sync::Arc;

use super::{NoiseModel, Pose};
use crate::error::{Error, Result};

/// One beam: its direction in the sensor frame and what it measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Beam {
    /// Direction in the sensor frame (unit length; [`RangeScan::new`] normalises).
    pub dir: [f64; 3],
    /// Measured range in metres; `None` when nothing returned within the sensor's range,
    /// which says "free up to the maximum range".
    pub range: Option<f64>,
}

/// One scan of a range sensor.
#[derive(Clone, Debug)]
pub struct RangeScan {
    /// Position of the scan in its sequence.
    pub index: usize,
    /// Sensor-to-world transform.
    pub pose: Pose,
    /// The beams.
    pub beams: Vec<Beam>,
    /// The sensor's maximum range: no-return beams are free up to here.
    pub max_range: f64,
    /// Range noise (polynomials in range); `None` uses the engine's default.
    pub noise: Option<Arc<NoiseModel>>,
}

impl RangeScan {
    /// A scan, checked: finite pose, non-zero finite directions (normalised here), positive
    /// finite ranges, positive maximum range, and a noise model without patches.
    pub fn new(
        index: usize,
        pose: Pose,
        beams: Vec<Beam>,
        max_range: f64,
        noise: Option<Arc<NoiseModel>>,
    ) -> Result<Self> {
        let bad = |m: String| Error::Invalid(format!("range scan {index}: {m}"));
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion().coords;
        if !(t.iter().chain(q.iter()).all(|v| v.is_finite())) {
            return Err(bad("pose is NaN or infinite".into()));
        }
        if !(max_range > 0.0 && max_range.is_finite()) {
            return Err(bad(format!("maximum range must be positive and finite, got {max_range}")));
        }
        if noise.as_ref().is_some_and(|n| n.patches.is_some()) {
            return Err(bad("a range scan's noise model cannot have per-pixel patches".into()));
        }
        let mut beams = beams;
        for (k, b) in beams.iter_mut().enumerate() {
            let n = (b.dir[0] * b.dir[0] + b.dir[1] * b.dir[1] + b.dir[2] * b.dir[2]).sqrt();
            if !(n > 0.0 && n.is_finite()) {
                return Err(bad(format!("beam {k}: direction {:?} is zero or not finite", b.dir)));
            }
            b.dir = b.dir.map(|d| d / n);
            if let Some(r) = b.range
                && !(r > 0.0 && r.is_finite())
            {
                return Err(bad(format!("beam {k}: range {r} is not positive and finite (use None for no return)")));
            }
        }
        Ok(RangeScan { index, pose, beams, max_range, noise })
    }

    /// A planar 360-degree scan: beam `k` of `ranges.len()` at angle `2 pi k / n` in the
    /// sensor's x-y plane (counter-clockwise from +x).
    ///
    /// ```
    /// use mrfmap::frames::{Pose, RangeScan};
    /// let scan = RangeScan::planar(0, Pose::identity(), &[Some(1.0), None, Some(0.5), None], 2.0, None).unwrap();
    /// assert!((scan.beams[1].dir[1] - 1.0).abs() < 1e-12); // 90 degrees: +y
    /// assert_eq!(scan.beams[1].range, None);
    /// ```
    pub fn planar(
        index: usize,
        pose: Pose,
        ranges: &[Option<f64>],
        max_range: f64,
        noise: Option<Arc<NoiseModel>>,
    ) -> Result<Self> {
        let n = ranges.len() as f64;
        let beams = ranges
            .iter()
            .enumerate()
            .map(|(k, &range)| {
                let a = std::f64::consts::TAU * k as f64 / n;
                Beam { dir: [a.cos(), a.sin(), 0.0], range }
            })
            .collect();
        Self::new(index, pose, beams, max_range, noise)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_scans_are_refused() {
        let beam = |dir, range| Beam { dir, range };
        let id = Pose::identity();
        let e = RangeScan::new(3, id, vec![beam([0.0; 3], Some(1.0))], 2.0, None).unwrap_err().to_string();
        assert!(e.contains("range scan 3") && e.contains("beam 0"), "{e}");
        let e = RangeScan::new(0, id, vec![beam([1.0, 0.0, 0.0], Some(f64::NAN))], 2.0, None).unwrap_err();
        assert!(e.to_string().contains("not positive"), "{e}");
        assert!(RangeScan::new(0, id, vec![], 0.0, None).is_err());
        let s = RangeScan::new(0, id, vec![beam([0.0, 3.0, 4.0], None)], 2.0, None).unwrap();
        assert_eq!(s.beams[0].dir, [0.0, 0.6, 0.8]);
    }
}
