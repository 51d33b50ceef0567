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
//!
//! With `--surfaces`, two maps of no engine beside them, scored the same way: the noise-free surfaces of
//! the keyframes and of every frame, the scored ones included, voxelised ([`surface_truth`]:
//! occupied where a clean depth point falls, free where only rays pass). They are what a
//! binary map scores with perfect depth, not a ceiling: a soft map can score above them (the
//! MRF does on livingroom1, RESULTS.md). With `--grid-offsets N` everything is built and
//! scored again with the world shifted by N random fractions of a voxel: at coarse
//! resolutions a score depends on where the grid cuts the scene's surfaces.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use mrfmap::frames::{Frame, NoiseModel, keyframes_by_motion};
use mrfmap::inference::{EngineConfig, EngineKind, MapOutput, check_build};
use mrfmap::map::Map;
use mrfmap::outputs::pictures::{write_accuracy_image, write_text};
use mrfmap::outputs::{AccuracyParams, PeakRule, Scorer, Up, View, ViewScore, render_map, surface_truth};
use mrfmap::random::Rng;
use mrfmap::source::Dataset;
use nalgebra::Vector3;

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
    /// Also score the noise-free surfaces of the keyframes and of every frame, voxelised:
    /// what a binary map scores with perfect depth.
    #[arg(long)]
    surfaces: bool,
    /// Also build and score at this many other placements of the voxel grid, each the world
    /// shifted by a random fraction of a voxel per axis: how much of a score is where the
    /// grid happens to cut the scene's surfaces (no pictures of these).
    #[arg(long, default_value_t = 0)]
    grid_offsets: u32,
}

/// The names in the report of the voxelised noise-free surfaces: the keyframes', every frame's.
const SURFACES: [&str; 2] = ["surfaces of the keyframes", "surfaces of every frame"];

/// One map's scores.
struct Row {
    /// The engine's name, or one of [`SURFACES`].
    name: &'static str,
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
            "engine": self.name,
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
    let setup =
        Setup { a: &a, clean: &clean, data: &data, forward: &forward, keyframes: &keyframes, held_out: &held_out };
    // The view whose accuracy images are written: the middle held-out one.
    let pictured = held_out[held_out.len() / 2];
    let rows = setup.rows([0.0; 3], Some(pictured))?;
    // Other placements of the grid: each a shift of the world by a random fraction of a voxel
    // per axis (the same fractions at every resolution), drawn from the noise's seed.
    let mut rng = Rng::stream(a.noise.seed, 0x6F1D, 0);
    let mut placements = Vec::new();
    for k in 0..a.grid_offsets {
        let fraction = [(); 3].map(|_| rng.uniform());
        tracing::info!("grid placement {} of {}: shift {fraction:.3?} voxel", k + 1, a.grid_offsets);
        placements.push((fraction, setup.rows(fraction, None)?));
    }
    let elapsed = started.elapsed().as_secs_f64();
    let noise_line = describe(&summary);
    let report = report(&a, &rows, &placements, &keyframes, held_out.len(), &noise_line, pictured, elapsed);
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
        "grid_placements": placements.iter().map(|(fraction, rows)| serde_json::json!({
            "shift_voxels": fraction,
            "rows": rows.iter().map(Row::json).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
    });
    write_text(&a.output.join("results.json"), &serde_json::to_string_pretty(&json)?)?;
    print!("{report}");
    Ok(())
}

/// What every placement of the grid is built and scored from.
struct Setup<'a> {
    a: &'a Args,
    clean: &'a Dataset,
    data: &'a Dataset,
    forward: &'a NoiseModel,
    keyframes: &'a [usize],
    held_out: &'a [usize],
}

