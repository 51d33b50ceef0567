//! Python bindings: build maps from numpy depth images and 4x4 poses with any engine, edit MRF
//! keyframes, query occupancy and variance at points (vectorised), get all voxels as arrays,
//! save, load and export. The Python-facing documentation is in `python/mrfmap/_mrfmap.pyi`.
//!
//! Every input array is checked here (dtype, shape, finite values, rigid poses) and refused with
//! a `ValueError` naming the argument, so bad input never reaches the engines.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use mrfmap::Choice;
use mrfmap::frames::{Beam, Camera, DepthImage, Frame, NoiseModel, Pose, RangeScan};
use mrfmap::inference::{
    Budget, BuildOptions, Engine, EngineConfig, EngineKind, Extent, KeyframeId, MapOutput, MrfEngine, check_build,
    frames_extent, new_engine, scan_extent,
};
use mrfmap::map::Aabb;
use mrfmap::map::Map;
use mrfmap::outputs::{
    LiveEngine, OctomapFormat, PlyOptions, PointAnswer, QueryOptions, VoxelSource, check_path, query_box, query_points,
    query_polyline, query_segments, write_octomap, write_ply,
};
use mrfmap::pipeline::{build, check_indices, dataset_extent, integrate, read_ahead, stream_bag};
use mrfmap::source::bag::BagOptions;
use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion};
use numpy::{PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::{PyMemoryError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// Occupancy and variance per queried point.
type Queried<'py> = PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>)>;

fn py_err(e: mrfmap::Error) -> PyErr {
    match e {
        mrfmap::Error::Io { .. } => PyOSError::new_err(e.to_string()),
        mrfmap::Error::Memory(_) => PyMemoryError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// `dtype` and `shape` of an array-like, for error messages.
fn describe(obj: &Bound<'_, PyAny>) -> String {
    let get = |name: &str| obj.getattr(name).and_then(|v| v.str().map(|s| s.to_string())).ok();
    match (get("dtype"), get("shape")) {
        (Some(d), Some(s)) => format!("dtype {d}, shape {s}"),
        _ => format!("a {}", obj.get_type().name().map(|n| n.to_string()).unwrap_or_default()),
    }
}

/// A 2-D array of any of the dtypes we accept, as f64 values in row-major order.
fn floats_2d(obj: &Bound<'_, PyAny>) -> Option<(usize, usize, Vec<f64>)> {
    if let Ok(a) = obj.extract::<PyReadonlyArray2<'_, f64>>() {
        let v = a.as_array();
        return Some((v.nrows(), v.ncols(), v.iter().copied().collect()));
    }
    if let Ok(a) = obj.extract::<PyReadonlyArray2<'_, f32>>() {
        let v = a.as_array();
        return Some((v.nrows(), v.ncols(), v.iter().map(|x| *x as f64).collect()));
    }
    None
}

/// A camera-to-world pose from a 4x4 rigid transform.
fn pose_of(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Pose> {
    let bad = |m: String| PyValueError::new_err(format!("{what}: {m}"));
    let Some((4, 4, m)) = floats_2d(obj) else {
        return Err(bad(format!("need a 4x4 float64 or float32 array, got {}", describe(obj))));
    };
    if m.iter().any(|v| !v.is_finite()) {
        return Err(bad("contains NaN or infinity".into()));
    }
    if (m[12].abs() + m[13].abs() + m[14].abs() + (m[15] - 1.0).abs()) > 1e-6 {
        return Err(bad(format!("last row must be [0, 0, 0, 1], got {:?}", &m[12..16])));
    }
    let r = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let off = (r.transpose() * r - Matrix3::identity()).abs().max();
    if off > 1e-4 || r.determinant() < 0.0 {
        return Err(bad(format!(
            "rotation part is not a rotation (|R^T R - I| = {off:.2e}, det {:.3})",
            r.determinant()
        )));
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(Pose::from_parts(Translation3::new(m[3], m[7], m[11]), q))
}

/// Points as an (N, 3) array of finite values; `what` names the argument in errors.
fn points_of(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<[f64; 3]>> {
    let Some((n, 3, v)) = floats_2d(obj) else {
        return Err(PyValueError::new_err(format!(
            "{what}: need an (N, 3) float64 or float32 array, got {}",
            describe(obj)
        )));
    };
    if v.iter().any(|x| !x.is_finite()) {
        return Err(PyValueError::new_err(format!("{what}: contains NaN or infinity")));
    }
    Ok((0..n).map(|i| [v[3 * i], v[3 * i + 1], v[3 * i + 2]]).collect())
}

/// The engine behind a mapper: the MRF keeps its own type for keyframe edits.
enum Inner {
    Mrf(Box<MrfEngine>),
    Online(Box<dyn Engine>),
}

impl Inner {
    fn engine(&self) -> &dyn Engine {
        match self {
            Inner::Mrf(e) => e.as_ref(),
            Inner::Online(e) => e.as_ref(),
        }
    }

    fn engine_mut(&mut self) -> &mut dyn Engine {
        match self {
            Inner::Mrf(e) => e.as_mut(),
            Inner::Online(e) => e.as_mut(),
        }
    }
}

/// Builds a map from depth images (see the stub file for the Python documentation).
#[pyclass(module = "mrfmap")]
struct Mapper {
    inner: Mutex<Inner>,
    /// What the engine was made from: its memory estimates.
    config: EngineConfig,
    camera: Camera,
    noise: Option<Arc<NoiseModel>>,
    frames: Mutex<usize>,
}

impl Mapper {
    /// Refuses a frame or scan spanning `extent` whose map alone would need more memory than
    /// the limit (`MRFMAP_MAX_MEMORY`, else three quarters of physical memory), as the CLI
    /// refuses a build: `MemoryError`, before any allocation.
    fn check_memory(&self, extent: Option<Extent>) -> PyResult<()> {
        let advice = "use a coarser resolution or a max_range";
        check_build(&self.config, extent, MapOutput::InMemory, advice).map_err(py_err)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn mrf_only<T>(&self, what: &str, f: impl FnOnce(&mut MrfEngine) -> mrfmap::Result<T>) -> PyResult<T> {
        match &mut *self.lock() {
            Inner::Mrf(e) => f(e).map_err(py_err),
            Inner::Online(e) => {
                Err(PyValueError::new_err(format!("{what} needs the mrf engine; this mapper runs {}", e.name())))
            }
        }
    }
}

#[pymethods]
impl Mapper {
    #[new]
    #[pyo3(signature = (resolution, fx, fy, cx, cy, width, height, engine="logodds", noise=None, max_range=None, particles=None, iterations=None, prior=None, **options))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        resolution: f64,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
        engine: &str,
        noise: Option<PathBuf>,
        max_range: Option<f64>,
        particles: Option<usize>,
        iterations: Option<usize>,
        prior: Option<f64>,
        options: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let kind: EngineKind = engine.parse().map_err(py_err)?;
        let camera = Camera::new(fx, fy, cx, cy, width, height, 1000.0).map_err(py_err)?;
        let noise = match noise {
            Some(p) => {
                let n = NoiseModel::load(&p).map_err(py_err)?;
                n.check_camera(&camera).map_err(|m| PyValueError::new_err(format!("{}: {m}", p.display())))?;
                Some(Arc::new(n))
            }
            None => None,
        };
        // The named options and the rest (`**options`) are one set of build options.
        let spec = PyDict::new(py);
        if let Some(o) = options {
            check_keys(o, OPTION_KEYS)?;
            if o.contains("keyframes")? {
                return Err(PyValueError::new_err(
                    "keyframes: a Mapper makes every frame it is given a keyframe (choose them before add_frame)",
                ));
            }
            spec.update(o.as_mapping())?;
        }
        spec.set_item("max_range", max_range)?;
        spec.set_item("prior", prior)?;
        spec.set_item("particles", particles)?;
        spec.set_item("iterations", iterations)?;
        let config = build_options(&spec)?.config(kind, resolution).map_err(py_err)?;
        let inner = if kind == EngineKind::Mrf {
            Inner::Mrf(Box::new(MrfEngine::new(resolution, config.limits, config.mrf).map_err(py_err)?))
        } else {
            Inner::Online(new_engine(&config).map_err(py_err)?)
        };
        Ok(Mapper { inner: Mutex::new(inner), config, camera, noise, frames: Mutex::new(0) })
    }

    /// Adds a depth image taken from `pose`; returns its id (the MRF keyframe id). MRF with
    /// `budget_ms` / `budget_tiles`: the online schedule runs within that budget.
    #[pyo3(signature = (depth, pose, depth_scale=None, budget_ms=None, budget_tiles=None))]
    #[allow(clippy::too_many_arguments)]
    fn add_frame(
        &self,
        py: Python<'_>,
        depth: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        depth_scale: Option<f64>,
        budget_ms: Option<f64>,
        budget_tiles: Option<usize>,
    ) -> PyResult<u64> {
        let budget =
            (budget_ms.is_some() || budget_tiles.is_some()).then_some(Budget { ms: budget_ms, tiles: budget_tiles });
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let values: Vec<f32> = if let Some((rows, cols, v)) = floats_2d(depth) {
            if depth_scale.is_some() {
                return Err(PyValueError::new_err("depth_scale is for uint16 depth; float depth is in metres"));
            }
            if (rows, cols) != (h, w) {
                return Err(PyValueError::new_err(format!("depth: shape ({rows}, {cols}) but the camera is {h}x{w}")));
            }
            // NaN and infinity mean "no measurement", as in float depth images from ROS.
            v.iter().map(|&z| if z.is_finite() && z > 0.0 { z as f32 } else { 0.0 }).collect()
        } else if let Ok(a) = depth.extract::<PyReadonlyArray2<'_, u16>>() {
            let Some(scale) = depth_scale.filter(|s| *s > 0.0 && s.is_finite()) else {
                return Err(PyValueError::new_err("uint16 depth needs depth_scale (units per metre, e.g. 1000)"));
            };
            let v = a.as_array();
            if v.dim() != (h, w) {
                return Err(PyValueError::new_err(format!("depth: shape {:?} but the camera is {h}x{w}", v.dim())));
            }
            v.iter().map(|&d| (d as f64 / scale) as f32).collect()
        } else {
            return Err(PyValueError::new_err(format!(
                "depth: need a 2-D float32/float64 (metres) or uint16 (with depth_scale) array, got {}",
                describe(depth)
            )));
        };
        let pose = pose_of(pose, "pose")?;
        let mut count = self.frames.lock().unwrap_or_else(|p| p.into_inner());
        let frame = Frame {
            index: *count,
            timestamp: *count as f64,
            depth: DepthImage::from_vec(w as u32, h as u32, values).expect("size checked"),
            pose,
            camera: self.camera,
            noise: self.noise.clone(),
        };
        let extent = frames_extent([frame.pose], std::slice::from_ref(&frame), &self.config);
        self.check_memory(extent)?;
        let id = py
            .detach(|| match (&mut *self.lock(), budget) {
                (Inner::Mrf(e), None) => e.add_keyframe(frame).map(|k| k.0),
                (Inner::Mrf(e), Some(b)) => e.add_keyframe_within(frame, b).map(|(k, _)| k.0),
                (Inner::Online(e), None) => e.integrate(&frame).map(|_| frame.index as u64),
                (Inner::Online(e), Some(_)) => Err(mrfmap::Error::Invalid(format!(
                    "budget_ms / budget_tiles are for the mrf engine's online schedule; {} integrates each frame whole",
                    e.name()
                ))),
            })
            .map_err(py_err)?;
        *count += 1;
        Ok(id)
    }

    /// Adds the posed depth images of a ROS bag (see the stub file); returns how many.
    #[pyo3(signature = (path, depth_topic, fixed_frame=None, pose_topic=None, camera_info_topic=None, max_pose_gap=0.1))]
    #[allow(clippy::too_many_arguments)]
    fn add_bag(
        &self,
        py: Python<'_>,
        path: PathBuf,
        depth_topic: String,
        fixed_frame: Option<String>,
        pose_topic: Option<String>,
        camera_info_topic: Option<String>,
        max_pose_gap: f64,
    ) -> PyResult<usize> {
        let options = BagOptions { depth_topic, camera_info_topic, fixed_frame, pose_topic, max_pose_gap };
        // The library's build loop over the bag's images, streamed: each is decoded and added
        // once its pose is known (memory holds a few images, whatever the bag's size).
        let start = *self.frames.lock().unwrap_or_else(|p| p.into_inner());
        let mut added = 0;
        let result = py.detach(|| {
            let mut inner = self.lock();
            let m = self.camera;
            stream_bag(&path, options, None, (&[], &[]), (&self.config, MapOutput::InMemory), |frames| {
                let mut frames = frames.map(|f| {
                    let (i, mut frame) = f?;
                    let c = frame.camera;
                    if (c.fx, c.fy, c.cx, c.cy, c.width, c.height) != (m.fx, m.fy, m.cx, m.cy, m.width, m.height) {
                        return Err(mrfmap::Error::file(
                            &path,
                            format!(
                                "the bag's camera (fx {}, fy {}, cx {}, cy {}, {}x{}) is not this mapper's",
                                c.fx, c.fy, c.cx, c.cy, c.width, c.height
                            ),
                        ));
                    }
                    frame.index = start + added;
                    frame.noise = self.noise.clone();
                    added += 1;
                    Ok((i, frame))
                });
                integrate(inner.engine_mut(), &mut frames, None, &mut (), None)
            })
        });
        // Frames added before an error still count.
        *self.frames.lock().unwrap_or_else(|p| p.into_inner()) = start + added;
        result.map_err(py_err)?;
        Ok(added)
    }

    /// Adds a range scan: beam directions (N, 3) in the sensor frame, ranges (N,) in metres
    /// (NaN, infinity or <= 0: no return, free up to `max_range`), sensor pose 4x4.
    fn add_scan(
        &self,
        py: Python<'_>,
        pose: &Bound<'_, PyAny>,
        directions: &Bound<'_, PyAny>,
        ranges: &Bound<'_, PyAny>,
        max_range: f64,
    ) -> PyResult<u64> {
        let pose = pose_of(pose, "pose")?;
        let Some((n, 3, dirs)) = floats_2d(directions) else {
            return Err(PyValueError::new_err(format!(
                "directions: need an (N, 3) float64 or float32 array, got {}",
                describe(directions)
            )));
        };
        let ranges: Vec<f64> = if let Ok(a) = ranges.extract::<PyReadonlyArray1<'_, f64>>() {
            a.as_array().to_vec()
        } else if let Ok(a) = ranges.extract::<PyReadonlyArray1<'_, f32>>() {
            a.as_array().iter().map(|r| *r as f64).collect()
        } else {
            return Err(PyValueError::new_err(format!(
                "ranges: need a 1-D float64 or float32 array, got {}",
                describe(ranges)
            )));
        };
        if ranges.len() != n {
            return Err(PyValueError::new_err(format!("ranges: {} values for {n} directions", ranges.len())));
        }
        let beams = (0..n)
            .map(|k| Beam {
                dir: [dirs[3 * k], dirs[3 * k + 1], dirs[3 * k + 2]],
                range: (ranges[k].is_finite() && ranges[k] > 0.0).then_some(ranges[k]),
            })
            .collect();
        // A camera's per-patch model means nothing for a scan; an aggregate one is in range.
        let noise = self.noise.clone().filter(|n| n.patches.is_none());
        let mut count = self.frames.lock().unwrap_or_else(|p| p.into_inner());
        let scan = RangeScan::new(*count, pose, beams, max_range, noise).map_err(py_err)?;
        self.check_memory(scan_extent(std::slice::from_ref(&scan), &self.config))?;
        py.detach(|| self.lock().engine_mut().integrate_scan(&scan)).map_err(py_err)?;
        *count += 1;
        Ok(scan.index as u64)
    }

    /// MRF: removes a keyframe (as if it had never been added, once re-run).
    fn remove_keyframe(&self, id: u64) -> PyResult<()> {
        self.mrf_only("remove_keyframe", |e| e.remove_keyframe(KeyframeId(id)))
    }

    /// MRF: moves a keyframe to a corrected pose.
    fn set_pose(&self, id: u64, pose: &Bound<'_, PyAny>) -> PyResult<()> {
        let pose = pose_of(pose, "pose")?;
        self.mrf_only("set_pose", |e| e.set_pose(KeyframeId(id), pose))
    }

    /// MRF: belief propagation, the constructor's `iterations` full sweeps (default 3) or
    /// `iterations` full sweeps; the online engines have nothing to run.
    #[pyo3(signature = (iterations=None))]
    fn run(&self, py: Python<'_>, iterations: Option<usize>) -> PyResult<()> {
        py.detach(|| {
            if let Inner::Mrf(e) = &mut *self.lock() {
                match iterations {
                    Some(n) => {
                        e.run(n);
                    }
                    None => e.finish().map_err(py_err)?,
                }
            }
            Ok(())
        })
    }

    /// MRF: belief propagation until no marginal moves by more than `tolerance`, re-tracing
    /// only the tiles whose inputs changed; returns (sweeps, keyframe updates, rays, converged).
    #[pyo3(signature = (tolerance=mrfmap::inference::DEFAULT_TOLERANCE, max_sweeps=100))]
    fn run_until(&self, py: Python<'_>, tolerance: f64, max_sweeps: usize) -> PyResult<(usize, usize, usize, bool)> {
        if !(tolerance > 0.0 && tolerance < 1.0) {
            return Err(PyValueError::new_err(format!("tolerance must be in (0, 1), got {tolerance}")));
        }
        py.detach(|| {
            self.mrf_only("run_until", |e| {
                let r = e.run_until(tolerance, max_sweeps);
                Ok((r.sweeps, r.keyframe_updates, r.rays, r.converged))
            })
        })
    }

    /// MRF: spends idle time on the online schedule's backlog (tiles never traced first);
    /// no budget runs until settled. Returns what it did as a dict.
    #[pyo3(signature = (ms=None, tiles=None))]
    fn refine<'py>(&self, py: Python<'py>, ms: Option<f64>, tiles: Option<usize>) -> PyResult<Bound<'py, PyDict>> {
        let r = py.detach(|| self.mrf_only("refine", |e| e.refine(Budget { ms, tiles })))?;
        let d = PyDict::new(py);
        d.set_item("tiles", r.tiles)?;
        d.set_item("own_tiles", r.own_tiles)?;
        d.set_item("rays", r.rays)?;
        d.set_item("backlog", r.backlog)?;
        d.set_item("settled", r.settled)?;
        d.set_item("ms", r.elapsed.as_secs_f64() * 1e3)?;
        Ok(d)
    }

    /// MRF: tiles waiting in the online schedule's backlog (0 for the other engines).
    #[getter]
    fn backlog(&self) -> usize {
        match &*self.lock() {
            Inner::Mrf(e) => e.backlog(),
            Inner::Online(_) => 0,
        }
    }

    /// The current map.
    fn map(&self, py: Python<'_>) -> PyMap {
        PyMap { map: py.detach(|| self.lock().engine().map()) }
    }

    /// Saves the current map straight from the live engine (a log-odds map a brick at a
    /// time, never copied whole); returns the number of occupied voxels.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<usize> {
        let saved = py.detach(|| self.lock().engine().save_map(&path, &Default::default())).map_err(py_err)?;
        Ok(saved.occupied)
    }

    /// Occupancy and variance at points, read from the live engine.
    fn query<'py>(&self, py: Python<'py>, points: &Bound<'py, PyAny>) -> Queried<'py> {
        occupancy_variance(py, &LiveEngine(self.lock().engine()), points)
    }

    /// `Map.query_points` on the live engine (no copy of the map).
    #[pyo3(signature = (points, unknown=0.5))]
    fn query_points<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        unknown: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_points(py, &LiveEngine(self.lock().engine()), points, unknown)
    }

    /// `Map.query_segments` on the live engine (no copy of the map).
    #[pyo3(signature = (starts, ends, unknown=0.5, k=2.0, threshold=0.5))]
    fn query_segments<'py>(
        &self,
        py: Python<'py>,
        starts: &Bound<'py, PyAny>,
        ends: &Bound<'py, PyAny>,
        unknown: f64,
        k: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_segments(py, &LiveEngine(self.lock().engine()), starts, ends, QueryOptions { unknown, k, threshold })
    }

    /// `Map.query_polyline` on the live engine (no copy of the map).
    #[pyo3(signature = (points, unknown=0.5, k=2.0, threshold=0.5))]
    fn query_polyline<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        unknown: f64,
        k: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_polyline(py, &LiveEngine(self.lock().engine()), points, QueryOptions { unknown, k, threshold })
    }

    /// `Map.query_boxes` on the live engine (no copy of the map).
    #[pyo3(signature = (mins, maxs, unknown=0.5, threshold=0.5))]
    fn query_boxes<'py>(
        &self,
        py: Python<'py>,
        mins: &Bound<'py, PyAny>,
        maxs: &Bound<'py, PyAny>,
        unknown: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let opts = QueryOptions { unknown, threshold, ..Default::default() };
        answer_boxes(py, &LiveEngine(self.lock().engine()), mins, maxs, opts)
    }

    /// The engine's name.
    #[getter]
    fn engine(&self) -> &'static str {
        self.lock().engine().name()
    }

    /// Voxel edge in metres.
    #[getter]
    fn resolution(&self) -> f64 {
        self.lock().engine().resolution()
    }

    fn __repr__(&self) -> String {
        let n = *self.frames.lock().unwrap_or_else(|p| p.into_inner());
        format!("Mapper(engine={:?}, resolution={}, frames={n})", self.engine(), self.resolution())
    }
}

