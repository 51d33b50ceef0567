//! `mrfmap bag info BAG`: what a ROS 2 bag holds: topics, types, counts, rates, and the frames
//! of its transform tree.

use std::path::PathBuf;

use anyhow::Result;
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
