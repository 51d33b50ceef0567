//! `mrfmap simulate`: scene file to dataset.

use std::path::PathBuf;

use anyhow::Result;
use mrfmap::source::{Scene, simulate};

#[derive(clap::Args)]
pub struct Args {
    /// Scene file (TOML; see README "Scene files").
    scene: PathBuf,
    /// Output dataset folder.
    out_dir: PathBuf,
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

pub fn run(a: Args) -> Result<()> {
    let scene = Scene::load(&a.scene)?;
    let s = simulate(&scene, &a.out_dir, a.seed)?;
    println!("{}: {} frames, {} valid pixels", a.out_dir.display(), s.frames, s.valid_pixels);
    Ok(())
}
