//! A ROS bag's depth images as a build's readings, read once: each image is decoded and handed
//! on as soon as its pose is known, so memory holds a few images whatever the bag's size. A
//! stream's length is known only at its end, so its memory is checked as it grows
//! ([`Growth`]) and `--frames` / `--exclude` indices are checked against the images at the end.

use std::path::Path;

use super::Readings;
use super::memory::Growth;
use super::selection::select_frames;
use crate::error::{Error, Result};
use crate::frames::{Frame, NoiseModel};
use crate::inference::{EngineConfig, MapOutput};
use crate::source::bag::{Bag, BagOptions, DepthStream};

/// Runs `build` on the posed depth images of the bag at `path` (those `frames` names, all
/// when empty, minus `exclude`), streamed, its memory checked for `config` building into
/// `output`; returns what `build` made and the frame indices it was given. Skipped images are
/// summarised in a warning; none posed is an error.
pub fn stream_bag<T>(
    path: &Path,
    options: BagOptions,
    noise: Option<NoiseModel>,
    (frames, exclude): (&[usize], &[usize]),
    (config, output): (&EngineConfig, MapOutput),
    build: impl FnOnce(&mut Readings<'_, Frame>) -> Result<T>,
) -> Result<(T, Vec<usize>)> {
    let topic = options.depth_topic.clone();
    let mut stream = DepthStream::new(Bag::open(path)?, options, noise);
    tracing::info!(
        "{}: depth images of {topic}, engine {}, resolution {} m (streamed)",
        path.display(),
        config.kind,
        config.resolution
    );
    let (mut growth, mut used) = (Growth::new(config, output), Vec::new());
    let built = {
        let mut chosen = stream.by_ref().filter_map(|frame| {
            let frame = match frame {
                Ok(f) if (!frames.is_empty() && !frames.contains(&f.index)) || exclude.contains(&f.index) => {
                    return None;
                }
                other => other,
            };
            Some(frame.and_then(|f| {
                growth.add(&f)?;
                used.push(f.index);
                Ok((f.index, f))
            }))
        });
        build(&mut chosen)?
    };
    let streamed = stream.report().ok_or_else(|| Error::file(path, "the bag's reader stopped without a report"))?;
    check_posed(path, &topic, streamed.frames, &streamed.skipped)?;
    // (The selection again, now that the number of frames is known: its errors.)
    select_frames(streamed.frames, frames, exclude)?;
    Ok((built, used))
}

/// A warning for the `skipped` messages of `topic`, or an error when none had a pose
/// (`count` is how many did).
pub fn check_posed(path: &Path, topic: &str, count: usize, skipped: &[String]) -> Result<()> {
    if let Some(first) = skipped.first() {
        tracing::warn!(
            "{}: {topic}: {} message(s) skipped without a pose (first: {first})",
            path.display(),
            skipped.len()
        );
    }
    if count == 0 {
        return Err(Error::file(path, format!("no image or scan of {topic} has a pose")));
    }
    Ok(())
}
