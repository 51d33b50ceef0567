//! `mrfmap experiment`: the papers' experiments, regenerated from scratch.
//!
//! - `crm-2d` (`crm2d.rs`): the CRM paper's simulation study on our own 2D world;
//! - `crm-laser` (`laser.rs`): the CRM paper's real-data experiment (sec. 8.3.1) on a CARMEN
//!   laser log;
//! - `mrfmap-table2` (`table2.rs`): the MRFMap paper's Table II on Augmented ICL-NUIM
//!   livingroom1, from its noise-free depth and `add-noise`'s Kinect model;
//! - `crm-icl` (`crm_icl.rs`): the CRM paper's ICL-NUIM experiment (sec. 8.3.2): MAE and
//!   PCC(sigma, |e|) of CRM and log-odds over time against a reference map.
//!
//! The first two compare CRM with log-odds under the paper's ramp inverse sensor model and its
//! 48-setting sweep ([`Method`], [`sweep`]).

mod crm2d;
mod crm_icl;
mod laser;
mod table2;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use mrfmap::source::{Dataset, NoisySummary};

use crate::commands::noise::NoiseArgs;
use mrfmap::frames::RangeScan;
use mrfmap::inference::{CrmEngine, CrmParams, Engine, LogOddsEngine, LogOddsParams, SensorModel};
use mrfmap::map::{Grid, Map, MapVoxel};
use mrfmap::outputs::{VoxelTruth, pearson, roc_auc};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    experiment: Experiment,
}

#[derive(clap::Subcommand)]
enum Experiment {
    /// The CRM paper's 2D simulation study: table, ISM sweep and map pictures.
    #[command(name = "crm-2d")]
    Crm2d(Crm2dArgs),
    /// The CRM paper's real-data experiment on a CARMEN laser log: a reference map from
    /// every beam, CRM and log-odds from a tenth of them, scored against it.
    #[command(name = "crm-laser")]
    CrmLaser(laser::Args),
    /// The MRFMap paper's Table II: noisy depth simulated from a noise-free dataset, keyframes by
    /// its geometric heuristic, MRF, log-odds and CRM at 0.05 / 0.02 / 0.01 m, scored on the other
    /// frames' noise-free depth.
    #[command(name = "mrfmap-table2")]
    MrfmapTable2(table2::Args),
    /// The CRM paper's ICL-NUIM experiment: a reference map from every noise-free frame, then
    /// CRM and log-odds fed the noisy frames one by one; MAE and PCC(sigma, |e|) over time.
    #[command(name = "crm-icl")]
    CrmIcl(crm_icl::Args),
}

#[derive(clap::Args)]
pub struct Crm2dArgs {
    /// Output folder (report.md and PNG pictures).
    #[arg(short, long)]
    output: PathBuf,
    /// CRM particle counts to compare; the first is the CRM the checks and pictures use.
    #[arg(long, value_delimiter = ',', default_value = "101,15", value_parser = particles)]
    particles: Vec<usize>,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Timing repeats (the best is reported).
    #[arg(long, default_value_t = 5)]
    repeat: u32,
}

pub fn run(a: Args) -> Result<()> {
    match a.experiment {
        Experiment::Crm2d(a) => crm2d::crm_2d(a),
        Experiment::CrmLaser(a) => laser::crm_laser(a),
        Experiment::MrfmapTable2(a) => table2::mrfmap_table2(a),
        Experiment::CrmIcl(a) => crm_icl::crm_icl(a),
    }
}

/// The methods of the table.
#[derive(Clone, Copy)]
enum Method {
    Crm(usize),
    LogOdds(SensorModel),
}

impl Method {
    fn label(&self) -> String {
        match self {
            Method::Crm(k) => format!("CRM, {k} particles ({} B/voxel)", 4 * (k + 1)),
            Method::LogOdds(SensorModel::Ramp { q_low, q_high, r_ramp, r_top }) => {
                format!("log-odds, ramp ISM q = {q_low:.2}/{q_high:.2}, r_ramp {r_ramp}, r_top {r_top}")
            }
            Method::LogOdds(m) => format!("log-odds {m:?}"),
        }
    }

    /// Builds the map from `scans`; returns it and the build time in seconds.
    fn run(&self, scans: &[RangeScan], cell: f64) -> Result<(Map, f64)> {
        let mut engine: Box<dyn Engine> = match *self {
            Method::Crm(k) => Box::new(CrmEngine::new(cell, Default::default(), CrmParams { particles: k })?),
            // Clamped only to keep log-odds finite: the paper's log-odds is not OctoMap's.
            Method::LogOdds(model) => Box::new(LogOddsEngine::new(
                cell,
                Default::default(),
                LogOddsParams { model, clamp_min: 1e-3, clamp_max: 1.0 - 1e-3, ..Default::default() },
            )?),
        };
        let t = Instant::now();
        for s in scans {
            engine.integrate_scan(s)?;
        }
        let elapsed = t.elapsed().as_secs_f64();
        Ok((engine.map(), elapsed))
    }