/// A finished map (see the stub file for the Python documentation).
#[pyclass(name = "Map", module = "mrfmap")]
struct PyMap {
    map: Map,
}

#[pymethods]
impl PyMap {
    /// Occupancy and variance at each point; NaN where the map knows nothing.
    fn query<'py>(&self, py: Python<'py>, points: &Bound<'py, PyAny>) -> Queried<'py> {
        occupancy_variance(py, &self.map, points)
    }

    /// Occupancy, standard deviation and known per point.
    #[pyo3(signature = (points, unknown=0.5))]
    fn query_points<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        unknown: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_points(py, &self.map, points, unknown)
    }

    /// Free-path probabilities and more per segment.
    #[pyo3(signature = (starts, ends, unknown=0.5, k=2.0, threshold=0.5))]
    fn query_segments<'py>(
        &self,
        py: Python<'py>,
        starts: &Bound<'py, PyAny>,
        ends: &Bound<'py, PyAny>,
        unknown: f64,
        k: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_segments(py, &self.map, starts, ends, QueryOptions { unknown, k, threshold })
    }

    /// Max occupancy, free probability and counts per box.
    #[pyo3(signature = (mins, maxs, unknown=0.5, threshold=0.5))]
    fn query_boxes<'py>(
        &self,
        py: Python<'py>,
        mins: &Bound<'py, PyAny>,
        maxs: &Bound<'py, PyAny>,
        unknown: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_boxes(py, &self.map, mins, maxs, QueryOptions { unknown, threshold, ..Default::default() })
    }

    /// One path through (K, 3) waypoints, each voxel counted once.
    #[pyo3(signature = (points, unknown=0.5, k=2.0, threshold=0.5))]
    fn query_polyline<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        unknown: f64,
        k: f64,
        threshold: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        answer_polyline(py, &self.map, points, QueryOptions { unknown, k, threshold })
    }

    /// All voxels: centres (N, 3), occupancy (N,) and variance (N,).
    #[allow(clippy::type_complexity)]
    fn voxels<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f32>>, Bound<'py, PyArray1<f32>>)> {
        let r = self.map.resolution();
        let n = self.map.voxels.len();
        let (mut centres, mut occ, mut var) = (Vec::with_capacity(3 * n), Vec::with_capacity(n), Vec::with_capacity(n));
        for (key, v) in self.map.voxels.iter() {
            centres.extend_from_slice(&key.center(r));
            let (_, sigma) = mrfmap::outputs::mean_sigma(&self.map, v);
            occ.push(v.occupancy);
            var.push((sigma * sigma) as f32);
        }
        let centres = PyArray1::from_vec(py, centres).reshape([n, 3])?;
        Ok((centres, PyArray1::from_vec(py, occ), PyArray1::from_vec(py, var)))
    }

    /// Saves in mrfmap's map format.
    fn save(&self, path: PathBuf) -> PyResult<()> {
        self.map.save(&path).map_err(py_err)
    }

    /// Writes a binary PLY of voxel centres with occupancy (and variance).
    #[pyo3(signature = (path, occupied_only=false))]
    fn export_ply(&self, path: PathBuf, occupied_only: bool) -> PyResult<usize> {
        let options = if occupied_only { PlyOptions::occupied_only() } else { PlyOptions { min_occupancy: None } };
        write_ply(&self.map, &path, options).map_err(py_err)
    }

    /// Writes an OctoMap `.bt` file.
    fn export_bt(&self, path: PathBuf) -> PyResult<()> {
        write_octomap(&self.map, &path, OctomapFormat::Binary).map(|_| ()).map_err(py_err)
    }

    /// Writes an OctoMap `.ot` file.
    fn export_ot(&self, path: PathBuf) -> PyResult<()> {
        write_octomap(&self.map, &path, OctomapFormat::Full).map(|_| ()).map_err(py_err)
    }

    /// Voxel edge in metres.
    #[getter]
    fn resolution(&self) -> f64 {
        self.map.resolution()
    }

    /// The engine that built the map.
    #[getter]
    fn engine(&self) -> &'static str {
        self.map.engine.name()
    }

    /// Voxels with occupancy above 0.5.
    #[getter]
    fn occupied_count(&self) -> usize {
        self.map.occupied_count()
    }

    fn __len__(&self) -> usize {
        self.map.voxels.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "Map(engine={:?}, resolution={}, voxels={}, occupied={})",
            self.map.engine,
            self.map.resolution(),
            self.map.voxels.len(),
            self.map.occupied_count()
        )
    }
}

