//! `mrfmap demo`: the end-to-end tour on the bundled scene.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use mrfmap::inference::{EngineConfig, EngineKind};
use mrfmap::map::{Map, OCCUPIED_THRESHOLD};
use mrfmap::outputs::{PlyOptions, write_ply};
use mrfmap::source::{Dataset, Scene, simulate};

/// The bundled scene, also at `crates/mrfmap-cli/assets/demo_room.toml`.
pub const DEMO_SCENE: &str = include_str!("../../assets/demo_room.toml");
const RESOLUTION: f64 = 0.02;
const SEED: u64 = 1;

#[derive(clap::Args)]
pub struct Args {
    /// Where to write the scene, dataset, maps and PLY files.
    #[arg(default_value = "mrfmap-demo")]
    out_dir: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let out = &a.out_dir;
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

    let dataset = Dataset::open(&data_dir)?;
    let indices: Vec<usize> = (0..dataset.len()).collect();
    println!("engine     time     voxels  occupied  on a true surface  files");
    for &kind in EngineKind::ALL {
        let config = EngineConfig::new(kind, RESOLUTION);
        let t = Instant::now();
        let report = super::build::build_map(&indices, &config, |i| dataset.frame(i))?;
        let elapsed = t.elapsed().as_secs_f64();
        let map_path = out.join(format!("{kind}.mrfmap"));
        let ply_path = out.join(format!("{kind}.ply"));
        report.map.save(&map_path)?;
        write_ply(&report.map, &ply_path, PlyOptions::occupied_only())?;
        println!(
            "{:<9} {:>5.1} s  {:>9}  {:>8}  {:>16.1}%  {}, {}",
            kind.name(),
            elapsed,
            report.map.voxels.len(),
            report.map.occupied_count(),
            100.0 * surface_precision(&report.map, &scene),
            map_path.display(),
            ply_path.display()
        );
    }
    println!("resolution {RESOLUTION} m; open the PLY files in any point viewer (MeshLab, CloudCompare).");
    Ok(())
}

/// Fraction of occupied voxels that overlap a solid of the scene (centre or a corner inside).
fn surface_precision(map: &Map, scene: &Scene) -> f64 {
    let r = map.resolution();
    let (mut occupied, mut touching) = (0usize, 0usize);
    for (key, v) in map.voxels.iter() {
        if v.occupancy <= OCCUPIED_THRESHOLD {
            continue;
        }
        occupied += 1;
        let lo = key.0.map(|i| i as f64 * r);
        let corners = (0..8).map(|c| [0, 1, 2].map(|a| lo[a] + r * ((c >> a) & 1) as f64));
        if scene.contains(key.center(r)) || corners.into_iter().any(|p| scene.contains(p)) {
            touching += 1;
        }
    }
    if occupied == 0 { 0.0 } else { touching as f64 / occupied as f64 }
}