    /// Mean and sigma of a cell nobody observed: the prior.
    fn prior(&self) -> (f64, f64) {
        match *self {
            // Uniform over k particles on [0, 1]: variance (k + 1) / (12 (k - 1)).
            Method::Crm(k) => (0.5, ((k as f64 + 1.0) / (12.0 * (k as f64 - 1.0))).sqrt()),
            Method::LogOdds(_) => (0.5, 0.5),
        }
    }
}

/// The paper's 48 ramp settings: q_high - 0.5 = 0.5 - q_low, r_ramp, r_top.
fn sweep() -> Vec<SensorModel> {
    let mut out = Vec::new();
    for dq in [0.05, 0.2, 0.4] {
        for r_ramp in [0.03, 0.05, 0.1, 0.3] {
            for r_top in [0.03, 0.05, 0.1, 0.3] {
                out.push(SensorModel::Ramp { q_low: 0.5 - dq, q_high: 0.5 + dq, r_ramp, r_top });
            }
        }
    }
    out
}

/// Scores of one map against the reference.
struct Scores {
    label: String,
    mae: f64,
    auc: f64,
    ic_125: f64,
    ic_2: f64,
    beyond_125: f64,
    beyond_2: f64,
    pcc: f64,
    observed: usize,
    seconds: f64,
}

impl Scores {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "label": self.label, "mae": self.mae, "auc": self.auc, "ic_1.25": self.ic_125, "ic_2": self.ic_2,
            "beyond_1.25_sigma": self.beyond_125, "beyond_2_sigma": self.beyond_2, "pcc_sigma_error": self.pcc,
            "observed": self.observed, "seconds": self.seconds,
        })
    }
}

/// `map`'s cells against the reference's known cells (occupied above 1/2); unobserved cells at
/// `prior`.
fn score(label: String, reference: &Grid<MapVoxel>, map: &Map, prior: (f64, f64), seconds: f64) -> Scores {
    let cells: Vec<VoxelTruth> = reference
        .iter()
        .map(|(k, r)| {
            let truth = if r.occupancy > 0.5 { 1.0 } else { 0.0 };
            let (mean, sigma) = map.voxels.get(k).map_or(prior, |v| v.mean_sigma(map.has_variance));
            VoxelTruth { truth, mean, sigma }
        })
        .collect();
    let n = cells.len().max(1) as f64;
    let beyond = |g: f64| cells.iter().filter(|t| t.error().abs() > g * t.sigma).count() as f64 / n;
    let errors: Vec<f64> = cells.iter().map(|t| t.error().abs()).collect();
    let sigmas: Vec<f64> = cells.iter().map(|t| t.sigma).collect();
    let means: Vec<f64> = cells.iter().map(|t| t.mean).collect();
    let labels: Vec<bool> = cells.iter().map(|t| t.truth > 0.5).collect();
    Scores {
        label,
        mae: errors.iter().sum::<f64>() / n,
        auc: roc_auc(&means, &labels),
        ic_125: cells.iter().map(|t| t.inconsistency(1.25)).sum(),
        ic_2: cells.iter().map(|t| t.inconsistency(2.0)).sum(),
        beyond_125: beyond(1.25),
        beyond_2: beyond(2.0),
        pcc: pearson(&sigmas, &errors),
        observed: reference.iter().filter(|(k, _)| map.voxels.get(*k).is_some()).count(),
        seconds,
    }
}

/// `clean` made noisy by `noise` in `dir/noisy` (replaced when it exists: it is the experiment's
/// own output), opened, with the summary of its noise.
fn noisy_copy(clean: &Dataset, dir: &Path, noise: &NoiseArgs) -> Result<(Dataset, NoisySummary)> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let noisy = dir.join("noisy");
    if noisy.exists() {
        std::fs::remove_dir_all(&noisy).with_context(|| format!("replacing {}", noisy.display()))?;
    }
    let summary = noise.write(clean, &noisy)?;
    Ok((Dataset::open(&noisy)?, summary))
}

/// clap parser for a CRM particle count: at least 2.
fn particles(s: &str) -> std::result::Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(k) if (2..=65_535).contains(&k) => Ok(k),
        Ok(k) => Err(format!("a CRM needs 2 to 65535 particles, got {k}")),
        Err(e) => Err(e.to_string()),
    }
}
