//! `mrfmap-table2`: the MRFMap paper's Table II (sec. V-B2) on Augmented ICL-NUIM livingroom1,
//! or any dataset of noise-free depth.
//!
//! As the paper: noisy depth simulated from the clean frames (the Kinect model of `add-noise`,
//! a fixed seed), keyframes by its geometric heuristic (translation or rotation from the last
//! keyframe beyond a threshold), maps from the keyframes' noisy depth with the MRF (the noise's
//! forward model), log-odds (OctoMap) and CRM at each resolution, scored with the reference
//! metric on every other frame's noise-free depth, with a constant 5 cm tolerance (the paper's
//! "constant noise model") and with the forward model's std at the peak. Writes `report.md`,
//! `results.json`, the accuracy image of one held-out view per map and a picture of each map
//! stood on the world's up axis; the noisy dataset stays in `noisy/` to build from again.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use mrfmap::frames::{NoiseModel, keyframes_by_motion};
use mrfmap::inference::{EngineConfig, EngineKind, MapOutput, check_build};
use mrfmap::map::Map;
use mrfmap::outputs::pictures::{write_accuracy_image, write_text};
use mrfmap::outputs::{AccuracyParams, PeakRule, Scorer, Up, View, ViewScore, render_map};
use mrfmap::source::Dataset;

use super::noisy_copy;
use crate::commands::eval::mean_std;
use crate::commands::noise::{NoiseArgs, describe};
use crate::commands::options::build_map;
use mrfmap::pipeline::{BUILD_ADVICE, dataset_extent};

/// The paper's Table II: (resolution, MRFMap, OctoMap) accuracy means.
const PAPER: [(f64, f64, f64); 3] = [(0.01, 0.945, 0.922), (0.02, 0.939, 0.882), (0.05, 0.891, 0.723)];

/// The constant tolerance the paper scores with (m).
const CONSTANT_SIGMA: f64 = 0.05;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset of noise-free depth (TUM / ICL-NUIM layout), e.g. icl-livingroom1.
    dataset: PathBuf,
    /// Output folder: report.md, results.json, pictures, and the noisy dataset in noisy/
    /// (replaced on every run).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    noise: NoiseArgs,
    /// Voxel edges (m).
    #[arg(long, value_delimiter = ',', default_value = "0.05,0.02,0.01", value_parser = crate::commands::positive)]
    resolutions: Vec<f64>,
    /// Engines, in report order.
    #[arg(long, value_delimiter = ',', default_value = "mrf,logodds,crm", value_parser = crate::commands::choice::<EngineKind>())]
    engines: Vec<EngineKind>,
    /// Keyframe heuristic: a new keyframe when the camera moved more than this (m) from the
    /// last one (the paper: 1.0 on the whole 2,870-frame sequence; 0.15 gives 21 keyframes on
    /// the first 211 frames).
    #[arg(long, default_value_t = 0.15, value_parser = crate::commands::positive)]
    translation: f64,
    /// ... or turned more than this (rad).
    #[arg(long, default_value_t = 0.15, value_parser = crate::commands::positive)]
    rotation: f64,
    /// Score every N-th frame that is not a keyframe (1: all of them, as the paper).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    views_every: u32,
    /// CRM particles per voxel.
    #[arg(long, default_value_t = 101, value_parser = clap::value_parser!(u16).range(2..))]
    particles: u16,
    /// The world's up axis for the map pictures (ICL-NUIM: +y).
    #[arg(long, default_value = "+y", allow_hyphen_values = true, value_parser = |s: &str| s.parse::<Up>().map_err(|e| e.to_string()))]
    up: Up,
}

/// One map's scores.
struct Row {
    engine: EngineKind,
    resolution: f64,
    /// Seconds to build (integration and inference).
    build_s: f64,
    voxels: usize,
    /// Per held-out view, accuracy with the constant tolerance and with the model's std.
    constant: Vec<f64>,
    model: Vec<f64>,
}

