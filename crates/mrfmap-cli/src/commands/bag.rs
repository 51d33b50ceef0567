//! `mrfmap bag info BAG`: what a ROS 2 or ROS 1 bag holds: topics, types, counts, rates, its log
//! time span, and the frames of its transform tree; `mrfmap export-dataset BAG -o DIR`: its depth images as a dataset.

use std::path::PathBuf;

use anyhow::{Context, Result};
use mrfmap::frames::NoiseModel;
use mrfmap::source::DatasetWriter;
use mrfmap::source::bag::{Bag, TopicInfo};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Subcommand)]
enum Command {
    /// Topics, types, message counts and rates, the log's start and duration, and the TF
    /// tree's frames.
    Info {
        /// A .mcap, .db3 or ROS 1 .bag file, or a bag folder.
        bag: PathBuf,
        /// Print one JSON object (`bag`, `start`, `end`, `duration` in seconds of log time,
        /// `topics` with `topic`, `type`, `messages`, `first`, `last`, `rate_hz`, and
        /// `tf_frames`).
        #[arg(long)]
        json: bool,
    },
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        Command::Info { bag, json } => {
            let bag = Bag::open(&bag)?;
            // Everything is read before anything is printed: a broken bag gives an error alone.
            let topics = bag.topics()?;
            let frames = bag.tf()?.frames();
            let start = topics.iter().map(|t| t.span.0).fold(f64::INFINITY, f64::min);
            let end = topics.iter().map(|t| t.span.1).fold(f64::NEG_INFINITY, f64::max);
            let rate = |t: &TopicInfo| {
                let dt = t.span.1 - t.span.0;
                (t.count > 1 && dt > 0.0).then(|| (t.count - 1) as f64 / dt)
            };
            if json {
                let finite = |v: f64| v.is_finite().then_some(v);
                let out = serde_json::json!({
                    "bag": bag.path.display().to_string(),
                    "start": finite(start),
                    "end": finite(end),
                    "duration": finite(end - start),
                    "topics": topics.iter().map(|t| serde_json::json!({
                        "topic": t.topic, "type": t.msgtype, "messages": t.count,
                        "first": t.span.0, "last": t.span.1, "rate_hz": rate(t),
                    })).collect::<Vec<_>>(),
                    "tf_frames": frames,
                });
                println!("{out}");
                return Ok(());
            }
            println!("{}", bag.path.display());
            if start.is_finite() {
                println!("log time: starts at {start:.3} s, lasts {:.3} s", end - start);
            } else {
                println!("no messages");
            }
            println!("{:<40} {:<36} {:>8} {:>9}", "topic", "type", "messages", "rate (Hz)");
            for t in &topics {
                let rate = rate(t).map_or("-".into(), |r| format!("{r:.2}"));
                println!("{:<40} {:<36} {:>8} {:>9}", t.topic, t.msgtype, t.count, rate);
            }
            if !frames.is_empty() {
                println!("TF frames: {}", frames.join(", "));
            }
            Ok(())
        }
    }
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A .mcap, .db3 or ROS 1 .bag file, or a bag folder.
    bag: PathBuf,
    /// Output dataset folder (TUM layout).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    topics: crate::commands::options::BagArgs,
    /// A noise model to write as the dataset's noise.toml.
    #[arg(long)]
    noise: Option<PathBuf>,
}

/// `mrfmap export-dataset`: a bag's posed depth images as a TUM-layout dataset, for `loo`,
/// `compare`, `eval` and other tools. Depth PNGs use depth_scale 5000 (0.2 mm steps, up to
/// 13.1 m), or 1000 (1 mm, up to 65.5 m) when a depth is beyond 13.1 m. The images stream (one
/// in memory at a time): a pass finds the farthest depth, the next writes them.
pub fn export_dataset(a: ExportArgs) -> Result<()> {
    let (mut farthest, mut camera) = (0.0f32, None);
    a.topics.each_frame(&a.bag, |f| {
        farthest = f.depth.data().iter().copied().fold(farthest, f32::max);
        camera.get_or_insert(f.camera);
        Ok(())
    })?;
    let mut camera = camera.with_context(|| format!("{}: no posed depth image could be read", a.bag.display()))?;
    camera.depth_scale = if farthest > 13.1 { 1000.0 } else { 5000.0 };
    let mut writer = DatasetWriter::create(&a.output, camera, false)?;
    a.topics.each_frame(&a.bag, |f| Ok(writer.add(f.timestamp, &f.pose, &f.depth, None)?))?;
    let noise = a.noise.as_deref().map(NoiseModel::load).transpose()?;
    let n = writer.finish(noise.as_ref())?;
    println!("{}: {n} frames (depth_scale {})", a.output.display(), camera.depth_scale);
    Ok(())
}
