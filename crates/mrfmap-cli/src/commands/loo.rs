//! `mrfmap loo`: leave-one-out accuracy, as the MRFMap paper's tables: for each view, build
//! a map from all other views and score it on the held-out one.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::frames::Frame;
use mrfmap::inference::EngineKind;
use mrfmap::outputs::{Scorer, ViewScore};

use super::build::{BagArgs, MapOptions, build_map, check_indices};
use super::eval::{MetricOptions, score, views_json, views_table};
use super::views::Views;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder, or a ROS bag (with --depth-topic and --fixed-frame or --pose-topic).
    dataset: PathBuf,
    /// Inference engine: logodds, mrf or crm.
    #[arg(long, default_value = "logodds", value_parser = ["logodds", "mrf", "crm"])]
    engine: String,
    /// Voxel edge in metres.
    #[arg(long, value_parser = super::positive, allow_hyphen_values = true)]
    resolution: f64,
    /// Views to hold out in turn (default: all).
    #[arg(long, value_delimiter = ',')]
    views: Vec<usize>,
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

/// Leave-one-out scores of `views` for one engine and resolution; `on_view` sees each
/// held-out build (for pictures).
#[allow(clippy::too_many_arguments)]
pub fn leave_one_out(
    dataset: &Views,
    frames: &[Frame],
    views: &[usize],
    kind: EngineKind,
    resolution: f64,
    options: &MapOptions,
    metric: &MetricOptions,
    mut on_view: impl FnMut(usize, &Scorer, &ViewScore) -> Result<()>,
) -> Result<Vec<(usize, ViewScore)>> {
    let config = options.config(kind, resolution)?;
    let mut scores = Vec::new();
    for &view in views {
        let others: Vec<usize> = (0..frames.len()).filter(|i| *i != view).collect();
        let report = build_map(&others, &config, |i| Ok(frames[i].clone()))?;
        let scorer = Scorer::new(&report.map, metric.params(&report.map));
        let s = score(&scorer, dataset, view)?;
        tracing::info!("{kind} {resolution} m, view {view}: accuracy {:?}", s.accuracy());
        on_view(view, &scorer, &s)?;
        scores.push((view, s));
    }
    Ok(scores)
}

pub fn run(a: Args) -> Result<()> {
    let kind: EngineKind = a.engine.parse()?;
    let dataset = Views::open(&a.dataset, a.options.noise.as_deref(), &a.bag)?;
    let views = if a.views.is_empty() { (0..dataset.len()).collect() } else { a.views.clone() };
    check_indices(dataset.len(), &views)?;
    let frames = dataset.frames()?;
    let scores = leave_one_out(&dataset, &frames, &views, kind, a.resolution, &a.options, &a.metric, |_, _, _| Ok(()))?;
    if a.json {
        println!("{{\"engine\": \"{kind}\", \"resolution\": {}, {}}}", a.resolution, views_json(&scores));
    } else {
        println!("leave-one-out, engine {kind}, resolution {} m", a.resolution);
        print!("{}", views_table(&scores));
    }
    Ok(())
}
