//! Boxes of space: [`Aabb`] (a world box: a map's bounds, a query's region, a crop) and the
//! voxels one covers ([`box_keys`]). Here, beside the store, because maps, rays and outputs
//! all use them.

use super::floor_i32;

/// An axis-aligned box in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lower corner.
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
}

impl Aabb {
    /// A box; fails unless `min < max` on every axis and all values are finite.
    pub fn new(min: [f64; 3], max: [f64; 3]) -> crate::Result<Self> {
        if min.iter().chain(max.iter()).any(|v| !v.is_finite()) {
            return Err(crate::Error::Invalid(format!(
                "bounds need finite numbers (a box is a finite region), got {min:?} and {max:?}"
            )));
        }
        if (0..3).any(|a| min[a] >= max[a]) {
            return Err(crate::Error::Invalid(format!("bounds need min < max on every axis, got {min:?} and {max:?}")));
        }
        Ok(Aabb { min, max })
    }

    /// Parses `XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`.
    ///
    /// ```
    /// let b = mrfmap::map::Aabb::parse("-2,-2,0,2,2,3").unwrap();
    /// assert_eq!(b.max, [2.0, 2.0, 3.0]);
    /// assert!(mrfmap::map::Aabb::parse("1,2,3").is_err());
    /// let e = mrfmap::map::Aabb::parse("-inf,0,0,1,1,1").unwrap_err();
    /// assert!(e.to_string().contains("finite"));
    /// ```
    pub fn parse(text: &str) -> crate::Result<Self> {
        let v: Vec<f64> = text
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| crate::Error::Invalid(format!("bounds {text:?}: {e}")))?;
        if v.len() != 6 {
            return Err(crate::Error::Invalid(format!(
                "bounds {text:?}: need 6 numbers XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX"
            )));
        }
        Aabb::new([v[0], v[1], v[2]], [v[3], v[4], v[5]])
    }

    /// Is `p` inside (boundary included)?
    pub fn contains(&self, p: [f64; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] && p[a] <= self.max[a])
    }

    /// The part `[a, b]` of `[s0, s1]` where `origin + s dir` is inside the box (slab method).
    pub fn clip(&self, origin: [f64; 3], dir: [f64; 3], s0: f64, s1: f64) -> Option<(f64, f64)> {
        let (mut a, mut b) = (s0, s1);
        for k in 0..3 {
            if dir[k] == 0.0 {
                if origin[k] < self.min[k] || origin[k] > self.max[k] {
                    return None;
                }
                continue;
            }
            let t0 = (self.min[k] - origin[k]) / dir[k];
            let t1 = (self.max[k] - origin[k]) / dir[k];
            let (lo, hi) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
            a = a.max(lo);
            b = b.min(hi);
        }
        (a < b).then_some((a, b))
    }
}

/// Whether `key` lies in the inclusive key range `(lo, hi)` (as [`box_keys`] gives it).
#[inline]
pub fn key_in_box(key: [i32; 3], (lo, hi): ([i32; 3], [i32; 3])) -> bool {
    (0..3).all(|a| key[a] >= lo[a] && key[a] <= hi[a])
}

/// The inclusive voxel-key range of the voxels overlapping `region` with positive volume.
pub fn box_keys(region: &Aabb, resolution: f64) -> ([i32; 3], [i32; 3]) {
    let lo = region.min.map(|x| floor_i32(x / resolution));
    // The last voxel starts strictly below max: ceil(max / r) - 1.
    let hi = region.max.map(|x| -floor_i32(-x / resolution) - 1);
    (lo, hi)
}
