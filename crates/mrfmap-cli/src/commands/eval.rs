//! `mrfmap eval`: how good is a map? The MRFMap accuracy metric on held-out views of a
//! dataset, and ground-truth metrics against an analytic scene. `loo` and `compare` reuse
//! the scoring pieces here.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use mrfmap::frames::NoiseModel;
use mrfmap::map::Map;
use mrfmap::outputs::pictures::{ray_plot_svg, write_accuracy_image, write_text, write_truth_slices};
use mrfmap::outputs::{AccuracyParams, PeakRule};
use mrfmap::outputs::{Scorer, TruthMetrics, ViewScore, truth_metrics};
use mrfmap::source::Scene;

use super::options::BagArgs;
use super::protocol::Protocol;
use super::views::{Target, Views};

/// Options of the accuracy metric, shared by `eval`, `loo` and `compare`.
#[derive(clap::Args, Clone)]
pub struct MetricOptions {
    /// Tolerance unit of the accuracy metric (m).
    #[arg(long, default_value_t = 0.05, value_parser = super::positive)]
    pub sigma: f64,
    /// Tolerance in units of sigma (the MRFMap paper's text uses 1.5, its code 1).
    #[arg(long, default_value_t = 1.0, value_parser = super::positive)]
    pub k: f64,
    /// Tolerance k times the dataset noise model's std at the peak's depth for each pixel,
    /// instead of k sigma (the reference implementation's rule when it models the sensor, as
    /// the MRFMap paper's Table I describes).
    #[arg(long)]
    pub sigma_model: bool,
    /// The MRFMap paper's boundary rule: a ray the map does not stop, whose depth lies beyond
    /// the mapped part, counts as accurate (default: invalid, as docs/ALGORITHMS.md 6.1).
    #[arg(long)]
    pub paper_boundary: bool,
    /// Where a ray's most likely surface is: `algorithms` (docs/ALGORITHMS.md 6.1: the entry of
    /// the voxel where the generating density peaks, compared as range) or `reference` (the
    /// reference implementation: the exit of the voxel with the largest mean density,
    /// compared as z-depth). Several, comma-separated, score the same maps each way.
    #[arg(long, value_delimiter = ',', default_value = "algorithms")]
    pub metric: Vec<PeakRule>,
    /// What held-out views are scored against: `truth` (their gt_depth/) or `biased` (gt_depth/
    /// plus the dataset noise model's bias: what the sensor reads without noise, the MRFMap
    /// reference implementation's target). Default: `truth`, or the `--protocol`'s.
    #[arg(long, value_enum)]
    pub target: Option<Target>,
}

impl MetricOptions {
    /// `k sigma` in metres.
    pub fn tolerance(&self) -> f64 {
        self.k * self.sigma
    }

    /// What held-out views are scored against under `protocol` (`--target` wins).
    pub fn target(&self, protocol: Protocol) -> Target {
        self.target.unwrap_or(protocol.target())
    }

    /// Metric parameters for `map` with peak rule `peak`.
    pub fn params(&self, map: &Map, peak: PeakRule) -> AccuracyParams {
        AccuracyParams {
            sigma: self.sigma,
            k: self.k,
            beyond_map_is_accurate: self.paper_boundary,
            peak,
            ..AccuracyParams::for_map(map)
        }
    }
}

/// A scorer of `map` under `metric` with peak rule `rule`; `noise` is the dataset's model,
/// which `--sigma-model` needs.
pub fn scorer<'a>(
    map: &'a Map,
    metric: &MetricOptions,
    rule: PeakRule,
    noise: Option<&'a NoiseModel>,
) -> Result<Scorer<'a>> {
    let scorer = Scorer::new(map, metric.params(map, rule));
    if !metric.sigma_model {
        return Ok(scorer);
    }
    let noise = noise.context("--sigma-model needs a noise model: the dataset has no noise.toml (give --noise)")?;
    Ok(scorer.with_model_tolerance(noise))
}

#[derive(clap::Args)]
pub struct Args {
    /// Map file.
    map: PathBuf,
    /// Dataset whose views are scored (its gt_depth/ when present, else depth/), or a ROS bag
    /// (with --depth-topic and --fixed-frame or --pose-topic; scored against its own depth).
    dataset: Option<PathBuf>,
    #[command(flatten)]
    bag: BagArgs,
    /// Views to score (default: all).
    #[arg(long, value_delimiter = ',')]
    views: Vec<usize>,
    #[command(flatten)]
    metric: MetricOptions,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
    /// Write per-view accuracy images (and the --pixel ray plot) into this folder.
    #[arg(long)]
    images: Option<PathBuf>,
    /// Pixel "u,v" whose ray is plotted (p_occ, vis, omega) into --images.
    #[arg(long, value_parser = parse_pixel)]
    pixel: Option<(u32, u32)>,
    /// Analytic scene the map was built from: report MAE, ROC AUC, I_c and sigma-error correlation.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// With --scene: write slices (mean, sigma, |error|, I_c) as PNG into this folder.
    #[arg(long)]
    slices: Option<PathBuf>,
    /// Heights of the slices (m; default: the middle of the map).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    slice_z: Vec<f64>,
}

