//! `mrfmap noise`: look at a noise model.

use std::path::PathBuf;

use anyhow::{Result, bail};
use mrfmap::frames::NoiseModel;
use mrfmap::outputs::pictures::noise_figure;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: NoiseCommand,
}

#[derive(clap::Subcommand)]
enum NoiseCommand {
    /// Bias and std against depth (aggregate and a few patches) and a patch map of std.
    Plot(PlotArgs),
}

#[derive(clap::Args)]
struct PlotArgs {
    /// Noise model (`noise.toml`).
    model: PathBuf,
    /// Output PNG.
    #[arg(short, long)]
    output: PathBuf,
    /// Depth at which the patch map shows std (metres).
    #[arg(long, default_value_t = 2.0, value_parser = super::positive)]
    depth: f64,
    /// Depth range of the curves: MIN,MAX (metres).
    #[arg(long, default_value = "0.3,5.0")]
    range: String,
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        NoiseCommand::Plot(p) => plot(p),
    }
}

fn plot(a: PlotArgs) -> Result<()> {
    let model = NoiseModel::load(&a.model)?;
    let parts: Vec<f64> = a.range.split(',').map(|s| s.trim().parse::<f64>()).collect::<Result<_, _>>()?;
    let &[lo, hi] = parts.as_slice() else {
        bail!("--range needs MIN,MAX, got {:?}", a.range);
    };
    if !(lo >= 0.0 && hi > lo && hi.is_finite()) {
        bail!("--range needs 0 <= MIN < MAX, got {lo},{hi}");
    }
    noise_figure(&model, (lo, hi), a.depth).save(&a.output)?;
    println!("{}", a.output.display());
    Ok(())
}
