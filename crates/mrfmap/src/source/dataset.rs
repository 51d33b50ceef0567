//! Datasets in the TUM RGB-D / ICL-NUIM layout (docs/ALGORITHMS.md section 2).
//!
//! ```text
//! DATASET/depth/*.png  depth.txt  groundtruth.txt  camera.toml  [noise.toml]  [world.toml]  [gt_depth/*.png]
//! ```
//! Opening a dataset reads the text files and associates depth frames with poses; depth
//! images are read on demand by [`Dataset::frame`], so large sequences stream.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::{Error, Result, read_text};
use crate::frames::{Camera, DepthImage, Frame, NoiseModel, Pose, Up, moved_beyond, pose_from_tum};
use crate::source::depth_png::read_depth_png;

/// How a dataset is opened.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DatasetOptions {
    /// Largest time difference (s) between a depth frame and its pose (TUM's associate rule).
    pub max_time_diff: f64,
}

impl Default for DatasetOptions {
    fn default() -> Self {
        DatasetOptions { max_time_diff: 0.02 }
    }
}

/// One depth frame matched to a pose.
#[derive(Clone, Debug)]
pub struct FrameInfo {
    /// Depth timestamp (s).
    pub timestamp: f64,
    /// Depth image path, relative to the dataset root (as in `depth.txt`).
    pub depth: PathBuf,
    /// Camera-to-world pose.
    pub pose: Pose,
}

/// An opened dataset.
///
/// ```no_run
/// let ds = mrfmap::source::Dataset::open("../shared/data/icl-livingroom-5".as_ref()).unwrap();
/// let frame = ds.frame(0).unwrap();
/// println!("{} frames, first has {} valid pixels", ds.len(), frame.depth.valid_count());
/// ```
#[derive(Clone, Debug)]
pub struct Dataset {
    root: PathBuf,
    camera: Camera,
    noise: Option<Arc<NoiseModel>>,
    up: Option<Up>,
    frames: Vec<FrameInfo>,
    unmatched: Vec<PathBuf>,
}

impl Dataset {
    /// Opens `root` with default options.
    pub fn open(root: &Path) -> Result<Self> {
        Self::open_with(root, DatasetOptions::default())
    }

    /// Opens `root`: reads `camera.toml`, `noise.toml` if present, `depth.txt` and
    /// `groundtruth.txt`, and associates frames with poses.
    pub fn open_with(root: &Path, options: DatasetOptions) -> Result<Self> {
        if !root.is_dir() {
            return Err(Error::file(root, "dataset folder not found"));
        }
        let camera_path = root.join("camera.toml");
        if !camera_path.exists() {
            return Err(Error::file(
                &camera_path,
                "missing: a dataset needs camera.toml with fx, fy, cx, cy, width, height, depth_scale",
            ));
        }
        let camera = Camera::load(&camera_path)?;
        let noise_path = root.join("noise.toml");
        let noise = if noise_path.exists() { Some(Arc::new(load_noise_for(&noise_path, &camera)?)) } else { None };
        let world_path = root.join("world.toml");
        let up = if world_path.exists() { Some(load_up(&world_path)?) } else { None };

        let depth_list = root.join("depth.txt");
        let depths = parse_depth_list(&depth_list)?;
        if depths.is_empty() {
            return Err(Error::file(&depth_list, "empty dataset: no depth frames listed"));
        }
        for (t, p, line) in &depths {
            if !root.join(p).is_file() {
                return Err(Error::file(
                    &depth_list,
                    format!("line {line}: frame at t = {t} names {}, which does not exist", p.display()),
                ));
            }
        }
        let poses = parse_groundtruth(&root.join("groundtruth.txt"))?;
        let pairs = associate(
            &depths.iter().map(|d| d.0).collect::<Vec<_>>(),
            &poses.iter().map(|p| p.0).collect::<Vec<_>>(),
            options.max_time_diff,
        );
        let mut frames = Vec::new();
        let mut unmatched = Vec::new();
        for (i, (t, path, _)) in depths.into_iter().enumerate() {
            match pairs[i] {
                Some(j) => frames.push(FrameInfo { timestamp: t, depth: path, pose: poses[j].1 }),
                None => unmatched.push((t, path)),
            }
        }
        // One line for all of them: a real TUM sequence has hundreds.
        if let (Some((t0, first)), Some((t1, _))) = (unmatched.first(), unmatched.last()) {
            tracing::warn!(
                "{}: {} depth frame(s) have no pose within {} s and are skipped (first {}, t = {t0} .. {t1})",
                root.join("groundtruth.txt").display(),
                unmatched.len(),
                options.max_time_diff,
                first.display()
            );
        }
        let unmatched: Vec<PathBuf> = unmatched.into_iter().map(|(_, p)| p).collect();
        if frames.is_empty() {
            return Err(Error::file(
                root.join("groundtruth.txt"),
                format!("no depth frame matched a pose within {} s", options.max_time_diff),
            ));
        }
        Ok(Dataset { root: root.to_path_buf(), camera, noise, up, frames, unmatched })
    }