impl Setup<'_> {
    /// Every resolution's rows (the voxelised surfaces, then the engines) with the world shifted by
    /// `fraction` of a voxel per axis; with `pictured`, the maps' pictures and that view's
    /// accuracy images are written.
    fn rows(&self, fraction: [f64; 3], pictured: Option<usize>) -> Result<Vec<Row>> {
        let (a, data) = (self.a, self.data);
        let every: Vec<usize> = (0..self.clean.len()).collect();
        let mut rows = Vec::new();
        for &resolution in &a.resolutions {
            let shift = Vector3::from(fraction) * resolution;
            let moved = |frame: mrfmap::Result<Frame>| {
                frame.map(|mut f| {
                    f.pose.translation.vector += shift;
                    f
                })
            };
            // (The surfaces' voxels are those a log-odds map of the same frames holds: its
            // estimate is theirs.)
            let surfaces = EngineConfig::new(EngineKind::LogOdds, resolution);
            for (name, frames) in SURFACES.into_iter().zip([self.keyframes, &every]).filter(|_| a.surfaces) {
                check_build(
                    &surfaces,
                    dataset_extent(self.clean, frames, &surfaces)?,
                    MapOutput::InMemory,
                    BUILD_ADVICE,
                )?;
                let t = Instant::now();
                let mut map = Map::new(EngineKind::LogOdds, resolution)?;
                map.voxels =
                    surface_truth(frames.iter().map(|&i| moved(self.clean.frame(i))), resolution, &surfaces.limits)?;
                let build_s = t.elapsed().as_secs_f64();
                let (constant, model) = self.score(&map, shift, |_, _| Ok(()))?;
                rows.push(Row { name, resolution, build_s, voxels: map.voxels.len(), constant, model });
            }
            for &kind in &a.engines {
                let mut config = EngineConfig::new(kind, resolution);
                config.crm.particles = a.particles as usize;
                check_build(
                    &config,
                    dataset_extent(data, self.keyframes, &config)?,
                    MapOutput::InMemory,
                    BUILD_ADVICE,
                )?;
                let t = Instant::now();
                let map = build_map(self.keyframes, &config, |i| moved(data.frame(i)))?.map;
                let build_s = t.elapsed().as_secs_f64();
                let tag = format!("{}_{}cm", kind.name(), resolution * 100.0);
                let (constant, model) = self.score(&map, shift, |view, score| {
                    if Some(view) == pictured {
                        write_accuracy_image(&a.output.join(format!("accuracy_{tag}_view{view}.png")), score)?;
                    }
                    Ok(())
                })?;
                if pictured.is_some() {
                    let view = View::overview(&map, a.up).context("the map is empty")?;
                    render_map(&map, &View { width: 800, height: 600, ..view })?
                        .save(&a.output.join(format!("map_{tag}.png")))?;
                }
                let row = Row { name: kind.name(), resolution, build_s, voxels: map.voxels.len(), constant, model };
                tracing::info!(
                    "{kind} {resolution} m: accuracy {:.4} (5 cm), {:.4} (model std); built in {build_s:.1} s",
                    mean_std(&row.constant).map_or(f64::NAN, |m| m.0),
                    mean_std(&row.model).map_or(f64::NAN, |m| m.0)
                );
                rows.push(row);
            }
        }
        Ok(rows)
    }

    /// Accuracy of `map` on each held-out view (the world shifted by `shift`) against the
    /// noise-free depth, with the constant tolerance and with the forward model's std at the
    /// peak (the reference metric); `each` sees every view's constant-tolerance score.
    fn score(
        &self,
        map: &Map,
        shift: Vector3<f64>,
        mut each: impl FnMut(usize, &ViewScore) -> Result<()>,
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        let params =
            AccuracyParams { sigma: CONSTANT_SIGMA, k: 1.0, peak: PeakRule::Exit, ..AccuracyParams::for_map(map) };
        let scorer = Scorer::new(map, params);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let bar = crate::progress::bar(Some(self.held_out.len()), "scoring");
        for &view in self.held_out {
            let mut frame = self.data.frame(view)?;
            frame.pose.translation.vector += shift;
            let truth = self.data.truth_depth(view)?.context("add-noise writes gt_depth/")?;
            let [constant, modelled] = <[ViewScore; 2]>::try_from(scorer.score_view_each(
                &frame.camera,
                &frame.pose,
                &truth,
                &[None, Some(self.forward)],
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
}

/// The rows' names in report order: the engines', then the voxelised surfaces' if asked for.
fn names(a: &Args) -> impl Iterator<Item = &'static str> + '_ {
    let surfaces = if a.surfaces { &SURFACES[..] } else { &[] };
    a.engines.iter().map(|k| k.name()).chain(surfaces.iter().copied())
}

/// A placement of the grid (the world's shift in voxels per axis) and its rows.
type Placement = ([f64; 3], Vec<Row>);

#[allow(clippy::too_many_arguments)]
fn report(
    a: &Args,
    rows: &[Row],
    placements: &[Placement],
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
         forward model (`noisy/noise.toml`).{} Total time {:.0} s.\n",
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
        if a.surfaces {
            " The rows \"surfaces of ...\" are no engine's: the noise-free surfaces of the keyframes and of every \
             frame, voxelised (occupied where a clean depth point falls, free where only rays pass), what a binary \
             map scores with perfect depth (a soft map can score above it)."
        } else {
            ""
        },
        elapsed
    );
    for (title, pick) in [
        ("Accuracy, constant 5 cm tolerance (the paper's Table II protocol)", 0),
        ("Accuracy, tolerance = the forward model's std at the peak", 1),
    ] {
        let _ = writeln!(r, "## {title}\n");
        engine_header(&mut r, &a.resolutions, &[" m"]);
        for name in names(a) {
            let _ = write!(r, "| {name} |");
            for &res in &a.resolutions {
                let row = rows.iter().find(|x| x.name == name && x.resolution == res);
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
    if !placements.is_empty() {
        let _ = writeln!(
            r,
            "## Where the grid cuts the surfaces\n\nAccuracy (constant 5 cm) with the dataset's placement of the grid and \
             with {} others, the world shifted by a random fraction of a voxel per axis ({}): the placement's mean \
             over the views, then the least and the largest over the placements.\n",
            placements.len(),
            placements
                .iter()
                .map(|(f, _)| format!("({:.2}, {:.2}, {:.2})", f[0], f[1], f[2]))
                .collect::<Vec<_>>()
                .join(", ")
        );
        engine_header(&mut r, &a.resolutions, &[" m: dataset's", "least", "largest"]);
        for name in names(a) {
            let _ = write!(r, "| {name} |");
            for &res in &a.resolutions {
                let mean = |rows: &[Row]| {
                    let row = rows.iter().find(|x| x.name == name && x.resolution == res);
                    row.and_then(|x| mean_std(&x.constant)).map(|m| m.0)
                };
                match mean(rows) {
                    Some(m) => {
                        let others = placements.iter().filter_map(|(_, rows)| mean(rows));
                        let (least, largest) = others.fold((m, m), |(l, h), x| (l.min(x), h.max(x)));
                        let _ = write!(r, " {m:.3} | {least:.3} | {largest:.3} |");
                    }
                    None => r.push_str(" - | - | - |"),
                }
            }
            r.push('\n');
        }
        r.push('\n');
    }
    let _ =
        writeln!(r, "## Builds\n\n| engine | resolution | build s | voxels | map | accuracy image (view {pictured}) |");
    let _ = writeln!(r, "|---|---|---|---|---|---|");
    for x in rows.iter().filter(|x| !SURFACES.contains(&x.name)) {
        let tag = format!("{}_{}cm", x.name, x.resolution * 100.0);
        let _ = writeln!(
            r,
            "| {} | {} m | {:.1} | {} | ![](map_{tag}.png) | ![](accuracy_{tag}_view{pictured}.png) |",
            x.name, x.resolution, x.build_s, x.voxels
        );
    }
    r
}

/// A Markdown table's header with an engine column, then per resolution the columns `cells`
/// (the first after the resolution), and its rule.
fn engine_header(r: &mut String, resolutions: &[f64], cells: &[&str]) {
    r.push_str("| engine |");
    for res in resolutions {
        let _ = write!(r, " {res}{} |", cells[0]);
        for cell in &cells[1..] {
            let _ = write!(r, " {cell} |");
        }
    }
    let _ = writeln!(r, "\n|---|{}", "---|".repeat(resolutions.len() * cells.len()));
}