pub fn parse_pixel(s: &str) -> Result<(u32, u32), String> {
    let (u, v) = s.split_once(',').ok_or("expected u,v")?;
    Ok((u.trim().parse().map_err(|e| format!("u: {e}"))?, v.trim().parse().map_err(|e| format!("v: {e}"))?))
}

/// Scores view `i` of `views` with `scorer`.
pub fn score(scorer: &Scorer, views: &Views, i: usize, target: Target) -> Result<ViewScore> {
    let depth = views.held_out_depth(i, target)?;
    let t = std::time::Instant::now();
    let s = scorer.score_view(&views.camera(), &views.pose(i), &depth);
    tracing::debug!("view {i} scored in {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    Ok(s)
}

/// Mean and sample standard deviation (0 for one value); `None` when empty.
pub fn mean_std(values: &[f64]) -> Option<(f64, f64)> {
    if values.is_empty() {
        return None;
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = if values.len() > 1 { values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    Some((mean, var.sqrt()))
}

/// JSON number, `null` for NaN / missing.
pub fn json_number(v: Option<f64>) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x}"),
        _ => "null".into(),
    }
}

/// Warns when `views` of `dataset` went into `map` (as `build` records them): the score is
/// then not a held-out score.
fn warn_if_not_held_out(map: &Map, dataset: &std::path::Path, views: &[usize]) {
    let same = |p: &str| {
        let canon = |q: &std::path::Path| std::fs::canonicalize(q).ok();
        canon(std::path::Path::new(p)).is_some_and(|a| Some(a) == canon(dataset))
    };
    let (Some(source), Some(frames)) = (map.params.get("source"), map.params.get("frames")) else { return };
    if !same(source) {
        return;
    }
    let used = mrfmap::pipeline::parse_ranges(frames);
    let seen: Vec<usize> = views.iter().copied().filter(|v| used.contains(v)).collect();
    if !seen.is_empty() {
        tracing::warn!(
            "views {seen:?} were used to build this map: their scores are not held-out scores (build with \
             --exclude to hold views out)"
        );
    }
}

/// `{"accuracy": mean, "views": [...]}` fields (without braces) for scored views.
pub fn views_json(scores: &[(usize, ViewScore)]) -> String {
    let accs: Vec<f64> = scores.iter().filter_map(|(_, s)| s.accuracy()).collect();
    let views: Vec<String> = scores
        .iter()
        .map(|(v, s)| {
            format!(
                "{{\"view\": {v}, \"accuracy\": {}, \"accurate\": {}, \"valid\": {}, \"invalid\": {}}}",
                json_number(s.accuracy()),
                s.accurate,
                s.valid(),
                s.invalid
            )
        })
        .collect();
    format!("\"accuracy\": {}, \"views\": [{}]", json_number(mean_std(&accs).map(|m| m.0)), views.join(", "))
}

/// JSON fields of the scores under one or several metrics: one metric as [`views_json`]
/// gives them; several as `"metrics": {"algorithms": {...}, "reference": {...}}`.
pub fn metrics_json(by_metric: &[(PeakRule, Vec<(usize, ViewScore)>)]) -> String {
    match by_metric {
        [(_, scores)] => views_json(scores),
        _ => {
            let each: Vec<String> =
                by_metric.iter().map(|(r, s)| format!("\"{}\": {{{}}}", r.name(), views_json(s))).collect();
            format!("\"metrics\": {{{}}}", each.join(", "))
        }
    }
}

/// A text table of scored views with the mean +- std line.
pub fn views_table(scores: &[(usize, ViewScore)]) -> String {
    let mut t = String::from("view  accuracy  accurate     valid   invalid\n");
    for (v, s) in scores {
        let acc = s.accuracy().map_or("-".into(), |a| format!("{a:.4}"));
        let _ = writeln!(t, "{v:>4}  {acc:>8}  {:>8}  {:>8}  {:>8}", s.accurate, s.valid(), s.invalid);
    }
    let accs: Vec<f64> = scores.iter().filter_map(|(_, s)| s.accuracy()).collect();
    match mean_std(&accs) {
        Some((m, sd)) => {
            let _ = writeln!(t, "mean  {m:.4} +- {sd:.4} over {} views", accs.len());
        }
        None => t.push_str("mean  - (no view has a valid pixel)\n"),
    }
    t
}

