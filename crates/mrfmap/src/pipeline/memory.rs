//! Memory checks of a build, before it starts and while it grows: a dataset's frames sized
//! from every pose and a few decoded frames ([`dataset_extent`]), and a stream's, whose length
//! is known only at its end, re-estimated as it doubles ([`Growth`]).

use crate::error::{Error, Result};
use crate::frames::{Frame, Pose};
use crate::inference::{EngineConfig, Extent, MapOutput, check_build, frames_extent};
use crate::source::Dataset;

/// Frames decoded for a memory estimate, at most.
pub const SAMPLE_FRAMES: usize = 8;

/// What a build refused for memory can change.
pub const BUILD_ADVICE: &str = "use a coarser --resolution, or map less with --bounds or --max-range";

/// Where the frames `indices` of `dataset` look, estimated from every pose and a few decoded
/// frames (decoding every frame twice would double the I/O).
pub fn dataset_extent(dataset: &Dataset, indices: &[usize], config: &EngineConfig) -> Result<Option<Extent>> {
    let step = indices.len().div_ceil(SAMPLE_FRAMES).max(1);
    let sampled = indices.iter().step_by(step).map(|&i| dataset.frame(i)).collect::<Result<Vec<_>>>()?;
    let poses = indices.iter().map(|&i| dataset.frames()[i].pose);
    Ok(frames_extent(poses, &sampled, config))
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
