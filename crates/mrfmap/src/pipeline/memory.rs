//! Memory checks of a build, before it starts and while it grows: a dataset's frames sized
//! from every pose and a few decoded frames, or from the poses alone where that settles the
//! check ([`dataset_extent`]), and a stream's, whose length is known only at its end,
//! re-estimated as it doubles ([`Growth`]).

use std::borrow::Cow;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::frames::{Frame, Pose};
use crate::inference::{
    ANNOUNCED_MEMORY, EngineConfig, Extent, MapOutput, check_build, estimate_memory, frames_extent,
    frames_extent_loaded, poses_bound,
};
use crate::limits;
use crate::source::Dataset;

/// Frames decoded for a memory estimate, at most.
pub const SAMPLE_FRAMES: usize = 8;

/// What a build refused for memory can change.
pub const BUILD_ADVICE: &str = "use a coarser --resolution, or map less with --bounds or --max-range";

/// Where the frames `indices` of `dataset` look, estimated from every pose and a few decoded
/// frames (decoding every frame twice would double the I/O). Where the box of the cameras
/// widened by the max range ([`poses_bound`], log-odds only) already settles the check, that
/// box is the answer and no frame is decoded: a build at 0.05 m spent 4-16% of its time
/// decoding frames for the estimate (BENCHMARKS.md, "Log-odds engine vs wavemap", session
/// 35). When the few are all the frames (eight or fewer) and take at most 10 MiB of depth
/// (eight 640 x 480 frames), they are decoded once, together on the pool's threads, and held
/// while the estimate reads them: the build decodes each of them again, and the estimate's own
/// decodes (two per frame, three for the MRF) were most of all. Otherwise they are decoded one
/// at a time, again for each of the estimate's passes
/// ([`frames_extent_loaded`]): there they are a small share of the decodes, and eight frames
/// held set a small map's peak (icl-livingroom1 at 0.05 m: 17.0 MiB where the build alone
/// peaks at 12.4; BENCHMARKS.md, "Log-odds engine vs wavemap", session 34).
pub fn dataset_extent(dataset: &Dataset, indices: &[usize], config: &EngineConfig) -> Result<Option<Extent>> {
    extent_holding_at_most(dataset, indices, config, HELD_DEPTH_BYTES)
}

/// Depth (4 bytes a pixel) of the frames [`dataset_extent`] may hold: eight 640 x 480 frames.
const HELD_DEPTH_BYTES: f64 = 10.0 * (1 << 20) as f64;

/// [`dataset_extent`], holding the sampled frames when they are all the frames and their depth
/// takes at most `hold` bytes.
fn extent_holding_at_most(
    dataset: &Dataset,
    indices: &[usize],
    config: &EngineConfig,
    hold: f64,
) -> Result<Option<Extent>> {
    let step = indices.len().div_ceil(SAMPLE_FRAMES).max(1);
    let sampled: Vec<usize> = indices.iter().step_by(step).copied().collect();
    let poses = indices.iter().map(|&i| dataset.frames()[i].pose);
    let camera = dataset.camera();
    let pixels = f64::from(camera.width) * f64::from(camera.height);
    if let Some(bound) = poses_bound(poses.clone(), pixels, config)
        && bound_settles_the_check(&bound, config)
    {
        tracing::debug!("memory: the box of the cameras and the max range settles the check; no frame sampled");
        return Ok(Some(bound));
    }
    let bytes = 4.0 * pixels * sampled.len() as f64;
    if sampled.len() == indices.len() && bytes <= hold {
        // (The first frame that fails is the one named, whichever thread read it.)
        let decoded: Vec<Result<Frame>> = sampled.par_iter().map(|&i| dataset.frame(i)).collect();
        let frames = decoded.into_iter().collect::<Result<Vec<Frame>>>()?;
        return Ok(frames_extent(poses, &frames, config));
    }
    frames_extent_loaded(poses, sampled.len(), |k| dataset.frame(sampled[k]).map(Cow::Owned), config)
}

