//! Analytic scenes: solid boxes, spheres and vertical cylinders seen by a pinhole depth
//! camera from listed or orbiting viewpoints, or along a path. They give exact depth images and exact
//! ground-truth occupancy ("is this point inside?") for tests and evaluation.
//!
//! The scene file format is fixed (README, "Scene files"); unknown keys are errors.

use std::path::Path;

use nalgebra::Vector3;
use serde::Deserialize;

use crate::error::{Error, Result, parse_toml, read_text};
use crate::frames::{Camera, DepthImage, Frame, NoiseModel, Pose, look_at};

/// A solid primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// Axis-aligned box.
    Box {
        /// Lower corner.
        min: [f64; 3],
        /// Upper corner.
        max: [f64; 3],
    },
    /// Ball.
    Sphere {
        /// Centre.
        center: [f64; 3],
        /// Radius.
        radius: f64,
    },
    /// Vertical (world z) cylinder with flat caps.
    Cylinder {
        /// Axis position in x, y.
        center: [f64; 2],
        /// Radius.
        radius: f64,
        /// Bottom and top z.
        z: [f64; 2],
    },
}

/// Interval of `t` where `o + t d` lies within `[lo, hi]` on one axis (`None` if never).
fn slab(o: f64, d: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
    if d == 0.0 {
        return (o >= lo && o <= hi).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let (a, b) = ((lo - o) / d, (hi - o) / d);
    Some(if a < b { (a, b) } else { (b, a) })
}

/// Interval where a quadratic `a t^2 + b t + c <= 0` (with `a >= 0`).
fn quadratic_inside(a: f64, b: f64, c: f64) -> Option<(f64, f64)> {
    if a == 0.0 {
        return (c <= 0.0).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return None;
    }
    let q = disc.sqrt();
    Some(((-b - q) / (2.0 * a), (-b + q) / (2.0 * a)))
}

fn intersect(a: Option<(f64, f64)>, b: Option<(f64, f64)>) -> Option<(f64, f64)> {
    let (a, b) = (a?, b?);
    let i = (a.0.max(b.0), a.1.min(b.1));
    (i.0 <= i.1).then_some(i)
}

impl Shape {
    /// Is `p` inside the solid (boundary included)?
    pub fn contains(&self, p: [f64; 3]) -> bool {
        match *self {
            Shape::Box { min, max } => (0..3).all(|a| p[a] >= min[a] && p[a] <= max[a]),
            Shape::Sphere { center, radius } => {
                (0..3).map(|a| (p[a] - center[a]).powi(2)).sum::<f64>() <= radius * radius
            }
            Shape::Cylinder { center, radius, z } => {
                (p[0] - center[0]).powi(2) + (p[1] - center[1]).powi(2) <= radius * radius
                    && p[2] >= z[0]
                    && p[2] <= z[1]
            }
        }
    }

    /// The interval of `t` where `o + t d` is inside the solid.
    fn interval(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, f64)> {
        match *self {
            Shape::Box { min, max } => {
                let x = slab(o.x, d.x, min[0], max[0]);
                intersect(intersect(x, slab(o.y, d.y, min[1], max[1])), slab(o.z, d.z, min[2], max[2]))
            }
            Shape::Sphere { center, radius } => {
                let oc = o - Vector3::from(center);
                quadratic_inside(d.dot(d), 2.0 * d.dot(&oc), oc.dot(&oc) - radius * radius)
            }
            Shape::Cylinder { center, radius, z } => {
                let (ox, oy) = (o.x - center[0], o.y - center[1]);
                let side = quadratic_inside(
                    d.x * d.x + d.y * d.y,
                    2.0 * (d.x * ox + d.y * oy),
                    ox * ox + oy * oy - radius * radius,
                );
                intersect(side, slab(o.z, d.z, z[0], z[1]))
            }
        }
    }

    /// Smallest `t >= 0` where the ray `o + t d` is inside the solid (0 if it starts inside).
    pub fn first_hit(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<f64> {
        let (lo, hi) = self.interval(o, d)?;
        (hi >= 0.0).then_some(lo.max(0.0))
    }
}

/// A simulated world: camera, optional noise model, solids and viewpoints.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The simulated depth camera (with `min_depth` / `max_depth`).
    pub camera: Camera,
    /// Noise added to `depth/`; `None` renders noise-free depth in both folders.
    pub noise: Option<NoiseModel>,
    /// The solids.
    pub shapes: Vec<Shape>,
    /// Camera poses, one per rendered frame.
    pub views: Vec<Pose>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    camera: Camera,
    noise: Option<toml::Value>,
    #[serde(rename = "box", default)]
    boxes: Vec<BoxDef>,
    #[serde(rename = "sphere", default)]
    spheres: Vec<SphereDef>,
    #[serde(rename = "cylinder", default)]
    cylinders: Vec<CylinderDef>,
    #[serde(rename = "view", default)]
    views: Vec<ViewDef>,
    orbit: Option<OrbitDef>,
    path: Option<PathDef>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxDef {
    min: [f64; 3],
    max: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SphereDef {
    center: [f64; 3],
    radius: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CylinderDef {
    center: [f64; 2],
    radius: f64,
    z: [f64; 2],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ViewDef {
    eye: [f64; 3],
    target: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OrbitDef {
    center: [f64; 3],
    radius: f64,
    height: f64,
    views: u32,
}

/// A trajectory: `frames` views at equal steps along the polyline through `waypoints`, each
/// looking horizontally along the direction of travel, turned by a yaw that swings
/// `sweep_deg / 2` degrees either way over `sweep_period` frames (a robot looking around).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PathDef {
    waypoints: Vec<[f64; 3]>,
    frames: u32,
    #[serde(default)]
    sweep_deg: f64,
    #[serde(default = "default_sweep_period")]
    sweep_period: f64,
}

fn default_sweep_period() -> f64 {
    40.0
}

/// Most views a scene may list or generate (each becomes a rendered image).
const MAX_VIEWS: u32 = 1_000_000;

impl PathDef {
    fn views(&self) -> std::result::Result<Vec<Pose>, String> {
        let finite = self.waypoints.iter().flatten().all(|v| v.is_finite());
        if self.waypoints.len() < 2 || !finite {
            return Err("[path]: need at least two finite waypoints".into());
        }
        if self.frames < 2 || self.frames > MAX_VIEWS {
            return Err(format!("[path]: frames must be 2 to {MAX_VIEWS}, got {}", self.frames));
        }
        let sweep = self.sweep_deg.is_finite() && self.sweep_deg >= 0.0 && self.sweep_deg < 360.0;
        if !(sweep && self.sweep_period > 0.0 && self.sweep_period.is_finite()) {
            return Err("[path]: need 0 <= sweep_deg < 360 and sweep_period > 0".into());
        }
        let points: Vec<Vector3<f64>> = self.waypoints.iter().map(|w| Vector3::from(*w)).collect();
        let legs: Vec<(Vector3<f64>, Vector3<f64>, f64)> = points
            .windows(2)
            .map(|w| (w[0], w[1] - w[0], (w[1] - w[0]).norm()))
            .filter(|(_, d, len)| *len > 1e-9 && d.x.hypot(d.y) > 1e-9)
            .collect();
        if legs.len() + 1 < points.len() {
            return Err("[path]: consecutive waypoints must differ in x or y (the camera looks along the path)".into());
        }
        let total: f64 = legs.iter().map(|l| l.2).sum();
        let (mut leg, mut start) = (0, 0.0);
        let mut views = Vec::with_capacity(self.frames as usize);
        for k in 0..self.frames {
            let s = total * k as f64 / (self.frames - 1) as f64;
            while leg + 1 < legs.len() && s > start + legs[leg].2 {
                start += legs[leg].2;
                leg += 1;
            }
            let (from, d, len) = legs[leg];
            let eye = from + d * ((s - start) / len).min(1.0);
            let yaw = d.y.atan2(d.x)
                + 0.5 * self.sweep_deg.to_radians() * (std::f64::consts::TAU * k as f64 / self.sweep_period).sin();
            let target = eye + Vector3::new(yaw.cos(), yaw.sin(), 0.0);
            views.push(look_at(eye, target).map_err(|m| format!("[path] view {k}: {m}"))?);
        }
        Ok(views)
    }
}

impl Scene {
    /// Reads a scene file.
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_toml(&read_text(path)?, path)
    }

    /// Parses scene TOML; `origin` names the file in errors.
    ///
    /// ```
    /// let text = r#"
    /// [camera]
    /// fx = 100.0
    /// fy = 100.0
    /// cx = 31.5
    /// cy = 23.5
    /// width = 64
    /// height = 48
    /// depth_scale = 5000.0
    /// [[box]]
    /// min = [-1.0, -1.0, -1.0]
    /// max = [1.0, 1.0, 1.0]
    /// [[view]]
    /// eye = [3.0, 0.0, 0.0]
    /// target = [0.0, 0.0, 0.0]
    /// "#;
    /// let scene = mrfmap::source::Scene::from_toml(text, "inline".as_ref()).unwrap();
    /// let depth = scene.render(&scene.views[0]);
    /// assert!((depth.get(32, 24).unwrap() - 2.0).abs() < 1e-6);
    /// assert!(scene.contains([0.5, 0.5, 0.5]));
    /// ```
    pub fn from_toml(text: &str, origin: &Path) -> Result<Self> {
        let f: SceneFile = parse_toml(text, origin)?;
        let bad = |m: String| Error::file(origin, m);
        f.camera.validate().map_err(|m| bad(format!("[camera]: {m}")))?;
        let noise = f.noise.map(|v| NoiseModel::from_value(v, origin)).transpose()?;
        if let Some(n) = &noise {
            n.check_camera(&f.camera).map_err(|m| bad(format!("[noise]: {m}")))?;
        }
        let mut shapes = Vec::new();
        for (i, b) in f.boxes.iter().enumerate() {
            if (0..3).any(|a| !(b.min[a] < b.max[a])) {
                return Err(bad(format!("box {i}: need min < max on every axis")));
            }
            shapes.push(Shape::Box { min: b.min, max: b.max });
        }
        for (i, s) in f.spheres.iter().enumerate() {
            if !(s.radius > 0.0) {
                return Err(bad(format!("sphere {i}: radius must be positive")));
            }
            shapes.push(Shape::Sphere { center: s.center, radius: s.radius });
        }
        for (i, c) in f.cylinders.iter().enumerate() {
            if !(c.radius > 0.0 && c.z[0] < c.z[1]) {
                return Err(bad(format!("cylinder {i}: need radius > 0 and z[0] < z[1]")));
            }
            shapes.push(Shape::Cylinder { center: c.center, radius: c.radius, z: c.z });
        }
        let mut views = Vec::new();
        for (i, v) in f.views.iter().enumerate() {
            views.push(
                look_at(Vector3::from(v.eye), Vector3::from(v.target)).map_err(|m| bad(format!("view {i}: {m}")))?,
            );
        }
        if let Some(o) = &f.orbit {
            if !views.is_empty() {
                return Err(bad("give either [[view]] entries or an [orbit], not both".into()));
            }
            if o.views == 0 || o.views > MAX_VIEWS || !(o.radius > 0.0) {
                return Err(bad(format!("[orbit]: need 1 to {MAX_VIEWS} views and radius > 0")));
            }
            for k in 0..o.views {
                let a = std::f64::consts::TAU * k as f64 / o.views as f64;
                let eye = Vector3::new(o.center[0] + o.radius * a.cos(), o.center[1] + o.radius * a.sin(), o.height);
                views.push(look_at(eye, Vector3::from(o.center)).map_err(|m| bad(format!("[orbit] view {k}: {m}")))?);
            }
        }
        if let Some(p) = &f.path {
            if !views.is_empty() {
                return Err(bad("give one of [[view]] entries, an [orbit] or a [path]".into()));
            }
            views = p.views().map_err(bad)?;
        }
        if views.is_empty() {
            return Err(bad("no viewpoints: add [[view]] entries, an [orbit] or a [path]".into()));
        }
        Ok(Scene { camera: f.camera, noise, shapes, views })
    }

    /// Ground-truth occupancy: is `p` inside any solid?
    pub fn contains(&self, p: [f64; 3]) -> bool {
        self.shapes.iter().any(|s| s.contains(p))
    }

    /// Exact z-depth image from `pose`; pixels whose depth is outside the camera's
    /// `[min_depth, max_depth]` (or that see nothing) are 0.
    pub fn render(&self, pose: &Pose) -> DepthImage {
        use rayon::prelude::*;
        let cam = &self.camera;
        let rot = pose.rotation.to_rotation_matrix();
        let eye = pose.translation.vector;
        let (min_z, max_z) = (cam.min_depth.unwrap_or(0.0), cam.max_depth.unwrap_or(f64::INFINITY));
        let w = cam.width as usize;
        let mut data = vec![0f32; cam.pixel_count()];
        data.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
            for (u, out) in row.iter_mut().enumerate() {
                // With the camera ray scaled to z = 1, the ray parameter is the z-depth.
                let d = rot * cam.pixel_ray(u as f64, v as f64);
                let z = self.shapes.iter().filter_map(|s| s.first_hit(&eye, &d)).fold(f64::INFINITY, f64::min);
                if z > 0.0 && z >= min_z && z <= max_z && z.is_finite() {
                    *out = z as f32;
                }
            }
        });
        DepthImage::from_vec(cam.width, cam.height, data).expect("sized from camera")
    }

    /// Frame `index` of the scene seen from `pose`: its depth image (noisy with the scene's
    /// noise model and `seed`, or noise-free), the scene's camera and noise model.
    pub fn frame(&self, index: usize, pose: &Pose, seed: Option<u64>) -> Frame {
        let truth = self.render(pose);
        let depth = match seed {
            Some(s) => self.add_noise(&truth, s, index),
            None => truth,
        };
        let noise = self.noise.clone().map(std::sync::Arc::new);
        Frame { index, timestamp: index as f64, depth, pose: *pose, camera: self.camera, noise }
    }

    /// `truth` with the scene's noise model applied ([`NoiseModel::sample`]); noise-free
    /// scenes return it unchanged.
    pub fn add_noise(&self, truth: &DepthImage, seed: u64, view: usize) -> DepthImage {
        match &self.noise {
            Some(noise) => noise.sample(truth, seed, view as u64),
            None => truth.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::Rng;

    /// Marching reference for `first_hit`: small steps along the ray, first inside sample.
    fn marched(s: &Shape, o: &Vector3<f64>, d: &Vector3<f64>, t_max: f64, h: f64) -> Option<f64> {
        let mut t = 0.0;
        while t <= t_max {
            let p = o + d * t;
            if s.contains([p.x, p.y, p.z]) {
                return Some(t);
            }
            t += h;
        }
        None
    }

    #[test]
    fn first_hit_agrees_with_marching() {
        let shapes = [
            Shape::Box { min: [-0.5, -0.3, 0.0], max: [0.4, 0.6, 0.8] },
            Shape::Sphere { center: [0.1, -0.2, 0.3], radius: 0.45 },
            Shape::Cylinder { center: [0.2, 0.1], radius: 0.25, z: [-0.2, 0.7] },
        ];
        let mut rng = Rng::new(21);
        let h = 1e-4;
        for s in &shapes {
            for _ in 0..300 {
                let o = Vector3::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), rng.range(-2.0, 2.0));
                let target = Vector3::new(rng.range(-0.6, 0.6), rng.range(-0.6, 0.6), rng.range(-0.4, 0.9));
                let d = (target - o).normalize();
                let exact = s.first_hit(&o, &d).filter(|t| *t <= 5.0);
                let reference = marched(s, &o, &d, 5.0, h);
                match (exact, reference) {
                    (Some(a), Some(b)) => assert!((a - b).abs() <= h, "{s:?}: {a} vs {b}"),
                    (None, None) => {}
                    // Grazing rays may slip between samples.
                    (Some(a), None) => {
                        let (lo, hi) = s.interval(&o, &d).unwrap();
                        assert!(hi - lo < 2.0 * h || a > 5.0 - h, "{s:?}: missed by marching");
                    }
                    (None, Some(b)) => panic!("{s:?}: exact missed a hit at {b}"),
                }
            }
        }
    }

    #[test]
    fn per_patch_noise_lands_on_its_patch() {
        // A wall 2 m ahead fills a 40x40 image of 2x2 patches, each with its own bias.
        let text = r#"
[camera]
fx = 20.0
fy = 20.0
cx = 19.5
cy = 19.5
width = 40
height = 40
depth_scale = 5000.0
[noise]
bias = [0.0]
std = [0.001]
[noise.patches]
size = 20
rows = 2
cols = 2
bias = [[0.0], [0.01], [0.02], [0.03]]
std = [[0.001], [0.001], [0.001], [0.004]]
[[box]]
min = [2.0, -10.0, -10.0]
max = [3.0, 10.0, 10.0]
[[view]]
eye = [0.0, 0.0, 0.0]
target = [1.0, 0.0, 0.0]
"#;
        let scene = Scene::from_toml(text, Path::new("patches.toml")).unwrap();
        let truth = scene.render(&scene.views[0]);
        let noisy = scene.add_noise(&truth, 5, 0);
        assert_eq!(noisy, scene.add_noise(&truth, 5, 0), "seeded");
        for (patch, (bias, std)) in [(0.0, 0.001), (0.01, 0.001), (0.02, 0.001), (0.03, 0.004)].into_iter().enumerate()
        {
            let (u0, v0) = ((patch % 2) as u32 * 20, (patch / 2) as u32 * 20);
            let res: Vec<f64> = (v0..v0 + 20)
                .flat_map(|v| (u0..u0 + 20).map(move |u| (u, v)))
                .map(|(u, v)| (noisy.get(u, v).unwrap() - truth.get(u, v).unwrap()) as f64)
                .collect();
            let n = res.len() as f64;
            let mean = res.iter().sum::<f64>() / n;
            let sd = (res.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / n).sqrt();
            assert!((mean - bias).abs() < 4.0 * std / n.sqrt() + 1e-6, "patch {patch}: mean {mean}, bias {bias}");
            assert!((sd / std - 1.0).abs() < 0.2, "patch {patch}: sd {sd}, std {std}");
        }
    }

    #[test]
    fn orbit_and_errors() {
        let base =
            "[camera]\nfx = 50.0\nfy = 50.0\ncx = 15.5\ncy = 11.5\nwidth = 32\nheight = 24\ndepth_scale = 5000.0\n";
        let orbit = format!("{base}[orbit]\ncenter = [0.0, 0.0, 0.5]\nradius = 2.0\nheight = 1.5\nviews = 4\n");
        let scene = Scene::from_toml(&orbit, Path::new("s.toml")).unwrap();
        assert_eq!(scene.views.len(), 4);
        let first = scene.views[0].translation.vector;
        assert!((first - Vector3::new(2.0, 0.0, 1.5)).norm() < 1e-12);
        let e = Scene::from_toml(&format!("{orbit}[[pyramid]]\nsize = 1\n"), Path::new("s.toml")).unwrap_err();
        assert!(e.to_string().contains("s.toml") && e.to_string().contains("pyramid"), "{e}");
        let e = Scene::from_toml(base, Path::new("s.toml")).unwrap_err();
        assert!(e.to_string().contains("no viewpoints"), "{e}");
        // A path: equal steps along the waypoints, looking along the way.
        let path =
            format!("{base}[path]\nwaypoints = [[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [2.0, 3.0, 1.0]]\nframes = 6\n");
        let scene = Scene::from_toml(&path, Path::new("s.toml")).unwrap();
        let eyes: Vec<Vector3<f64>> = scene.views.iter().map(|p| p.translation.vector).collect();
        assert!((eyes[1] - Vector3::new(1.0, 0.0, 1.0)).norm() < 1e-12, "{:?}", eyes[1]);
        assert!((eyes[5] - Vector3::new(2.0, 3.0, 1.0)).norm() < 1e-12);
        let ahead = |p: &Pose| p.rotation * Vector3::z();
        assert!((ahead(&scene.views[0]) - Vector3::x()).norm() < 1e-9);
        assert!((ahead(&scene.views[4]) - Vector3::y()).norm() < 1e-9);
        let e = Scene::from_toml(
            &format!("{path}[orbit]\ncenter = [0.0, 0.0, 0.5]\nradius = 2.0\nheight = 1.5\nviews = 4\n"),
            Path::new("s.toml"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("one of"), "{e}");
        let e = Scene::from_toml(
            &format!("{base}[path]\nwaypoints = [[0.0, 0.0, 1.0]]\nframes = 6\n"),
            Path::new("s.toml"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("two finite waypoints"), "{e}");
    }
}
