//! `mrfmap bench`: per-frame integration time at several resolutions, frames preloaded so
//! only the engine is timed. Build with `--release`; the peer script compares it with OctoMap.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use mrfmap::inference::{EngineConfig, EngineKind, new_engine};
use mrfmap::source::Dataset;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder.
    dataset: PathBuf,
    /// Engine to time.
    #[arg(long, default_value = "logodds")]
    engine: String,
    /// Resolutions (metres).
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.02, 0.01])]
    resolutions: Vec<f64>,
    /// Builds per resolution; the fastest is reported (least disturbed by other load).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
}

pub fn run(a: Args) -> Result<()> {
    let kind: EngineKind = a.engine.parse()?;
    let dataset = Dataset::open(&a.dataset)?;
    let frames = (0..dataset.len()).map(|i| dataset.frame(i)).collect::<mrfmap::Result<Vec<_>>>()?;
    println!(
        "# {} frames of {}, engine {kind}, {} threads, best of {}",
        frames.len(),
        a.dataset.display(),
        rayon::current_num_threads(),
        a.repeat
    );
    println!("resolution\tms_per_frame\toccupied\tvoxels\tmemory_mib");
    for &resolution in &a.resolutions {
        let mut best = f64::INFINITY;
        let mut last = None;
        for _ in 0..a.repeat.max(1) {
            let mut engine = new_engine(&EngineConfig::new(kind, resolution))?;
            let t = Instant::now();
            for f in &frames {
                engine.integrate(f)?;
            }
            engine.finish()?;
            best = best.min(t.elapsed().as_secs_f64());
            last = Some(engine.map());
        }
        let map = last.expect("at least one run");
        println!(
            "{resolution}\t{:.2}\t{}\t{}\t{:.1}",
            best * 1e3 / frames.len() as f64,
            map.occupied_count(),
            map.voxels.len(),
            map.voxels.memory_bytes() as f64 / (1 << 20) as f64
        );
    }
    Ok(())
}
