//! `crm-2d`: the CRM paper's simulation study (secs. 8.1-8.2, the table of its Fig. 7 and the
//! pictures of its Fig. 8) on our own 2 m x 2 m world (`GridWorld::crm_paper`): 23 waypoints,
//! a 60-beam 360-degree range sensor of 1 m, Gaussian range noise of 0.25 to 3 cells. CRM
//! against log-odds with the paper's ramp inverse sensor model and its 48-setting sweep.
//! Metrics over all 1600 cells, observed or not (unobserved cells keep their prior).

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;
use mrfmap::frames::RangeScan;
use mrfmap::inference::SensorModel;
use mrfmap::outputs::pictures::{viridis, write_text};
use mrfmap::outputs::{Canvas, TruthMetrics, VoxelTruth, grid_world_truths, metrics_of};
use mrfmap::random::Rng;
use mrfmap::source::GridWorld;

use super::{Crm2dArgs, Method, sweep};

/// Noise levels in cells (the paper's 0.25 s ... 3 s).
const NOISE_CELLS: [f64; 5] = [0.25, 0.5, 1.0, 2.0, 3.0];
const BEAMS: usize = 60;
const MAX_RANGE: f64 = 1.0;

struct Row {
    method: Method,
    metrics: TruthMetrics,
    /// Cells the method observed (allocated in its map).
    observed: usize,
    /// Metrics over the observed cells only.
    observed_metrics: TruthMetrics,
    seconds: f64,
    cells: Vec<VoxelTruth>,
}

fn evaluate(method: Method, world: &GridWorld, scans: &[RangeScan], repeat: u32) -> Result<Row> {
    let mut best = f64::INFINITY;
    let mut map = None;
    for _ in 0..repeat.max(1) {
        let (m, t) = method.run(scans, world.cell)?;
        best = best.min(t);
        map = Some(m);
    }
    let map = map.expect("at least one run");
    let cells = grid_world_truths(world, &map, method.prior());
    let seen: Vec<VoxelTruth> = (0..world.height)
        .flat_map(|y| (0..world.width).map(move |x| (x, y)))
        .zip(&cells)
        .filter(|((x, y), _)| map.voxels.get(world.key(*x, *y)).is_some())
        .map(|(_, t)| *t)
        .collect();
    Ok(Row {
        method,
        metrics: metrics_of(&cells),
        observed: seen.len(),
        observed_metrics: metrics_of(&seen),
        seconds: best,
        cells,
    })
}