impl Row {
    fn json(&self) -> serde_json::Value {
        let summary = |a: &[f64]| {
            let (mean, std) = mean_std(a).unwrap_or((f64::NAN, f64::NAN));
            serde_json::json!({"mean": mean, "std": std, "views": a})
        };
        serde_json::json!({
            "engine": self.engine.name(),
            "resolution": self.resolution,
            "build_seconds": self.build_s,
            "voxels": self.voxels,
            "accuracy_constant_5cm": summary(&self.constant),
            "accuracy_model_std": summary(&self.model),
        })
    }
}

pub fn mrfmap_table2(a: Args) -> Result<()> {
    let started = Instant::now();
    let clean = Dataset::open(&a.dataset)?;
    let (data, summary) = noisy_copy(&clean, &a.output, &a.noise)?;
    let forward: NoiseModel = data.noise().map(|n| (**n).clone()).context("add-noise writes noise.toml")?;

    let poses: Vec<_> = data.frames().iter().map(|f| f.pose).collect();
    let keyframes = keyframes_by_motion(&poses, a.translation, a.rotation);
    let held_out: Vec<usize> =
        (0..data.len()).filter(|i| !keyframes.contains(i)).step_by(a.views_every as usize).collect();
    if held_out.is_empty() {
        bail!("every frame of {} is a keyframe: nothing is left to score on", a.dataset.display());
    }
    tracing::info!("{} keyframes of {} frames; {} held-out views scored", keyframes.len(), data.len(), held_out.len());
    // The view whose accuracy images are written: the middle held-out one.
    let pictured = held_out[held_out.len() / 2];

    let mut rows = Vec::new();
    for &resolution in &a.resolutions {
        for &kind in &a.engines {
            let mut config = EngineConfig::new(kind, resolution);
            config.crm.particles = a.particles as usize;
            check_build(&config, dataset_extent(&data, &keyframes, &config)?, MapOutput::InMemory, BUILD_ADVICE)?;
            let t = Instant::now();
            let map = build_map(&keyframes, &config, |i| data.frame(i))?.map;
            let build_s = t.elapsed().as_secs_f64();
            let tag = format!("{}_{}cm", kind.name(), resolution * 100.0);
            let (constant, model) = score(&map, &data, &forward, &held_out, |view, score| {
                if view == pictured {
                    write_accuracy_image(&a.output.join(format!("accuracy_{tag}_view{view}.png")), score)?;
                }
                Ok(())
            })?;
            let view = View::overview(&map, a.up).context("the map is empty")?;
            render_map(&map, &View { width: 800, height: 600, ..view })?
                .save(&a.output.join(format!("map_{tag}.png")))?;
            let row = Row { engine: kind, resolution, build_s, voxels: map.voxels.len(), constant, model };
            tracing::info!(
                "{kind} {resolution} m: accuracy {:.4} (5 cm), {:.4} (model std); built in {build_s:.1} s",
                mean_std(&row.constant).map_or(f64::NAN, |m| m.0),
                mean_std(&row.model).map_or(f64::NAN, |m| m.0)
            );
            rows.push(row);
        }
    }
    let elapsed = started.elapsed().as_secs_f64();
    let noise_line = describe(&summary);
    let report = report(&a, &rows, &keyframes, held_out.len(), &noise_line, pictured, elapsed);
    write_text(&a.output.join("report.md"), &report)?;
    let json = serde_json::json!({
        "dataset": a.dataset.display().to_string(),
        "model": a.noise.model,
        "seed": a.noise.seed,
        "particles": a.particles,
        "keyframes": keyframes,
        "held_out_views": held_out,
        "noise": noise_line,
        "seconds": elapsed,
        "rows": rows.iter().map(Row::json).collect::<Vec<_>>(),
    });
    write_text(&a.output.join("results.json"), &serde_json::to_string_pretty(&json)?)?;
    print!("{report}");
    Ok(())
}