/// The legacy `query`: occupancy and variance, NaN where unknown.
fn occupancy_variance<'py>(py: Python<'py>, source: &impl VoxelSource, points: &Bound<'py, PyAny>) -> Queried<'py> {
    let pts = points_of(points, "points")?;
    let answers = py.detach(|| query_points(source, &pts, &QueryOptions::default()));
    let known = |a: &PointAnswer, v: f64| if a.known { v } else { f64::NAN };
    let occ = answers.iter().map(|a| known(a, a.occupancy)).collect();
    let var = answers.iter().map(|a| known(a, a.sigma * a.sigma)).collect();
    Ok((PyArray1::from_vec(py, occ), PyArray1::from_vec(py, var)))
}

fn checked(options: QueryOptions) -> PyResult<QueryOptions> {
    options.validate().map_err(py_err)?;
    Ok(options)
}

fn answer_points<'py>(
    py: Python<'py>,
    source: &impl VoxelSource,
    points: &Bound<'py, PyAny>,
    unknown: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let options = checked(QueryOptions { unknown, ..Default::default() })?;
    let pts = points_of(points, "points")?;
    let answers = py.detach(|| query_points(source, &pts, &options));
    let out = PyDict::new(py);
    out.set_item("occupancy", PyArray1::from_iter(py, answers.iter().map(|a| a.occupancy)))?;
    out.set_item("std", PyArray1::from_iter(py, answers.iter().map(|a| a.sigma)))?;
    out.set_item("known", PyArray1::from_iter(py, answers.iter().map(|a| a.known)))?;
    Ok(out)
}

