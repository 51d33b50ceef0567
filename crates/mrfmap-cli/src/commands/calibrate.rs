//! `mrfmap calibrate`: learn a per-patch noise model from measured and true depth images.

use std::collections::BTreeSet;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use mrfmap::atomic_file::write_atomic;
use mrfmap::frames::{CalibrationOptions, Calibrator, Camera, IMPLAUSIBLE, NoiseModel, PatchFit};
use mrfmap::source::read_depth_png;

#[derive(clap::Args)]
pub struct Args {
    /// Folder of measured 16-bit depth PNGs (e.g. a dataset's `depth/`).
    #[arg(long)]
    measured: PathBuf,
    /// Folder of true depth PNGs with the same file names (e.g. `gt_depth/`).
    #[arg(long)]
    truth: PathBuf,
    /// Output noise model (TOML, the `noise.toml` format).
    #[arg(short, long)]
    output: PathBuf,
    /// Depth units per metre in the PNGs (default: `depth_scale` of the `camera.toml` next to
    /// the measured folder).
    #[arg(long, value_parser = super::positive)]
    depth_scale: Option<f64>,
    /// Patch side in pixels.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..))]
    patch: u32,
    /// Polynomial degree (0-2).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u8).range(0..=2))]
    degree: u8,
    /// Ignore true depths below this (metres).
    #[arg(long, default_value_t = 0.2)]
    min_depth: f64,
    /// Ignore true depths at or above this (metres).
    #[arg(long, default_value_t = 10.0)]
    max_depth: f64,
    /// Depth bin width (metres).
    #[arg(long, default_value_t = 0.1, value_parser = super::positive)]
    bin: f64,
    /// Residuals a bin needs to enter a fit.
    #[arg(long, default_value_t = 30)]
    min_samples: usize,
    /// Write only the aggregate model (no `[patches]` table).
    #[arg(long)]
    aggregate_only: bool,
}

/// PNG file names in `dir`, sorted.
fn png_names(dir: &Path) -> Result<BTreeSet<String>> {
    let entries = std::fs::read_dir(dir).with_context(|| format!("{}: cannot list folder", dir.display()))?;
    let mut names = BTreeSet::new();
    for e in entries {
        let e = e.with_context(|| format!("{}: cannot list folder", dir.display()))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if name.to_ascii_lowercase().ends_with(".png") {
            names.insert(name);
        }
    }
    Ok(names)
}

fn depth_scale(a: &Args) -> Result<f64> {
    if let Some(s) = a.depth_scale {
        return Ok(s);
    }
    let cam = a.measured.parent().unwrap_or(Path::new(".")).join("camera.toml");
    if !cam.exists() {
        bail!("{}: not found; give --depth-scale (depth units per metre in the PNGs)", cam.display());
    }
    Ok(Camera::load(&cam)?.depth_scale)
}

pub fn run(a: Args) -> Result<()> {
    let options = CalibrationOptions {
        patch: a.patch,
        degree: a.degree as usize,
        min_depth: a.min_depth,
        max_depth: a.max_depth,
        bin: a.bin,
        min_samples: a.min_samples,
    };
    let mut calibrator = Calibrator::new(options).map_err(anyhow::Error::msg)?;
    let scale = depth_scale(&a)?;
    let measured = png_names(&a.measured)?;
    let truth = png_names(&a.truth)?;
    let pairs: Vec<&String> = measured.intersection(&truth).collect();
    for (dir, mine, theirs, other) in
        [(&a.measured, &measured, &truth, &a.truth), (&a.truth, &truth, &measured, &a.measured)]
    {
        let missing: Vec<&String> = mine.difference(theirs).collect();
        if !missing.is_empty() {
            tracing::warn!(
                "{} image(s) in {} have no partner in {} and are skipped (first: {})",
                missing.len(),
                dir.display(),
                other.display(),
                missing[0]
            );
        }
    }
    if pairs.is_empty() {
        bail!("no PNG file names appear in both {} and {}", a.measured.display(), a.truth.display());
    }
    let bar = crate::progress::bar(Some(pairs.len()), "calibrate");
    for name in &pairs {
        let m_path = a.measured.join(name);
        let t_path = a.truth.join(name);
        let m = read_depth_png(&m_path, scale, None)?;
        let t = read_depth_png(&t_path, scale, None)?;
        calibrator.add(&m, &t).map_err(|e| anyhow::anyhow!("{}: {e}", m_path.display()))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let result = calibrator.finish().map_err(anyhow::Error::msg)?;
    let patches = result.model.patches.as_ref().expect("calibration always fits patches");
    let fallback: Vec<String> = result
        .fits
        .iter()
        .enumerate()
        .filter(|&(_, &f)| f == PatchFit::Aggregate)
        .map(|(i, _)| format!("({}, {})", i as u32 / patches.cols, i as u32 % patches.cols))
        .collect();
    let mut model = result.model.clone();
    if a.aggregate_only {
        model = NoiseModel::aggregate(model.bias, model.std);
    }
    write_atomic(&a.output, |w| w.write_all(model.to_toml().as_bytes()))?;

    println!(
        "{}: {} image pairs, {} residuals, {:.2}% rejected as outliers",
        a.output.display(),
        result.images,
        result.samples,
        100.0 * result.outliers as f64 / result.samples.max(1) as f64
    );
    let count = |kind: PatchFit| result.fits.iter().filter(|&&f| f == kind).count();
    if count(PatchFit::Implausible) > 0 {
        tracing::warn!(
            "{} patches' own polynomials were implausible in the calibrated depths (std not positive or over {}x \
             the aggregate's, or bias that many aggregate stds off; typically a patch that saw a narrow range of \
             depths): they use the aggregate adjusted to their bins instead",
            count(PatchFit::Implausible),
            IMPLAUSIBLE
        );
    }
    println!(
        "patches: {} x {} of {} px, {} fitted, {} adjusted (aggregate shifted and scaled to their few depth bins), \
         {} adjusted as their own fit was implausible, {} without data use the aggregate{}",
        patches.rows,
        patches.cols,
        patches.size,
        count(PatchFit::Fitted),
        count(PatchFit::Adjusted),
        count(PatchFit::Implausible),
        fallback.len(),
        if fallback.is_empty() {
            String::new()
        } else {
            format!(
                " (row, col): {}{}",
                fallback[..fallback.len().min(12)].join(" "),
                if fallback.len() > 12 { " ..." } else { "" }
            )
        }
    );
    println!("aggregate (median over fitted patches):");
    println!("  bias = {:?}\n  std  = {:?}", model.bias.0, model.std.0);
    for z in [1.0, 2.0, 3.0] {
        println!("  at {z:.1} m: bias {:+.1} mm, std {:.1} mm", model.bias.eval(z) * 1e3, model.std.eval(z) * 1e3);
    }
    Ok(())
}