    /// The world's up axis, when `world.toml` declares it (`up = "+y"`).
    pub fn up(&self) -> Option<Up> {
        self.up
    }

    /// Dataset folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Camera intrinsics.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The dataset's noise model (from `noise.toml`, or set with [`Dataset::set_noise_file`]).
    pub fn noise(&self) -> Option<&Arc<NoiseModel>> {
        self.noise.as_ref()
    }

    /// Replaces the noise model (e.g. `--noise FILE`); checks it fits the camera.
    pub fn set_noise_file(&mut self, path: &Path) -> Result<()> {
        self.noise = Some(Arc::new(load_noise_for(path, &self.camera)?));
        Ok(())
    }

    /// Associated frames, in depth-timestamp order.
    pub fn frames(&self) -> &[FrameInfo] {
        &self.frames
    }

    /// Number of associated frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True if there are no frames (never, for an opened dataset).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Depth files listed in `depth.txt` that matched no pose.
    pub fn unmatched(&self) -> &[PathBuf] {
        &self.unmatched
    }

    /// Loads frame `index` (its noisy `depth/` image).
    pub fn frame(&self, index: usize) -> Result<Frame> {
        let info = self.info(index)?;
        Ok(Frame {
            index,
            timestamp: info.timestamp,
            depth: self.read_depth(&self.root.join(&info.depth))?,
            pose: info.pose,
            camera: self.camera,
            noise: self.noise.clone(),
        })
    }

    /// The noise-free `gt_depth/` twin of frame `index`, `None` when the dataset has none.
    pub fn truth_depth(&self, index: usize) -> Result<Option<DepthImage>> {
        let info = self.info(index)?;
        let name = info.depth.file_name().ok_or_else(|| Error::file(&info.depth, "not a file name"))?;
        let path = self.root.join("gt_depth").join(name);
        if !self.root.join("gt_depth").is_dir() {
            return Ok(None);
        }
        if !path.is_file() {
            return Err(Error::file(&path, "missing: gt_depth/ exists but has no image for this frame"));
        }
        self.read_depth(&path).map(Some)
    }

    fn info(&self, index: usize) -> Result<&FrameInfo> {
        self.frames.get(index).ok_or_else(|| {
            Error::Invalid(format!("frame {index} does not exist: {} has {} frames", self.root.display(), self.len()))
        })
    }

    fn read_depth(&self, path: &Path) -> Result<DepthImage> {
        read_depth_png(path, self.camera.depth_scale, Some((self.camera.width, self.camera.height)))
    }
}

fn load_noise_for(path: &Path, camera: &Camera) -> Result<NoiseModel> {
    let noise = NoiseModel::load(path)?;
    noise.check_camera(camera).map_err(|m| Error::file(path, m))?;
    Ok(noise)
}

/// Non-comment lines of a TUM text file as `(line number, fields)`.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let l = l.trim();
        (!l.is_empty() && !l.starts_with('#')).then(|| (i + 1, l.split_whitespace().collect()))
    })
}

fn parse_number(path: &Path, line: usize, field: &str) -> Result<f64> {
    field.parse::<f64>().map_err(|_| Error::file(path, format!("line {line}: {field:?} is not a number")))
}