/// Writes the accuracy image of a view, and the ray plot of `pixel` if given.
pub fn write_view_pictures(
    dir: &Path,
    prefix: &str,
    scorer: &Scorer,
    views: &Views,
    (view, score): (usize, &ViewScore),
    pixel: Option<(u32, u32)>,
    (tolerance, target): (f64, Target),
) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = vec![dir.join(format!("{prefix}view{view}_accuracy.png"))];
    write_accuracy_image(&written[0], score)?;
    if let Some((u, v)) = pixel {
        let depth = views.held_out_depth(view, target)?;
        match scorer.ray_profile(&views.camera(), &views.pose(view), &depth, (u, v)) {
            Some((steps, verdict)) => {
                let title = format!("{prefix}view {view}, pixel ({u}, {v}): {:?}", verdict.class);
                let path = dir.join(format!("{prefix}view{view}_ray_{u}_{v}.svg"));
                write_text(&path, &ray_plot_svg(&title, &steps, &verdict, tolerance))?;
                written.push(path);
            }
            None => tracing::warn!("view {view}: pixel ({u}, {v}) has no held-out depth or is outside the image"),
        }
    }
    Ok(written)
}

fn truth_json(m: &TruthMetrics) -> String {
    format!(
        "{{\"voxels\": {}, \"mae\": {}, \"auc\": {}, \"ic_gamma_0.5\": {}, \"ic_gamma_2\": {}, \"pearson_sigma_error\": {}, \"precision\": {}, \"recall\": {}}}",
        m.voxels,
        json_number(Some(m.mae)),
        json_number(Some(m.auc)),
        json_number(Some(m.ic_half)),
        json_number(Some(m.ic_two)),
        json_number(Some(m.pearson_sigma_error)),
        json_number(Some(m.precision)),
        json_number(Some(m.recall))
    )
}

pub fn run(a: Args) -> Result<()> {
    if a.dataset.is_none() && a.scene.is_none() {
        bail!(
            "nothing to evaluate against: give a DATASET (accuracy metric) and/or --scene SCENE.toml (ground-truth metrics)"
        );
    }
    if a.slices.is_some() && a.scene.is_none() {
        bail!("--slices needs --scene");
    }
    let map = Map::load(&a.map)?;
    let mut json_fields = Vec::new();
    if let Some(ds_path) = &a.dataset {
        let dataset = Views::open(ds_path, None, &a.bag)?;
        let noise = dataset.noise();
        let views = if a.views.is_empty() { (0..dataset.len()).collect() } else { a.views.clone() };
        mrfmap::pipeline::check_indices(dataset.len(), &views)?;
        warn_if_not_held_out(&map, ds_path, &views);
        let target = a.metric.target(Protocol::Truth);
        let mut by_metric = Vec::new();
        for &rule in &a.metric.metric {
            let scorer = scorer(&map, &a.metric, rule, noise.as_deref())?;
            let bar = crate::progress::bar(Some(views.len()), "scoring");
            let mut scores = Vec::new();
            for &v in &views {
                scores.push((v, score(&scorer, &dataset, v, target)?));
                bar.inc(1);
            }
            bar.finish_and_clear();
            if let Some(dir) = &a.images {
                let prefix = if a.metric.metric.len() > 1 { format!("{}_", rule.name()) } else { String::new() };
                for (v, s) in &scores {
                    let judged = (a.metric.tolerance(), target);
                    write_view_pictures(dir, &prefix, &scorer, &dataset, (*v, s), a.pixel, judged)?;
                }
            }
            by_metric.push((rule, scores));
        }
        if a.json {
            json_fields.push(metrics_json(&by_metric));
        } else {
            for (rule, scores) in &by_metric {
                if by_metric.len() > 1 {
                    println!("metric {}", rule.name());
                }
                print!("{}", views_table(scores));
            }
        }
    }
    if let Some(scene_path) = &a.scene {
        let scene = Scene::load(scene_path)?;
        let m = truth_metrics(&map, &scene);
        if a.json {
            json_fields.push(format!("\"truth\": {}", truth_json(&m)));
        } else {
            println!(
                "ground truth ({} voxels): MAE {:.4}, ROC AUC {:.4}, I_c(0.5) {:.1} ({:.4}/voxel), I_c(2) {:.1} ({:.4}/voxel), corr(sigma, |e|) {:.4}, occupied (> 0.5): precision {:.4}, recall {:.4}",
                m.voxels,
                m.mae,
                m.auc,
                m.ic_half,
                m.ic_half / m.voxels.max(1) as f64,
                m.ic_two,
                m.ic_two / m.voxels.max(1) as f64,
                m.pearson_sigma_error,
                m.precision,
                m.recall
            );
        }
        if let Some(dir) = &a.slices {
            let heights = if a.slice_z.is_empty() {
                let (lo, hi) = map.bounds().context("the map is empty: nothing to slice")?;
                vec![0.5 * (lo[2] + hi[2])]
            } else {
                a.slice_z.clone()
            };
            for z in heights {
                for p in write_truth_slices(&map, &scene, z, dir)? {
                    tracing::info!("wrote {}", p.display());
                }
            }
        }
    }
    if a.json {
        println!("{{{}}}", json_fields.join(", "));
    }
    Ok(())
}