/// Pairs of (N, 3) arrays of one length.
fn pairs_of(a: &Bound<'_, PyAny>, b: &Bound<'_, PyAny>, names: [&str; 2]) -> PyResult<Vec<([f64; 3], [f64; 3])>> {
    let (a, b) = (points_of(a, names[0])?, points_of(b, names[1])?);
    if a.len() != b.len() {
        return Err(PyValueError::new_err(format!(
            "{} and {} need the same number of rows, got {} and {}",
            names[0],
            names[1],
            a.len(),
            b.len()
        )));
    }
    Ok(a.into_iter().zip(b).collect())
}

fn answer_segments<'py>(
    py: Python<'py>,
    source: &impl VoxelSource,
    starts: &Bound<'py, PyAny>,
    ends: &Bound<'py, PyAny>,
    options: QueryOptions,
) -> PyResult<Bound<'py, PyDict>> {
    let options = checked(options)?;
    let segs = pairs_of(starts, ends, ["starts", "ends"])?;
    for (i, (a, b)) in segs.iter().enumerate() {
        check_path(&[*a, *b], source.resolution()).map_err(|e| PyValueError::new_err(format!("segment {i}: {e}")))?;
    }
    let answers = py.detach(|| query_segments(source, &segs, &options));
    let out = PyDict::new(py);
    out.set_item("p_free", PyArray1::from_iter(py, answers.iter().map(|a| a.p_free)))?;
    out.set_item("expected_occupied", PyArray1::from_iter(py, answers.iter().map(|a| a.expected_occupied)))?;
    out.set_item("p_free_lcb", PyArray1::from_iter(py, answers.iter().map(|a| a.p_free_lcb)))?;
    let hits: Vec<f64> = answers.iter().flat_map(|a| a.first_hit.unwrap_or([f64::NAN; 3])).collect();
    out.set_item("first_hit", PyArray1::from_vec(py, hits).reshape([answers.len(), 3])?)?;
    out.set_item("voxels", PyArray1::from_iter(py, answers.iter().map(|a| a.voxels)))?;
    out.set_item("unknown", PyArray1::from_iter(py, answers.iter().map(|a| a.unknown)))?;
    Ok(out)
}

