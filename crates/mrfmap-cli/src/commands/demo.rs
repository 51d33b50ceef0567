//! `mrfmap demo`: the end-to-end tour on the bundled scene.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use super::views::Target;
use anyhow::{Context, Result};
use mrfmap::inference::{EngineConfig, EngineKind};
use mrfmap::outputs::{AccuracyParams, PeakRule, PlyOptions, Scorer, truth_metrics, write_ply};
use mrfmap::source::{Dataset, Scene, simulate};

/// The bundled scene, also at `crates/mrfmap-cli/assets/demo_room.toml`.
pub const DEMO_SCENE: &str = include_str!("../../assets/demo_room.toml");
const RESOLUTION: f64 = 0.02;
const SEED: u64 = 1;
/// The view left out of every map and scored.
const HELD_OUT: usize = 6;

#[derive(clap::Args)]
pub struct Args {
    /// Where to write the scene, dataset, maps and PLY files.
    #[arg(default_value = "mrfmap-demo")]
    out_dir: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let out = &a.out_dir;
    if out.exists() && !out.is_dir() {
        anyhow::bail!("{}: exists and is not a folder; give the demo a folder to write to", out.display());
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let scene_path = out.join("scene.toml");
    mrfmap::atomic_file::write_atomic(&scene_path, |w| w.write_all(DEMO_SCENE.as_bytes()))?;
    let scene = Scene::load(&scene_path)?;

    let t = Instant::now();
    let data_dir = out.join("dataset");
    let sim = simulate(&scene, &data_dir, SEED)?;
    println!(
        "simulated {} views of {} ({:.1} s): {}",
        sim.frames,
        scene_path.display(),
        t.elapsed().as_secs_f64(),
        data_dir.display()
    );

    let dataset = super::views::Views::Dataset(Dataset::open(&data_dir)?);
    // One view is held out of every map and scored, as the MRFMap paper's tables do.
    let held_out = HELD_OUT.min(dataset.len() - 1);
    let indices: Vec<usize> = (0..dataset.len()).filter(|&i| i != held_out).collect();
    println!("maps from {} views at {RESOLUTION} m; view {held_out} is held out and scored", indices.len());
    println!("engine     time   occupied  held-out accuracy    MAE     AUC  precision  recall  files");
    for &kind in EngineKind::ALL {
        let config = EngineConfig::new(kind, RESOLUTION);
        let t = Instant::now();
        let report = super::options::build_map(&indices, &config, |i| dataset.frame(i))?;
        let elapsed = t.elapsed().as_secs_f64();
        let map_path = out.join(format!("{kind}.mrfmap"));
        let ply_path = out.join(format!("{kind}.ply"));
        report.map.save(&map_path)?;
        write_ply(&report.map, &ply_path, PlyOptions::occupied_only())?;
        let params = AccuracyParams { peak: PeakRule::Exit, ..AccuracyParams::for_map(&report.map) };
        let accuracy =
            super::eval::score(&Scorer::new(&report.map, params), &dataset, held_out, Target::Truth)?.accuracy();
        let truth = truth_metrics(&report.map, &scene);
        println!(
            "{:<9} {:>5.1} s  {:>9}  {:>17}  {:>5.3}  {:>6.3}  {:>9.3}  {:>6.3}  {}, {}",
            kind.name(),
            elapsed,
            report.map.occupied_count(),
            accuracy.map_or("-".into(), |a| format!("{a:.3}")),
            truth.mae,
            truth.auc,
            truth.precision,
            truth.recall,
            map_path.display(),
            ply_path.display()
        );
    }
    println!(
        "occupied: voxels above 0.5. held-out accuracy: share of the held-out view's pixels whose \
         most likely surface in the map lies within 5 cm of the true depth (`mrfmap eval --metric \
         reference`). MAE: mean |true occupancy - map occupancy| over the map's voxels (0 is \
         perfect). AUC: how well occupancy ranks occupied above free voxels (1 is perfect, 0.5 \
         is chance). precision: share of the occupied voxels that are at least half solid in the \
         scene; recall: share of the map's at least half solid voxels that are occupied (for a \
         planner thresholding at 0.5, 1 - precision is space blocked for nothing, 1 - recall \
         obstacles missed). Open the PLY files in any point viewer (MeshLab, CloudCompare)."
    );
    Ok(())
}
