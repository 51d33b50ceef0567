//! `mrfmap noise`: look at a noise model; `mrfmap add-noise`: make a clean dataset noisy.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use mrfmap::frames::NoiseModel;
use mrfmap::outputs::pictures::noise_figure;
use mrfmap::source::{Dataset, DepthNoise, NoiseStatistics, NoisySummary, StructuredLight, add_noise};

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

/// `mrfmap add-noise`.
#[derive(clap::Args)]
pub struct AddArgs {
    /// Dataset with noise-free depth (TUM / ICL-NUIM layout).
    dataset: PathBuf,
    /// Output dataset folder (must not exist): noisy `depth/`, the input's depth as `gt_depth/`,
    /// and `noise.toml`, the forward model to map it with.
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    noise: NoiseArgs,
}

/// The simulated sensor: what `add-noise` and the experiments that add noise share.
#[derive(clap::Args)]
pub struct NoiseArgs {
    /// `kinect`: a structured-light sensor in disparity, as Augmented ICL-NUIM's noisy depth
    /// (1/8 px quantisation, a fixed distortion, white noise, lateral jitter, a border and
    /// grazing-angle holes; docs/ALGORITHMS.md 3.1). Or a `noise.toml`: Gaussian in depth with
    /// its bias and std (per patch or aggregate).
    #[arg(long, default_value = "kinect")]
    pub model: String,
    /// Seed: the sensor (its fixed distortion) and every frame's noise follow from it.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Kinect only: lose pixels the projector cannot light (shadows beside depth edges), as a
    /// real Kinect does; Augmented ICL-NUIM's frames have none.
    #[arg(long)]
    pub shadows: bool,
}

impl NoiseArgs {
    /// The noise `--model` names: `kinect` (with projector shadows if asked) or a noise.toml.
    pub fn noise(&self) -> Result<DepthNoise> {
        if self.model == "kinect" {
            return Ok(DepthNoise::StructuredLight(StructuredLight {
                shadows: self.shadows,
                ..StructuredLight::kinect()
            }));
        }
        if self.shadows {
            bail!("--shadows is a setting of --model kinect, not of a noise.toml model");
        }
        let path = PathBuf::from(&self.model);
        if !path.is_file() {
            bail!("--model {}: neither `kinect` nor an existing noise.toml file", self.model);
        }
        Ok(DepthNoise::Model(NoiseModel::load(&path)?))
    }

    /// Writes `clean` made noisy to `out` (which must not exist), with a progress bar.
    pub fn write(&self, clean: &Dataset, out: &Path) -> Result<NoisySummary> {
        let noise = self.noise()?;
        let bar = crate::progress::bar(Some(clean.len()), "add-noise");
        let summary = add_noise(clean, out, &noise, self.seed, |done| bar.set_position(done as u64))
            .with_context(|| format!("adding noise to {}", clean.root().display()))?;
        bar.finish_and_clear();
        Ok(summary)
    }
}

/// One line on `summary`'s noise: the frames' mean statistics against their clean depth.
pub fn describe(summary: &NoisySummary) -> String {
    let stats: Vec<_> = summary.statistics.iter().flatten().collect();
    if stats.is_empty() {
        return "no pixel valid in both noisy and clean depth".into();
    }
    let mean = |f: &dyn Fn(&NoiseStatistics) -> f64| stats.iter().map(|s| f(s)).sum::<f64>() / stats.len() as f64;
    format!(
        "noisy - clean, mean over {} frames: median {:+.1} mm, MAD {:.1} mm, 95th percentile |e| {:.1} mm, \
         {:.1}% of valid pixels lost, {:.0} depth levels per frame",
        stats.len(),
        1e3 * mean(&|s| s.median),
        1e3 * mean(&|s| s.mad),
        1e3 * mean(&|s| s.p95_abs),
        100.0 * mean(&|s| s.lost),
        mean(&|s| s.levels as f64)
    )
}

pub fn add(a: AddArgs) -> Result<()> {
    let dataset = Dataset::open(&a.dataset)?;
    if dataset.truth_depth(0)?.is_some() {
        tracing::warn!(
            "{} already has gt_depth/: its depth/ is made noisy and written as the new gt_depth/",
            a.dataset.display()
        );
    }
    let summary = a.noise.write(&dataset, &a.output)?;
    println!("{}: {} frames", a.output.display(), summary.frames);
    println!("{}", describe(&summary));
    Ok(())
}