fn answer_polyline<'py>(
    py: Python<'py>,
    source: &impl VoxelSource,
    points: &Bound<'py, PyAny>,
    options: QueryOptions,
) -> PyResult<Bound<'py, PyDict>> {
    let options = checked(options)?;
    let pts = points_of(points, "points")?;
    check_path(&pts, source.resolution()).map_err(|e| PyValueError::new_err(e.to_string()))?;
    let a = py.detach(|| query_polyline(source, &pts, &options));
    let out = PyDict::new(py);
    out.set_item("p_free", a.p_free)?;
    out.set_item("expected_occupied", a.expected_occupied)?;
    out.set_item("p_free_lcb", a.p_free_lcb)?;
    out.set_item("first_hit", a.first_hit.map(|h| h.to_vec()))?;
    out.set_item("voxels", a.voxels)?;
    out.set_item("unknown", a.unknown)?;
    Ok(out)
}

fn answer_boxes<'py>(
    py: Python<'py>,
    source: &impl VoxelSource,
    mins: &Bound<'py, PyAny>,
    maxs: &Bound<'py, PyAny>,
    options: QueryOptions,
) -> PyResult<Bound<'py, PyDict>> {
    let options = checked(options)?;
    let boxes = pairs_of(mins, maxs, ["mins", "maxs"])?
        .into_iter()
        .map(|(lo, hi)| Aabb::new(lo, hi))
        .collect::<mrfmap::Result<Vec<_>>>()
        .map_err(py_err)?;
    let answers = py
        .detach(|| boxes.iter().map(|b| query_box(source, b, &options)).collect::<mrfmap::Result<Vec<_>>>())
        .map_err(py_err)?;
    let out = PyDict::new(py);
    out.set_item("max_occupancy", PyArray1::from_iter(py, answers.iter().map(|a| a.max_occupancy)))?;
    out.set_item("p_free", PyArray1::from_iter(py, answers.iter().map(|a| a.p_free)))?;
    out.set_item("occupied", PyArray1::from_iter(py, answers.iter().map(|a| a.occupied)))?;
    out.set_item("free", PyArray1::from_iter(py, answers.iter().map(|a| a.free)))?;
    out.set_item("unknown", PyArray1::from_iter(py, answers.iter().map(|a| a.unknown)))?;
    Ok(out)
}