pub(super) fn crm_2d(a: Crm2dArgs) -> Result<()> {
    std::fs::create_dir_all(&a.output)?;
    let (world, waypoints) = GridWorld::crm_paper();
    let cell = world.cell;
    let mut report = String::from("# CRM paper, simulation study (secs. 8.1-8.2) on our 2D world\n\n");
    let _ = writeln!(
        report,
        "{} x {} cells of {cell} m, {} waypoints, {BEAMS} beams over 360 degrees, range {MAX_RANGE} m, \
         seed {}. Metrics over all {} cells (unobserved cells at their prior). Times: all {} scans, \
         best of {}, this machine.\n",
        world.width,
        world.height,
        waypoints.len(),
        a.seed,
        world.width * world.height,
        waypoints.len(),
        a.repeat
    );
    let paper = Method::LogOdds(SensorModel::CRM_PAPER);
    let mut table: Vec<(String, Vec<Row>)> = Vec::new();
    let mut sweep_rows: Vec<Vec<Row>> = Vec::new();
    for (level, &n) in NOISE_CELLS.iter().enumerate() {
        let std = n * cell;
        let mut rng = Rng::stream(a.seed, level as u64, 0);
        let scans: Vec<RangeScan> = waypoints
            .iter()
            .enumerate()
            .map(|(i, p)| world.scan(i, *p, BEAMS, MAX_RANGE, std, &mut rng))
            .collect::<mrfmap::Result<_>>()?;
        let mut rows = Vec::new();
        for &k in &a.particles {
            rows.push(evaluate(Method::Crm(k), &world, &scans, a.repeat)?);
        }
        rows.push(evaluate(paper, &world, &scans, a.repeat)?);
        let swept: Vec<Row> =
            sweep().into_iter().map(|m| evaluate(Method::LogOdds(m), &world, &scans, 1)).collect::<Result<_>>()?;
        if level == 0 {
            figure(&world, &waypoints, &rows[0], &rows[a.particles.len()], &a.output.join("crm2d_maps.png"))?;
        }
        table.push((format!("{n} s"), rows));
        sweep_rows.push(swept);
        tracing::info!("noise {n} cells done");
    }

    // The Fig. 7 table: one block per metric, one row per method, one column per noise level.
    let _ = writeln!(report, "## Table (the paper's Fig. 7)\n");
    let _ = write!(report, "| metric | method |");
    for (label, _) in &table {
        let _ = write!(report, " {label} |");
    }
    let _ = writeln!(report, "\n|---|---|{}", "---|".repeat(table.len()));
    type Metric = (&'static str, fn(&Row) -> f64, usize);
    let metrics: [Metric; 8] = [
        ("observed cells", |r| r.observed as f64, 0),
        ("MAE", |r| r.metrics.mae, 3),
        ("MAE, observed cells", |r| r.observed_metrics.mae, 3),
        ("I_c (gamma 0.5), observed cells", |r| r.observed_metrics.ic_half, 1),
        ("AUC", |r| r.metrics.auc, 3),
        ("I_c (gamma 0.5)", |r| r.metrics.ic_half, 1),
        ("PCC(sigma, abs error)", |r| r.metrics.pearson_sigma_error, 3),
        ("t [ms]", |r| r.seconds * 1e3, 2),
    ];
    for (name, value, digits) in metrics {
        for m in 0..table[0].1.len() {
            let _ = write!(report, "| {name} | {} |", table[0].1[m].method.label());
            for (_, rows) in &table {
                let _ = write!(report, " {:.digits$} |", value(&rows[m]));
            }
            let _ = writeln!(report);
        }
        // The best of the sweep by MAE, per noise level.
        let _ = write!(report, "| {name} | log-odds, best of the 48-setting sweep by MAE |");
        for swept in &sweep_rows {
            let best = swept.iter().min_by(|x, y| x.metrics.mae.total_cmp(&y.metrics.mae)).expect("48 rows");
            let _ = write!(report, " {:.digits$} |", value(best));
        }
        let _ = writeln!(report);
    }

    // The sweep (the paper's Fig. 10) at 1 cell of noise.
    let one = NOISE_CELLS.iter().position(|&n| n == 1.0).expect("1 s is a level");
    let crm = &table[one].1[0];
    let swept = &sweep_rows[one];
    let beaten = swept.iter().filter(|r| crm.metrics.mae < r.metrics.mae).count();
    let _ = writeln!(
        report,
        "\n## ISM sweep at 1 s noise (the paper's Fig. 10)\n\nCRM ({} particles): MAE {:.3}, I_c {:.1}. \
         CRM has the lower MAE than {beaten} of the 48 log-odds settings.\n\n\
         | q_high - 0.5 | r_ramp | r_top | MAE | AUC | I_c (gamma 0.5) | PCC | MAE gain of CRM |\n|---|---|---|---|---|---|---|---|",
        a.particles[0], crm.metrics.mae, crm.metrics.ic_half
    );
    for r in swept {
        if let Method::LogOdds(SensorModel::Ramp { q_high, r_ramp, r_top, .. }) = r.method {
            let _ = writeln!(
                report,
                "| {:.2} | {r_ramp} | {r_top} | {:.3} | {:.3} | {:.1} | {:.3} | {:+.1}% |",
                q_high - 0.5,
                r.metrics.mae,
                r.metrics.auc,
                r.metrics.ic_half,
                r.metrics.pearson_sigma_error,
                100.0 * (r.metrics.mae - crm.metrics.mae) / r.metrics.mae
            );
        }
    }
    let _ = writeln!(
        report,
        "\n`crm2d_maps.png`: at 0.25 s noise, columns CRM ({} particles) and log-odds (paper ISM); \
         rows truth with waypoints, mean, sigma (0 to 0.5), |error|, I_c with gamma 0.5 (the paper's Fig. 8).",
        a.particles[0]
    );
    let path = a.output.join("report.md");
    write_text(&path, &report)?;
    print!("{report}");
    tracing::info!("wrote {}", path.display());
    Ok(())
}

/// The paper's Fig. 8 for two methods: truth, mean, sigma, |error| and I_c per cell.
fn figure(world: &GridWorld, waypoints: &[[f64; 2]], a: &Row, b: &Row, path: &Path) -> Result<()> {
    let px = 6i64;
    let (w, h) = (world.width as i64 * px, world.height as i64 * px);
    let (left, top, gap) = (110i64, 40i64, 20i64);
    let mut c = Canvas::new((left + 2 * (w + gap)) as u32, (top + 5 * (h + gap)) as u32);
    let black = [0, 0, 0];
    c.text(left, 12, "CRM", 2, black);
    c.text(left + w + gap, 12, "LOG-ODDS", 2, black);
    type Value = (&'static str, fn(&VoxelTruth) -> f64);
    let rows: [Value; 5] = [
        ("TRUTH", |t| t.truth),
        ("MEAN", |t| t.mean),
        ("SIGMA", |t| 2.0 * t.sigma),
        ("ABS ERROR", |t| t.error().abs()),
        ("I_C 0.5", |t| t.inconsistency(0.5)),
    ];
    for (ri, (label, value)) in rows.iter().enumerate() {
        let y0 = top + ri as i64 * (h + gap);
        c.text(8, y0 + h / 2, label, 1, black);
        for (ci, row) in [a, b].into_iter().enumerate() {
            let x0 = left + ci as i64 * (w + gap);
            for y in 0..world.height {
                for x in 0..world.width {
                    let t = &row.cells[y * world.width + x];
                    let colour = if ri == 0 {
                        if t.truth > 0.5 { [60, 60, 60] } else { [255, 255, 255] }
                    } else {
                        viridis(value(t))
                    };
                    // World y up, image rows down.
                    let (cx, cy) = (x0 + x as i64 * px, y0 + (world.height - 1 - y) as i64 * px);
                    c.fill(cx, cy, cx + px, cy + px, colour);
                }
            }
            if ri == 0 {
                for p in waypoints {
                    let (cx, cy) =
                        (x0 + (p[0] / world.cell * px as f64) as i64, y0 + h - (p[1] / world.cell * px as f64) as i64);
                    c.fill(cx - 2, cy - 2, cx + 3, cy + 3, [220, 30, 30]);
                }
            }
        }
    }
    c.save(path)?;
    Ok(())
}
