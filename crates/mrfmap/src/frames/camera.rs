//! Pinhole camera intrinsics (docs/ALGORITHMS.md section 1), read from a dataset's `camera.toml`.

use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result, parse_toml, read_text};

/// Pinhole intrinsics of a depth camera, no distortion.
///
/// `fx` or `fy` may be negative (ICL-NUIM flips the image y axis this way): the
/// pixel ray formula below handles it without special cases.
///
/// ```
/// let cam = mrfmap::frames::Camera::new(525.0, 525.0, 319.5, 239.5, 640, 480, 5000.0).unwrap();
/// let ray = cam.pixel_ray(319.5, 239.5);
/// assert_eq!((ray.x, ray.y, ray.z), (0.0, 0.0, 1.0));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Focal length in pixels along image columns.
    pub fx: f64,
    /// Focal length in pixels along image rows (negative for ICL-NUIM).
    pub fy: f64,
    /// Principal point column.
    pub cx: f64,
    /// Principal point row.
    pub cy: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Stored depth value per metre (5000 for TUM and ICL-NUIM 16-bit PNGs).
    pub depth_scale: f64,
    /// Nearest valid z-depth of the sensor in metres (used by the simulator; informational).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_depth: Option<f64>,
    /// Farthest valid z-depth of the sensor in metres (used by the simulator; informational).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_depth: Option<f64>,
}

/// Largest image side accepted (pixels).
pub const MAX_SIDE: u32 = 65_535;
/// Most pixels an image may have (a 16k x 8k sensor; 512 MiB as f32 depths).
pub const MAX_PIXELS: usize = 1 << 27;

impl Camera {
    /// Intrinsics without a depth range; fails on a zero focal length, empty image or bad scale.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32, depth_scale: f64) -> Result<Self> {
        let cam = Camera { fx, fy, cx, cy, width, height, depth_scale, min_depth: None, max_depth: None };
        cam.validate().map_err(Error::Invalid)?;
        Ok(cam)
    }

    /// Reads `camera.toml`; every problem names the file.
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_toml(&read_text(path)?, path)
    }

    /// Parses `camera.toml` text; `origin` names the file in errors.
    pub fn from_toml(text: &str, origin: &Path) -> Result<Self> {
        let cam: Camera = parse_toml(text, origin)?;
        cam.validate().map_err(|m| Error::file(origin, m))?;
        Ok(cam)
    }

    /// The TOML text of this camera, as `load` reads it.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("camera fields are plain numbers")
    }

    pub(crate) fn validate(&self) -> std::result::Result<(), String> {
        let finite = [self.fx, self.fy, self.cx, self.cy, self.depth_scale];
        if finite.iter().any(|v| !v.is_finite()) {
            return Err("intrinsics must be finite numbers".into());
        }
        if self.fx == 0.0 || self.fy == 0.0 {
            return Err(format!("focal lengths must be non-zero (fx = {}, fy = {})", self.fx, self.fy));
        }
        if self.width == 0 || self.height == 0 {
            return Err(format!("image size must be positive ({}x{})", self.width, self.height));
        }
        if self.width > MAX_SIDE || self.height > MAX_SIDE || self.pixel_count() > MAX_PIXELS {
            return Err(format!(
                "image size {}x{} is larger than any depth sensor's (at most {MAX_SIDE} pixels a side and \
                 {MAX_PIXELS} pixels in all)",
                self.width, self.height
            ));
        }
        if self.depth_scale <= 0.0 {
            return Err(format!("depth_scale must be positive, got {}", self.depth_scale));
        }
        if let (Some(a), Some(b)) = (self.min_depth, self.max_depth)
            && !(a >= 0.0 && b > a)
        {
            return Err(format!("need 0 <= min_depth < max_depth, got {a} and {b}"));
        }
        Ok(())
    }

    /// Camera-frame ray through pixel `(u, v)`, scaled so its z component is 1:
    /// multiplying by a z-depth gives the 3D point.
    #[inline]
    pub fn pixel_ray(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// Pixel coordinates `(u, v)` of a camera-frame point in front of the camera.
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_inverts_pixel_ray_with_negative_fy() {
        let cam = Camera::new(481.2, -480.0, 319.5, 239.5, 640, 480, 5000.0).unwrap();
        let p = cam.pixel_ray(100.0, 30.0) * 2.5;
        let (u, v) = cam.project(&p).unwrap();
        assert!((u - 100.0).abs() < 1e-9 && (v - 30.0).abs() < 1e-9);
        assert!(p.y > 0.0, "negative fy flips rows above the centre to +y");
    }

    #[test]
    fn rejects_bad_values() {
        assert!(Camera::new(0.0, 1.0, 0.0, 0.0, 10, 10, 1.0).is_err());
        assert!(Camera::new(1.0, 1.0, 0.0, 0.0, 0, 10, 1.0).is_err());
        assert!(Camera::new(1.0, 1.0, 0.0, 0.0, 10, 10, -5.0).is_err());
    }
}