/// Loads a map file written by `mrfmap build` or `Map.save`.
#[pyfunction]
fn load_map(path: PathBuf) -> PyResult<PyMap> {
    Ok(PyMap { map: Map::load(&path).map_err(py_err)? })
}

/// Renders a scene file into a dataset folder (as `mrfmap simulate`); returns the frames.
#[pyfunction]
#[pyo3(signature = (scene, out_dir, seed=0))]
fn simulate(py: Python<'_>, scene: PathBuf, out_dir: PathBuf, seed: u64) -> PyResult<usize> {
    py.detach(|| {
        let scene = mrfmap::source::Scene::load(&scene)?;
        mrfmap::source::simulate(&scene, &out_dir, seed).map(|s| s.frames)
    })
    .map_err(py_err)
}

/// The keyword arguments that fill a [`BuildOptions`]: `mrfmap build`'s options by the same names.
const OPTION_KEYS: &[&str] = &[
    "max_range",
    "bounds",
    "iterations",
    "tolerance",
    "work",
    "prior",
    "allocation",
    "keyframes",
    "damping",
    "ray_spacing",
    "min_evidence",
    "particles",
    "marking",
    "clamp",
];

/// Refuses a key of `spec` that is not in `known`, listing those that are.
fn check_keys(spec: &Bound<'_, PyDict>, known: &[&str]) -> PyResult<()> {
    for key in spec.keys() {
        let key: String = key.extract()?;
        if !known.contains(&key.as_str()) {
            return Err(PyValueError::new_err(format!("unknown option {key:?} (known: {})", known.join(", "))));
        }
    }
    Ok(())
}

/// `spec[key]` as a `T`; `None` when absent or None.
fn get<'py, T: FromPyObjectOwned<'py>>(spec: &Bound<'py, PyDict>, key: &str) -> PyResult<Option<T>> {
    match spec.get_item(key)? {
        Some(v) if !v.is_none() => {
            v.extract::<T>().map(Some).map_err(|e| PyValueError::new_err(format!("{key}: {}", Into::<PyErr>::into(e))))
        }
        _ => Ok(None),
    }
}