/// Whether [`check_build`] of a pose bound ([`poses_bound`]) says what it would say of the
/// frames' own estimate, so that the frames need not be decoded for it: the bound's estimate,
/// which is at least theirs, is within the limit and below what is announced (so the frames'
/// is too, and neither refuses nor announces), and the cameras lie a voxel or more apart (the
/// frames' box holds the cameras, so it is at least a voxel across, and neither warns of a
/// map of a few voxels). Builds at 0.05 m with a max range of 6 m pass (icl-livingroom-5,
/// icl-livingroom1, coffin-world); at 0.02 m the same box holds gigabytes' worth of bricks,
/// and the frames are sampled as before.
fn bound_settles_the_check(bound: &Extent, config: &EngineConfig) -> bool {
    let estimate = [MapOutput::Saved, MapOutput::InMemory]
        .into_iter()
        .map(|output| estimate_memory(config, bound, output))
        .fold(0.0, f64::max);
    let reach = config.limits.max_range.unwrap_or(f64::INFINITY);
    estimate <= ANNOUNCED_MEMORY.min(limits::max_memory() as f64) && bound.size() - 2.0 * reach >= config.resolution
}

/// The memory check of a streamed build: the map's estimate from the poses so far and a few
/// frames spread over them, checked each time the number of frames doubles, and the resident
/// size at every frame (between two estimates the map may double).
pub struct Growth<'a> {
    config: &'a EngineConfig,
    output: MapOutput,
    poses: Vec<Pose>,
    /// Every `stride`-th frame, at most [`SAMPLE_FRAMES`] of them (the stride doubles).
    sample: Vec<Frame>,
    stride: usize,
}

impl<'a> Growth<'a> {
    /// A check for a build with `config` into `output`, before its first frame.
    pub fn new(config: &'a EngineConfig, output: MapOutput) -> Self {
        Growth { config, output, poses: Vec::new(), sample: Vec::new(), stride: 1 }
    }

