//! `mrfmap bag info BAG`: what a ROS 2 bag holds: topics, types, counts, rates, and the frames
//! of its transform tree; `mrfmap export-dataset BAG -o DIR`: its depth images as a dataset.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::frames::NoiseModel;
use mrfmap::source::DatasetWriter;
use mrfmap::source::bag::Bag;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Subcommand)]
enum Command {
    /// Topics, types, message counts and rates, and the TF tree's frames.
    Info {
        /// A .mcap file or a bag folder.
        bag: PathBuf,
    },
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        Command::Info { bag } => {
            let bag = Bag::open(&bag)?;
            println!("{}", bag.path.display());
            println!("{:<40} {:<36} {:>8} {:>9}", "topic", "type", "messages", "rate (Hz)");
            for t in bag.topics()? {
                let dt = t.span.1 - t.span.0;
                let rate =
                    if t.count > 1 && dt > 0.0 { format!("{:.2}", (t.count - 1) as f64 / dt) } else { "-".into() };
                println!("{:<40} {:<36} {:>8} {:>9}", t.topic, t.msgtype, t.count, rate);
            }
            let frames = bag.tf()?.frames();
            if !frames.is_empty() {
                println!("TF frames: {}", frames.join(", "));
            }
            Ok(())
        }
    }
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A .mcap or .db3 file, or a bag folder.
    bag: PathBuf,
    /// Output dataset folder (TUM layout).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    topics: crate::commands::build::BagArgs,
    /// A noise model to write as the dataset's noise.toml.
    #[arg(long)]
    noise: Option<PathBuf>,
}

/// `mrfmap export-dataset`: a bag's posed depth images as a TUM-layout dataset, for `loo`,
/// `compare`, `eval` and other tools. Depth PNGs use depth_scale 5000 (0.2 mm steps, up to
/// 13.1 m), or 1000 (1 mm, up to 65.5 m) when a depth is beyond 13.1 m.
pub fn export_dataset(a: ExportArgs) -> Result<()> {
    let frames = a.topics.frames(&a.bag, None)?;
    let farthest = frames.iter().flat_map(|f| f.depth.data().iter().copied()).fold(0.0f32, f32::max);
    let mut camera = frames[0].camera;
    camera.depth_scale = if farthest > 13.1 { 1000.0 } else { 5000.0 };
    let mut writer = DatasetWriter::create(&a.output, camera, false)?;
    for f in &frames {
        writer.add(f.timestamp, &f.pose, &f.depth, None)?;
    }
    let noise = a.noise.as_deref().map(NoiseModel::load).transpose()?;
    let n = writer.finish(noise.as_ref())?;
    println!("{}: {n} frames (depth_scale {})", a.output.display(), camera.depth_scale);
    Ok(())
}