/// Accuracy of `map` on each of `views` against the noise-free depth, with the constant
/// tolerance and with `model`'s std at the peak (the reference metric); `each` sees every view's
/// constant-tolerance score.
fn score(
    map: &Map,
    data: &Dataset,
    model: &NoiseModel,
    views: &[usize],
    mut each: impl FnMut(usize, &ViewScore) -> Result<()>,
) -> Result<(Vec<f64>, Vec<f64>)> {
    let params = AccuracyParams { sigma: CONSTANT_SIGMA, k: 1.0, peak: PeakRule::Exit, ..AccuracyParams::for_map(map) };
    let scorer = Scorer::new(map, params);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    let bar = crate::progress::bar(Some(views.len()), "scoring");
    for &view in views {
        let frame = data.frame(view)?;
        let truth = data.truth_depth(view)?.context("add-noise writes gt_depth/")?;
        let [constant, modelled] = <[ViewScore; 2]>::try_from(scorer.score_view_each(
            &frame.camera,
            &frame.pose,
            &truth,
            &[None, Some(model)],
        ))
        .expect("two tolerances");
        each(view, &constant)?;
        a.extend(constant.accuracy());
        b.extend(modelled.accuracy());
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok((a, b))
}

fn report(
    a: &Args,
    rows: &[Row],
    keyframes: &[usize],
    scored: usize,
    noise_line: &str,
    pictured: usize,
    elapsed: f64,
) -> String {
    let mut r = String::new();
    let _ = writeln!(r, "# MRFMap Table II: {}\n", a.dataset.display());
    let _ = writeln!(
        r,
        "Noise: `{}` (seed {}); {noise_line}. Keyframes ({}: moved > {} m or turned > {} rad from the last): {}. \
         Scored: {scored} other frames ({}) against their noise-free depth, reference metric \
         (docs/ALGORITHMS.md 6.1). Default engine settings (CRM: {} particles); the MRF and CRM map with the noise's \
         forward model (`noisy/noise.toml`). Total time {:.0} s.\n",
        a.noise.model,
        a.noise.seed,
        keyframes.len(),
        a.translation,
        a.rotation,
        keyframes.iter().map(usize::to_string).collect::<Vec<_>>().join(","),
        if a.views_every == 1 {
            "every non-keyframe".to_string()
        } else {
            format!("every {}th non-keyframe", a.views_every)
        },
        a.particles,
        elapsed
    );
    for (title, pick) in [
        ("Accuracy, constant 5 cm tolerance (the paper's Table II protocol)", 0),
        ("Accuracy, tolerance = the forward model's std at the peak", 1),
    ] {
        let _ = writeln!(r, "## {title}\n");
        let _ = write!(r, "| engine |");
        for res in &a.resolutions {
            let _ = write!(r, " {res} m |");
        }
        let _ = writeln!(r, "\n|---|{}", "---|".repeat(a.resolutions.len()));
        for &kind in &a.engines {
            let _ = write!(r, "| {kind} |");
            for &res in &a.resolutions {
                let row = rows.iter().find(|x| x.engine == kind && x.resolution == res);
                let values = row.map(|x| if pick == 0 { &x.constant } else { &x.model });
                match values.and_then(|v| mean_std(v)) {
                    Some((m, s)) => {
                        let _ = write!(r, " {m:.3} +- {s:.3} |");
                    }
                    None => r.push_str(" - |"),
                }
            }
            r.push('\n');
        }
        if pick == 0 {
            for (label, column) in [("paper MRFMap", 1), ("paper OctoMap", 2)] {
                let _ = write!(r, "| {label} |");
                for &res in &a.resolutions {
                    match PAPER.iter().find(|p| (p.0 - res).abs() < 1e-9) {
                        Some(p) => {
                            let _ = write!(r, " {:.3} |", if column == 1 { p.1 } else { p.2 });
                        }
                        None => r.push_str(" - |"),
                    }
                }
                r.push('\n');
            }
        }
        r.push('\n');
    }
    let _ =
        writeln!(r, "## Builds\n\n| engine | resolution | build s | voxels | map | accuracy image (view {pictured}) |");
    let _ = writeln!(r, "|---|---|---|---|---|---|");
    for x in rows {
        let tag = format!("{}_{}cm", x.engine.name(), x.resolution * 100.0);
        let _ = writeln!(
            r,
            "| {} | {} m | {:.1} | {} | ![](map_{tag}.png) | ![](accuracy_{tag}_view{pictured}.png) |",
            x.engine.name(),
            x.resolution,
            x.build_s,
            x.voxels
        );
    }
    r
}