/// The [`BuildOptions`] of `spec`'s [`OPTION_KEYS`] (its other keys are the caller's), with the
/// defaults for the keys it does not hold or holds as None.
fn build_options(spec: &Bound<'_, PyDict>) -> PyResult<BuildOptions> {
    fn named<T: Choice>(spec: &Bound<'_, PyDict>, key: &str) -> PyResult<Option<T>> {
        get::<String>(spec, key)?.map(|s| T::parse(&s).map_err(py_err)).transpose()
    }
    let bounds = get::<Vec<f64>>(spec, "bounds")?
        .map(|b| match b.as_slice() {
            [a, b, c, d, e, f] => Aabb::new([*a, *b, *c], [*d, *e, *f]).map_err(py_err),
            _ => Err(PyValueError::new_err("bounds: need [xmin, ymin, zmin, xmax, ymax, zmax]")),
        })
        .transpose()?;
    let d = BuildOptions::default();
    Ok(BuildOptions {
        max_range: get(spec, "max_range")?,
        bounds,
        iterations: get(spec, "iterations")?,
        tolerance: get(spec, "tolerance")?,
        work: get(spec, "work")?,
        prior: get(spec, "prior")?.unwrap_or(d.prior),
        allocation: named(spec, "allocation")?.unwrap_or(d.allocation),
        keyframes: named(spec, "keyframes")?.unwrap_or(d.keyframes),
        damping: get(spec, "damping")?.unwrap_or(d.damping),
        ray_spacing: get(spec, "ray_spacing")?.unwrap_or(d.ray_spacing),
        min_evidence: get(spec, "min_evidence")?.unwrap_or(d.min_evidence),
        particles: get(spec, "particles")?.unwrap_or(d.particles),
        marking: named(spec, "marking")?.unwrap_or(d.marking),
        clamp: get(spec, "clamp")?,
    })
}

/// How a dataset is built into a map, whole or in tiles: the keyword arguments of
/// `build_dataset` and `mrfmap.distributed.build` (the stub file documents them).
struct BuildSpec {
    dataset: mrfmap::source::Dataset,
    config: EngineConfig,
    /// Tile edge, height and margin, for tiled builds.
    tile: Option<(f64, Option<f64>, Option<f64>)>,
    /// Worker threads (None: all cores).
    threads: Option<usize>,
}

impl BuildSpec {
    /// Keys beside [`OPTION_KEYS`].
    const KEYS: &[&str] = &["resolution", "engine", "tile", "tile_height", "margin", "noise", "threads"];

    fn of(dataset: &std::path::Path, spec: &Bound<'_, PyDict>) -> PyResult<Self> {
        check_keys(spec, &[Self::KEYS, OPTION_KEYS].concat())?;
        let resolution: f64 =
            get(spec, "resolution")?.ok_or_else(|| PyValueError::new_err("resolution is required"))?;
        let kind: EngineKind =
            get::<String>(spec, "engine")?.as_deref().unwrap_or("logodds").parse().map_err(py_err)?;
        let mut dataset = mrfmap::source::Dataset::open(dataset).map_err(py_err)?;
        if let Some(noise) = get::<PathBuf>(spec, "noise")? {
            dataset.set_noise_file(&noise).map_err(py_err)?;
        }
        let config = build_options(spec)?.config(kind, resolution).map_err(py_err)?;
        let tile = get::<f64>(spec, "tile")?
            .map(|t| Ok::<_, PyErr>((t, get(spec, "tile_height")?, get(spec, "margin")?)))
            .transpose()?;
        Ok(BuildSpec { dataset, config, tile, threads: get(spec, "threads")? })
    }

    fn tiling(&self) -> PyResult<mrfmap::inference::Tiling> {
        let (edge, height, margin) =
            self.tile.ok_or_else(|| PyValueError::new_err("tile (the tile edge in metres) is required"))?;
        mrfmap::inference::Tiling::new(&self.config, edge, height, margin).map_err(py_err)
    }

    /// Runs `work` on `threads` threads (all cores without), without the GIL.
    fn run<T: Send>(&self, py: Python<'_>, work: impl FnOnce() -> mrfmap::Result<T> + Send) -> PyResult<T> {
        py.detach(|| match self.threads {
            Some(n) => rayon::ThreadPoolBuilder::new()
                .num_threads(n.max(1))
                .start_handler(|_| mrfmap::placement::register_thread())
                .build()
                .map_err(|e| mrfmap::Error::Invalid(format!("threads: {e}")))?
                .install(work),
            None => work(),
        })
        .map_err(py_err)
    }

    /// Refuses frame indices the dataset does not have.
    fn check_frames(&self, indices: &[usize]) -> PyResult<()> {
        check_indices(self.dataset.len(), indices).map_err(py_err)
    }

    fn frames(&self, indices: Vec<usize>) -> impl Iterator<Item = mrfmap::Result<Frame>> + '_ {
        indices.into_iter().map(|i| self.dataset.frame(i))
    }
}

/// Builds a dataset folder's frames into one map (see the stub file).
#[pyfunction]
#[pyo3(signature = (dataset, **options))]
fn build_dataset(py: Python<'_>, dataset: PathBuf, options: Option<&Bound<'_, PyDict>>) -> PyResult<PyMap> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    if spec.tile.is_some() {
        return Err(PyValueError::new_err("build_dataset builds one map; tiled builds: mrfmap.distributed.build"));
    }
    let report = spec.run(py, || {
        let all: Vec<usize> = (0..spec.dataset.len()).collect();
        // Refused before any work, as `mrfmap build` refuses (MemoryError).
        let advice = "use a coarser resolution, or map less with bounds or max_range";
        check_build(&spec.config, dataset_extent(&spec.dataset, &all, &spec.config)?, MapOutput::InMemory, advice)?;
        // (The dataset's camera is known before its first frame: the engine is readied for it.)
        let config = EngineConfig { camera: Some(*spec.dataset.camera()), ..spec.config };
        read_ahead(&all, |i| spec.dataset.frame(i), |frames| build(&config, frames, Some(all.len()), &mut (), None))
    })?;
    Ok(PyMap { map: report.map })
}

/// A tile's key as Python sees it.
type TileKeyTuple = (i32, i32, i32);

