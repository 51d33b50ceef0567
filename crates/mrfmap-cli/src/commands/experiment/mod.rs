//! `mrfmap experiment`: the papers' experiments, regenerated from scratch.
//!
//! - `crm-2d` (`crm2d.rs`): the CRM paper's simulation study on our own 2D world;
//! - `crm-laser` (`laser.rs`): the CRM paper's real-data experiment (sec. 8.3.1) on a CARMEN
//!   laser log.
//!
//! Both compare CRM with log-odds under the paper's ramp inverse sensor model and its
//! 48-setting sweep ([`Method`], [`sweep`]).

mod crm2d;
mod laser;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use mrfmap::frames::RangeScan;
use mrfmap::inference::{CrmEngine, CrmParams, Engine, LogOddsEngine, LogOddsParams, SensorModel};
use mrfmap::map::Map;

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
}

#[derive(clap::Args)]
pub struct Crm2dArgs {
    /// Output folder (report.md and PNG pictures).
    #[arg(short, long)]
    output: PathBuf,
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