    /// Counts `frame` in, and fails if the build has outgrown the memory limit or will.
    pub fn add(&mut self, frame: &Frame) -> Result<()> {
        let n = self.poses.len();
        self.poses.push(frame.pose);
        if n.is_multiple_of(self.stride) {
            self.sample.push(frame.clone());
            if self.sample.len() > SAMPLE_FRAMES {
                // Frames 0, s, 2s, ... are kept: those at even places are the multiples of 2s.
                self.stride *= 2;
                let mut place = 0;
                self.sample.retain(|_| {
                    place += 1;
                    place % 2 == 1
                });
            }
        }
        let limit = crate::limits::max_memory();
        if let Some(resident) = crate::limits::resident_memory().filter(|&r| r > limit) {
            return Err(Error::Memory(format!(
                "the map outgrew the memory limit after {} frames ({} resident, limit {}; {BUILD_ADVICE}, or raise \
                 the limit with --max-memory / MRFMAP_MAX_MEMORY)",
                n + 1,
                crate::limits::human(resident as f64),
                crate::limits::human(limit as f64)
            )));
        }
        if !(n + 1).is_power_of_two() {
            return Ok(());
        }
        let extent = frames_extent(self.poses.iter().copied(), &self.sample, self.config);
        check_build(self.config, extent, self.output, BUILD_ADVICE)
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::inference::EngineKind;
    use crate::source::{Scene, simulate};

    /// A 20-frame orbit of a small scene, simulated into a folder named by `name`.
    fn orbit_dataset(name: &str) -> std::path::PathBuf {
        let scene = Scene::from_toml(
            "[camera]\nfx = 40.0\nfy = 40.0\ncx = 15.5\ncy = 11.5\nwidth = 32\nheight = 24\ndepth_scale = 5000.0\n\
             [[box]]\nmin = [-1.0, -1.0, -0.1]\nmax = [1.0, 1.0, 0.0]\n\
             [[box]]\nmin = [-0.2, -0.2, 0.0]\nmax = [0.2, 0.2, 0.5]\n\
             [orbit]\ncenter = [0.0, 0.0, 0.0]\nradius = 1.5\nheight = 1.0\nviews = 20\n",
            Path::new("scene.toml"),
        )
        .unwrap();
        let dir = std::env::temp_dir().join(format!("mrfmap-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        simulate(&scene, &dir, 1).unwrap();
        dir
    }

    /// A log-odds build with a max range is checked against the box of its cameras widened by
    /// the max range where that settles the check (coarse voxels), and against its sampled
    /// frames where it does not (fine voxels); the bound is above the frames' estimate in every
    /// count and in memory; other engines and builds without a max range are always sampled.
    #[test]
    fn a_pose_bound_stands_for_the_frames_only_where_it_settles_the_check() {
        let dir = orbit_dataset("pose-bound");
        let dataset = Dataset::open(&dir).unwrap();
        let indices: Vec<usize> = (0..dataset.frames().len()).collect();
        let poses = || indices.iter().map(|&i| dataset.frames()[i].pose);
        let sampled = |config: &EngineConfig| extent_holding_at_most(&dataset, &indices, config, 0.0).unwrap();
        let pixels = 32.0 * 24.0;
        for (resolution, settles) in [(0.05, true), (0.002, false)] {
            let mut config = EngineConfig::new(EngineKind::LogOdds, resolution);
            config.limits.max_range = Some(3.0);
            let (bound, frames) = (poses_bound(poses(), pixels, &config).unwrap(), sampled(&config).unwrap());
            for (b, f) in [(bound.bricks, frames.bricks), (bound.layers, frames.layers), (bound.voxels, frames.voxels)]
            {
                assert!(b >= f, "{resolution}: bound {b} below the frames' {f}");
            }
            for output in [MapOutput::Saved, MapOutput::InMemory] {
                assert!(estimate_memory(&config, &bound, output) >= estimate_memory(&config, &frames, output));
            }
            assert_eq!(bound_settles_the_check(&bound, &config), settles, "{resolution}");
            let expected = if settles { bound } else { frames };
            assert_eq!(dataset_extent(&dataset, &indices, &config).unwrap(), Some(expected), "{resolution}");
            // Without a max range, or for another engine: no bound.
            config.limits.max_range = None;
            assert!(poses_bound(poses(), pixels, &config).is_none());
            for kind in [EngineKind::Crm, EngineKind::Mrf] {
                let mut other = EngineConfig::new(kind, resolution);
                other.limits.max_range = Some(3.0);
                assert!(poses_bound(poses(), pixels, &other).is_none(), "{kind:?}");
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A dataset's estimate, its sampled frames decoded together (on the pool's threads) or one
    /// at a time for each pass, is the estimate of the same frames held, for every engine (the
    /// MRF walks twice), for a long build and for a build of a few frames.
    #[test]
    fn a_dataset_estimate_equals_the_estimate_of_its_frames_held() {
        let dir = orbit_dataset("estimate");
        // (A noise-free scene writes no noise model: a zero one made the dataset unreadable.)
        assert!(!dir.join("noise.toml").exists());
        let dataset = Dataset::open(&dir).unwrap();
        let indices: Vec<usize> = (0..dataset.frames().len()).collect();
        let step = indices.len().div_ceil(SAMPLE_FRAMES);
        let sampled: Vec<Frame> = indices.iter().step_by(step).map(|&i| dataset.frame(i).unwrap()).collect();
        assert!(sampled.len() > 1 && sampled.len() <= SAMPLE_FRAMES);
        // Twenty frames, eight of them sampled (decoded one at a time for each pass), and six
        // frames, all sampled (decoded together and held, or not with no room to hold them).
        let few: Vec<usize> = (3..9).collect();
        let few_frames: Vec<Frame> = few.iter().map(|&i| dataset.frame(i).unwrap()).collect();
        for kind in [EngineKind::LogOdds, EngineKind::Crm, EngineKind::Mrf] {
            let config = EngineConfig::new(kind, 0.05);
            for (indices, sampled) in [(&indices, &sampled), (&few, &few_frames)] {
                let held = frames_extent(indices.iter().map(|&i| dataset.frames()[i].pose), sampled, &config);
                assert!(held.is_some_and(|e| e.bricks > 0.0), "{kind:?}");
                assert_eq!(held, dataset_extent(&dataset, indices, &config).unwrap(), "{kind:?}");
                assert_eq!(held, extent_holding_at_most(&dataset, indices, &config, 0.0).unwrap(), "{kind:?}");
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
