//! `mrfmap loo`: leave-one-out accuracy, as the MRFMap paper's tables: for each view, build
//! a map from all other views and score it on the held-out one.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::frames::Frame;
use mrfmap::inference::EngineKind;
use mrfmap::outputs::{PeakRule, Scorer, ViewScore};

use super::eval::{MetricOptions, metrics_json, score, scorer, views_table};
use super::options::{BagArgs, MapOptions, build_map};
use super::protocol::Protocol;
use super::views::Views;
use mrfmap::pipeline::check_indices;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder, or a ROS bag (with --depth-topic and --fixed-frame or --pose-topic).
    dataset: PathBuf,
    /// Inference engine: logodds, mrf or crm.
    #[arg(long, default_value = "logodds", value_parser = super::choice::<EngineKind>())]
    engine: EngineKind,
    /// Voxel edge in metres.
    #[arg(long, value_parser = super::positive, allow_hyphen_values = true)]
    resolution: f64,
    /// Views to hold out in turn (default: all).
    #[arg(long, value_delimiter = ',')]
    views: Vec<usize>,
    /// Experiment protocol: `truth` (the dataset's noise model; scored against gt_depth/) or
    /// `reference` (the MRFMap reference implementation's coffin-world set-up: constant 0.05 m
    /// std, a 3x wider likelihood, no bias, log-odds clamped to [0.0001, 0.9999]; scored
    /// against gt_depth/ plus the dataset model's bias). README, "Protocols".
    #[arg(long, value_enum, default_value_t = Protocol::Truth)]
    protocol: Protocol,
    #[command(flatten)]
    options: MapOptions,
    #[command(flatten)]
    metric: MetricOptions,
    #[command(flatten)]
    bag: BagArgs,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

/// Per peak rule, the score of each held-out view.
pub type ScoresByRule = Vec<(PeakRule, Vec<(usize, ViewScore)>)>;

/// Leave-one-out scores of `views` for one engine, resolution and protocol, per metric of
/// `metric` (the same maps scored each way); `on_view` sees each held-out build with the
/// first metric's scorer (for pictures).
#[allow(clippy::too_many_arguments)]
pub fn leave_one_out(
    dataset: &Views,
    frames: &[Frame],
    views: &[usize],
    (kind, resolution): (EngineKind, f64),
    protocol: Protocol,
    options: &MapOptions,
    metric: &MetricOptions,
    mut on_view: impl FnMut(usize, &Scorer, &ViewScore) -> Result<()>,
) -> Result<ScoresByRule> {
    let config = protocol.options(options).config(kind, resolution)?;
    let frames = protocol.frames(frames);
    let target = metric.target(protocol);
    let noise = dataset.noise();
    let mut by_metric: Vec<(PeakRule, Vec<(usize, ViewScore)>)> =
        metric.metric.iter().map(|&r| (r, Vec::new())).collect();
    for &view in views {
        let others: Vec<usize> = (0..frames.len()).filter(|i| *i != view).collect();
        let report = build_map(&others, &config, |i| Ok(frames[i].clone()))?;
        for (n, (rule, scores)) in by_metric.iter_mut().enumerate() {
            let scorer = scorer(&report.map, metric, *rule, noise.as_deref())?;
            let s = score(&scorer, dataset, view, target)?;
            tracing::info!(
                "{kind} {resolution} m, {} protocol, view {view}: accuracy {} ({} metric)",
                protocol.name(),
                s.accuracy().map_or("- (no valid pixel)".to_string(), |a| format!("{a:.4}")),
                rule.name()
            );
            if n == 0 {
                on_view(view, &scorer, &s)?;
            }
            scores.push((view, s));
        }
    }
    Ok(by_metric)
}

pub fn run(a: Args) -> Result<()> {
    let kind = a.engine;
    let dataset = Views::open(&a.dataset, a.options.noise.as_deref(), &a.bag)?;
    let views = if a.views.is_empty() { (0..dataset.len()).collect() } else { a.views.clone() };
    check_indices(dataset.len(), &views)?;
    let frames = dataset.frames()?;
    let by_metric = leave_one_out(
        &dataset,
        &frames,
        &views,
        (kind, a.resolution),
        a.protocol,
        &a.options,
        &a.metric,
        |_, _, _| Ok(()),
    )?;
    if a.json {
        println!(
            "{{\"engine\": \"{kind}\", \"resolution\": {}, \"protocol\": \"{}\", {}}}",
            a.resolution,
            a.protocol.name(),
            metrics_json(&by_metric)
        );
    } else {
        println!("leave-one-out, engine {kind}, resolution {} m, {} protocol", a.resolution, a.protocol.name());
        for (rule, scores) in &by_metric {
            if by_metric.len() > 1 {
                println!("metric {}", rule.name());
            }
            print!("{}", views_table(scores));
        }
    }
    Ok(())
}