fn parse_depth_list(path: &Path) -> Result<Vec<(f64, PathBuf, usize)>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (line, f) in data_lines(&text) {
        if f.len() < 2 {
            return Err(Error::file(path, format!("line {line}: expected \"timestamp path\"")));
        }
        out.push((parse_number(path, line, f[0])?, PathBuf::from(f[1]), line));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// `world.toml`: facts about the dataset's world frame; today its up axis, `up = "+y"`.
fn load_up(path: &Path) -> Result<Up> {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct World {
        up: String,
    }
    let world: World = crate::error::parse_toml(&read_text(path)?, path)?;
    world.up.parse().map_err(|e: Error| Error::file(path, e.to_string()))
}

fn parse_groundtruth(path: &Path) -> Result<Vec<(f64, Pose)>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (line, f) in data_lines(&text) {
        if f.len() != 8 {
            return Err(Error::file(
                path,
                format!("line {line}: expected \"timestamp tx ty tz qx qy qz qw\", found {} fields", f.len()),
            ));
        }
        let v: Vec<f64> = f.iter().map(|s| parse_number(path, line, s)).collect::<Result<_>>()?;
        let (pose, normalised) = pose_from_tum([v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]])
            .map_err(|m| Error::file(path, format!("line {line}: {m}")))?;
        if normalised {
            tracing::warn!("{}: line {line}: quaternion is not unit length; normalised", path.display());
        }
        out.push((v[0], pose, line));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    // One timestamp, one pose: a repeated line is dropped, a conflicting one is an error
    // (which of the two the camera had cannot be known).
    out.dedup_by(|later, kept| later.0 == kept.0 && !moved_beyond(&kept.1, &later.1, 1e-6, 1e-6));
    if let Some(w) = out.windows(2).find(|w| w[0].0 == w[1].0) {
        let (a, b) = (w[0].2.min(w[1].2), w[0].2.max(w[1].2));
        return Err(Error::file(path, format!("lines {a} and {b} give timestamp {} two different poses", w[0].0)));
    }
    Ok(out.into_iter().map(|(t, pose, _)| (t, pose)).collect())
}

/// TUM's `associate.py` rule: among all (depth, pose) pairs closer than `max_diff`, take
/// the closest first, each timestamp used at most once. `poses` must be sorted.
/// Returns, per depth frame, the index of its pose.
fn associate(depths: &[f64], poses: &[f64], max_diff: f64) -> Vec<Option<usize>> {
    let mut candidates = Vec::new();
    for (i, &t) in depths.iter().enumerate() {
        let start = poses.partition_point(|&p| p < t - max_diff);
        for (j, &p) in poses.iter().enumerate().skip(start) {
            if p > t + max_diff {
                break;
            }
            candidates.push(((t - p).abs(), i, j));
        }
    }
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut depth_match = vec![None; depths.len()];
    let mut pose_used = vec![false; poses.len()];
    for (_, i, j) in candidates {
        if depth_match[i].is_none() && !pose_used[j] {
            depth_match[i] = Some(j);
            pose_used[j] = true;
        }
    }
    depth_match
}

/// Decoded frames of a dataset kept for reuse (neighbouring tiles of a tiled build share
/// frames), the oldest dropped first beyond a budget of memory: a tenth of the limit
/// ([`crate::limits::max_memory`]), at most 1 GiB.
pub struct FrameCache<'a> {
    dataset: &'a Dataset,
    frames: std::collections::HashMap<usize, Arc<Frame>>,
    order: std::collections::VecDeque<usize>,
    bytes: usize,
    budget: usize,
}

impl<'a> FrameCache<'a> {
    /// An empty cache of `dataset`'s frames.
    pub fn new(dataset: &'a Dataset) -> Self {
        let budget = (crate::limits::max_memory() / 10).min(1 << 30) as usize;
        FrameCache { dataset, frames: Default::default(), order: Default::default(), bytes: 0, budget }
    }

    /// Frame `index`, decoded now or earlier.
    pub fn get(&mut self, index: usize) -> Result<Arc<Frame>> {
        if let Some(f) = self.frames.get(&index) {
            return Ok(f.clone());
        }
        let frame = Arc::new(self.dataset.frame(index)?);
        let size = |f: &Frame| std::mem::size_of_val(f.depth.data());
        self.bytes += size(&frame);
        self.frames.insert(index, frame.clone());
        self.order.push_back(index);
        while self.bytes > self.budget && self.order.len() > 1 {
            let old = self.order.pop_front().expect("more than one");
            if let Some(f) = self.frames.remove(&old) {
                self.bytes -= size(&f);
            }
        }
        Ok(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn association_is_closest_first_and_one_to_one() {
        let depths = [0.0, 0.011, 1.0, 2.0];
        let poses = [0.001, 0.012, 1.5, 2.019];
        assert_eq!(associate(&depths, &poses, 0.02), vec![Some(0), Some(1), None, Some(3)]);
        // Two depth frames competing for one pose: the closer wins, the other is unmatched.
        assert_eq!(associate(&[0.0, 0.01], &[0.009], 0.02), vec![None, Some(0)]);
    }
}