/// Which of `frames` (default: all) reach which tile: `[((x, y, z), [frame, ...]), ...]`, reading
/// each frame once.
#[pyfunction]
#[pyo3(signature = (dataset, frames=None, **options))]
fn _plan_tiles(
    py: Python<'_>,
    dataset: PathBuf,
    frames: Option<Vec<usize>>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<Vec<(TileKeyTuple, Vec<usize>)>> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    let tiling = spec.tiling()?;
    let indices = frames.unwrap_or_else(|| (0..spec.dataset.len()).collect());
    spec.check_frames(&indices)?;
    let plan = spec.run(py, || tiling.plan(&spec.config, &indices, |i| spec.dataset.frame(i)))?;
    Ok(plan.into_iter().map(|(k, f)| ((k.0[0], k.0[1], k.0[2]), f)).collect())
}

/// How many frames the dataset folder holds (its poses; no image is read), once the tiled
/// build's options are checked: what a distributed build asks before it starts a cluster.
#[pyfunction]
#[pyo3(signature = (dataset, **options))]
fn _frame_count(py: Python<'_>, dataset: PathBuf, options: Option<&Bound<'_, PyDict>>) -> PyResult<usize> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    spec.tiling()?;
    Ok(spec.dataset.len())
}

/// The memory (bytes) building tile `key` from `frames` adds to a running process: its
/// estimate without the program's own base.
#[pyfunction]
#[pyo3(signature = (dataset, key, frames, **options))]
fn _tile_estimate(
    py: Python<'_>,
    dataset: PathBuf,
    key: (i32, i32, i32),
    frames: Vec<usize>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<f64> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    let tiling = spec.tiling()?;
    let key = mrfmap::map::TileKey([key.0, key.1, key.2]);
    spec.check_frames(&frames)?;
    let pose = |i: usize| spec.dataset.frames()[i].pose;
    let estimate = spec.run(py, || tiling.estimate(&spec.config, key, &frames, pose, |i| spec.dataset.frame(i)))?;
    // What the build adds to a running process: the estimate without its program base.
    Ok((estimate - mrfmap::inference::BASE_MEMORY).max(0.0))
}

/// Builds tile `key` from `frames` into the folder `out_dir`; returns its index entry (a dict)
/// and the tile map's parameters.
#[pyfunction]
#[pyo3(signature = (dataset, out_dir, key, frames, **options))]
fn _build_tile<'py>(
    py: Python<'py>,
    dataset: PathBuf,
    out_dir: PathBuf,
    key: (i32, i32, i32),
    frames: Vec<usize>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    let tiling = spec.tiling()?;
    let key = mrfmap::map::TileKey([key.0, key.1, key.2]);
    spec.check_frames(&frames)?;
    let (entry, params) = spec.run(py, || tiling.build_into(&out_dir, &spec.config, key, spec.frames(frames)))?;
    let out = PyDict::new(py);
    out.set_item("key", entry.key.to_vec())?;
    out.set_item("file", entry.file)?;
    out.set_item("voxels", entry.voxels)?;
    out.set_item("occupied", entry.occupied)?;
    out.set_item("bricks", entry.bricks)?;
    out.set_item("memory_bytes", entry.memory_bytes)?;
    out.set_item("frames", entry.frames)?;
    out.set_item("bounds", entry.bounds.map(|b| b.to_vec()))?;
    out.set_item("params", params)?;
    Ok(out)
}

/// Writes the index of a tiled map into `out_dir` from the entries `_build_tile` returned
/// (the last step of a tiled build: it makes the folder a map).
#[pyfunction]
#[pyo3(signature = (dataset, out_dir, entries, **options))]
fn _write_tile_index(
    py: Python<'_>,
    dataset: PathBuf,
    out_dir: PathBuf,
    entries: Vec<Bound<'_, PyDict>>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<usize> {
    let spec = BuildSpec::of(&dataset, &options.cloned().unwrap_or_else(|| PyDict::new(py)))?;
    let tiling = spec.tiling()?;
    let mut params: std::collections::BTreeMap<String, String> = match entries.first() {
        Some(e) => e.get_item("params")?.map(|p| p.extract()).transpose()?.unwrap_or_default(),
        None => Default::default(),
    };
    params.insert("source".into(), dataset.display().to_string());
    let mut index = tiling.index(&spec.config, params);
    for e in &entries {
        let field = |k: &str| -> PyResult<Bound<'_, PyAny>> {
            e.get_item(k)?.ok_or_else(|| PyValueError::new_err(format!("tile entry without {k:?}")))
        };
        let key: Vec<i32> = field("key")?.extract()?;
        let bounds: Option<Vec<Vec<f64>>> = field("bounds")?.extract()?;
        index.tiles.push(mrfmap::map::TileEntry {
            key: key.try_into().map_err(|_| PyValueError::new_err("tile key: need three integers"))?,
            file: field("file")?.extract()?,
            voxels: field("voxels")?.extract()?,
            occupied: field("occupied")?.extract()?,
            bricks: field("bricks")?.extract()?,
            memory_bytes: field("memory_bytes")?.extract()?,
            frames: field("frames")?.extract()?,
            bounds: bounds
                .map(|b| match b.as_slice() {
                    [lo, hi] if lo.len() == 3 && hi.len() == 3 => Ok([[lo[0], lo[1], lo[2]], [hi[0], hi[1], hi[2]]]),
                    _ => Err(PyValueError::new_err("tile bounds: need [[x, y, z], [x, y, z]]")),
                })
                .transpose()?,
        });
    }
    index.save(&out_dir).map_err(py_err)?;
    Ok(index.tiles.len())
}

#[pymodule]
fn _mrfmap(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Mapper>()?;
    m.add_class::<PyMap>()?;
    m.add_function(wrap_pyfunction!(load_map, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add_function(wrap_pyfunction!(build_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(_frame_count, m)?)?;
    m.add_function(wrap_pyfunction!(_plan_tiles, m)?)?;
    m.add_function(wrap_pyfunction!(_tile_estimate, m)?)?;
    m.add_function(wrap_pyfunction!(_build_tile, m)?)?;
    m.add_function(wrap_pyfunction!(_write_tile_index, m)?)?;
    Ok(())
}
