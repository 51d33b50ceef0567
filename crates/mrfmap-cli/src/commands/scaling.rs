//! `mrfmap scaling`: how time and memory grow with resolution, image size and (MRF) the
//! number of keyframes, as tables (`report.md`) and PNG plots. Release builds only make sense.
//!
//! Memory is the process's peak resident set during each build, measured by resetting the
//! peak (`/proc/self/clear_refs`) before it; the preloaded frames are in every figure (the
//! baseline row says how much they take).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use mrfmap::frames::{Camera, DepthImage, Frame};
use mrfmap::inference::{
    CrmParams, DEFAULT_MAX_SWEEPS, DEFAULT_TOLERANCE, Engine, EngineConfig, EngineKind, MrfEngine, MrfParams,
    new_engine,
};
use mrfmap::outputs::pictures::write_text;
use mrfmap::outputs::{Rgb, Series, line_plot};
use mrfmap::source::{Dataset, Scene};

use super::bench::BASE_SWEEPS;
use super::demo::DEMO_SCENE;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset for the resolution and image-size curves.
    dataset: PathBuf,
    /// Output folder.
    #[arg(short, long)]
    output: PathBuf,
    /// Resolutions (metres).
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.04, 0.03, 0.02, 0.015, 0.01])]
    resolutions: Vec<f64>,
    /// Keyframe counts for the MRF curves (views of the demo room at 0.05 m).
    #[arg(long, value_delimiter = ',', default_values_t = [1, 5, 10, 20, 40, 60])]
    keyframes: Vec<usize>,
    /// CRM particles.
    #[arg(long, default_value_t = 15)]
    particles: usize,
    /// Which curves to measure (default: all three).
    #[arg(long, value_delimiter = ',', value_enum, default_values_t = [Curve::Resolution, Curve::ImageSize, Curve::Keyframes])]
    curves: Vec<Curve>,
}

/// The curves `mrfmap scaling` can draw.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Curve {
    /// Time and memory of every engine against resolution.
    Resolution,
    /// Time of every engine against image size.
    ImageSize,
    /// MRF time against the number of keyframes.
    Keyframes,
}

const ENGINES: [(EngineKind, Rgb); 3] =
    [(EngineKind::LogOdds, [31, 119, 180]), (EngineKind::Mrf, [214, 39, 40]), (EngineKind::Crm, [44, 160, 44])];

/// Peak resident memory (MiB) since the last reset, and a reset for the next measurement.
fn peak_mib_and_reset() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kb = status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or(f64::NAN);
    let _ = std::fs::write("/proc/self/clear_refs", "5");
    kb / 1024.0
}

/// Seconds per frame and peak MiB of a full build (integrate every frame, then finish).
fn time_build(kind: EngineKind, resolution: f64, particles: usize, frames: &[Frame]) -> Result<(f64, f64)> {
    peak_mib_and_reset();
    let config = EngineConfig { crm: CrmParams { particles }, ..EngineConfig::new(kind, resolution) };
    let mut engine = new_engine(&config)?;
    let t = Instant::now();
    for f in frames {
        engine.integrate(f)?;
    }
    engine.finish()?;
    let secs = t.elapsed().as_secs_f64() / frames.len() as f64;
    let mib = peak_mib_and_reset();
    drop(engine);
    Ok((secs, mib))
}

/// `frame` with every `stride`-th pixel in each direction (the camera scaled to match).
fn subsample(frame: &Frame, stride: u32) -> Result<Frame> {
    let c = &frame.camera;
    let (w, h) = (c.width / stride, c.height / stride);
    let s = stride as f64;
    // Pixel (u, v) of the small image is pixel (s u, s v) of the full one.
    let camera = Camera::new(c.fx / s, c.fy / s, c.cx / s, c.cy / s, w, h, c.depth_scale)?;
    let mut depth = DepthImage::new(w, h);
    for v in 0..h {
        for u in 0..w {
            if let Some(z) = frame.depth.get(u * stride, v * stride) {
                depth.set(u, v, z);
            }
        }
    }
    // The per-patch noise table is tied to the full image; use its aggregate.
    let noise = frame.noise.as_ref().map(|n| Arc::new(mrfmap::frames::NoiseModel::aggregate(n.bias, n.std)));
    Ok(Frame { depth, camera, noise, ..frame.clone() })
}

/// A line plot of `series` on a log10 y axis, saved to `path`.
fn plot(path: &std::path::Path, title: &str, x_label: &str, y_label: &str, series: &[Series]) -> Result<()> {
    line_plot(title, x_label, y_label, series, true).save(path)?;
    Ok(())
}

pub fn run(a: Args) -> Result<()> {
    std::fs::create_dir_all(&a.output)?;
    let dataset = Dataset::open(&a.dataset)?;
    // The keyframe curve renders its own views of the demo room.
    let frames = if a.curves.iter().any(|c| *c != Curve::Keyframes) {
        (0..dataset.len()).map(|i| dataset.frame(i)).collect::<mrfmap::Result<Vec<_>>>()?
    } else {
        Vec::new()
    };
    let baseline = peak_mib_and_reset();
    let mut report = format!(
        "# Scaling on {} ({} frames of {}x{}), {} threads\n\nCommand: `mrfmap scaling {} -o {}`. \
         Baseline (frames loaded): {baseline:.0} MiB peak resident. CRM with {} particles.\n",
        a.dataset.display(),
        dataset.len(),
        dataset.camera().width,
        dataset.camera().height,
        rayon::current_num_threads(),
        a.dataset.display(),
        a.output.display(),
        a.particles
    );

    if a.curves.contains(&Curve::Resolution) {
        resolution_curves(&a, &frames, &mut report)?;
    }
    if a.curves.contains(&Curve::ImageSize) {
        image_size_curves(&a, &frames, &mut report)?;
    }
    if a.curves.contains(&Curve::Keyframes) {
        keyframe_curves(&a, &mut report)?;
    }
    let plots: Vec<&str> = [
        (Curve::Resolution, "`time_vs_resolution.png`, `memory_vs_resolution.png`"),
        (Curve::ImageSize, "`time_vs_image_size.png`"),
        (Curve::Keyframes, "`mrf_vs_keyframes.png`"),
    ]
    .iter()
    .filter(|(c, _)| a.curves.contains(c))
    .map(|p| p.1)
    .collect();
    let _ = writeln!(report, "\nPlots: {}.", plots.join(", "));
    write_text(&a.output.join("report.md"), &report)?;
    print!("{report}");
    Ok(())
}

/// Time and peak memory of every engine against resolution.
fn resolution_curves(a: &Args, frames: &[Frame], report: &mut String) -> Result<()> {
    let _ = writeln!(
        report,
        "\n## Time and peak memory vs resolution\n\n| engine | res (m) | s/frame | peak MiB |\n|---|---|---|---|"
    );
    let (mut time_series, mut mem_series) = (Vec::new(), Vec::new());
    for (kind, colour) in ENGINES {
        let (mut t, mut m) = (Vec::new(), Vec::new());
        for &r in &a.resolutions {
            let (secs, mib) = time_build(kind, r, a.particles, frames)?;
            let _ = writeln!(report, "| {kind} | {r} | {secs:.3} | {mib:.0} |");
            tracing::info!("{kind} {r}: {secs:.3} s/frame, {mib:.0} MiB");
            t.push((r * 100.0, secs));
            m.push((r * 100.0, mib));
        }
        time_series.push((kind.name().to_string(), colour, t));
        mem_series.push((kind.name().to_string(), colour, m));
    }
    plot(
        &a.output.join("time_vs_resolution.png"),
        "TIME PER FRAME VS RESOLUTION",
        "VOXEL SIZE (CM)",
        "LOG10 S/FRAME",
        &time_series,
    )?;
    plot(
        &a.output.join("memory_vs_resolution.png"),
        "PEAK MEMORY VS RESOLUTION",
        "VOXEL SIZE (CM)",
        "LOG10 MIB",
        &mem_series,
    )?;

    Ok(())
}

/// Time of every engine against image size (every engine at 0.02 m).
fn image_size_curves(a: &Args, frames: &[Frame], report: &mut String) -> Result<()> {
    let _ = writeln!(report, "\n## Time vs image size (0.02 m)\n\n| engine | image | s/frame |\n|---|---|---|");
    let mut image_series = Vec::new();
    for (kind, colour) in ENGINES {
        let mut t = Vec::new();
        for stride in [8u32, 4, 2, 1] {
            let small: Vec<Frame> = frames.iter().map(|f| subsample(f, stride)).collect::<Result<_>>()?;
            let (secs, _) = time_build(kind, 0.02, a.particles, &small)?;
            let pixels = small[0].camera.pixel_count();
            let _ = writeln!(report, "| {kind} | {}x{} | {secs:.3} |", small[0].camera.width, small[0].camera.height);
            t.push((pixels as f64 / 1000.0, secs));
        }
        image_series.push((kind.name().to_string(), colour, t));
    }
    plot(
        &a.output.join("time_vs_image_size.png"),
        "TIME PER FRAME VS IMAGE SIZE (0.02 M)",
        "THOUSANDS OF PIXELS",
        "LOG10 S/FRAME",
        &image_series,
    )?;

    Ok(())
}

/// MRF time against the number of keyframes, on views of the demo room on a circle.
fn keyframe_curves(a: &Args, report: &mut String) -> Result<()> {
    let scene = Scene::from_toml(DEMO_SCENE, "demo_room.toml".as_ref()).context("demo scene")?;
    if a.keyframes.contains(&0) {
        anyhow::bail!("--keyframes: every count must be at least 1");
    }
    let n_max = a.keyframes.iter().copied().max().unwrap_or(1);
    // Rendered views (the orbit and the far copies) and the engines' copies of them, plus
    // about 4 MiB of tiles per keyframe in each of the two engines (2.8 MiB measured at 0.05 m).
    let pixels = scene.camera.pixel_count() as f64;
    let estimate = n_max as f64 * (4.0 * pixels * 4.0 + 8.0 * 1024.0 * 1024.0);
    mrfmap::limits::check_memory("the keyframe curve", estimate, "use fewer --keyframes")?;
    let orbit = |k: usize| {
        let angle = std::f64::consts::TAU * k as f64 / n_max as f64;
        let eye = [2.0 + 1.2 * angle.cos(), 2.0 + 1.2 * angle.sin(), 1.4];
        mrfmap::frames::look_at(eye.into(), [2.0, 2.0, 0.6].into()).expect("valid view")
    };
    let render = |k: usize, offset: f64| {
        let mut frame = scene.frame(k, &orbit(k), Some(7));
        frame.pose.translation.vector.x += offset; // far-away copies do not overlap
        frame
    };
    let room: Vec<Frame> = (0..=n_max).map(|k| render(k, 0.0)).collect();
    let _ = writeln!(
        report,
        "\n## MRF vs number of keyframes (demo room, 0.05 m)\n\nFull build: add N keyframes and \
         infer with the default schedule (3 sweeps; timed). The map is then \
         inferred to convergence (at most {BASE_SWEEPS} sweeps, not timed; \"converged\" says \
         whether it got there), as `mrfmap bench --incremental` does. Add one, overlapping: add \
         a view of the same room to the N inferred keyframes and infer again with the \
         change-driven schedule (tolerance 0.001, at most 10 sweeps; every keyframe overlaps it). Add one, apart: the N keyframes are copies 100 m apart from each other \
         (none overlaps the new one except the first).\n\n\
         | N | full build s | converged | add one (overlapping) s | add one (apart) s | tiles traced (overlapping) | tiles traced (apart) |\n|---|---|---|---|---|---|---|"
    );
    let (mut full, mut add_near, mut add_far) = (Vec::new(), Vec::new(), Vec::new());
    for &n in &a.keyframes {
        let params = MrfParams::default();
        let tolerance = params.tolerance.unwrap_or(DEFAULT_TOLERANCE);
        let build = |frames: &[Frame]| -> Result<(MrfEngine, f64, bool)> {
            let mut e = MrfEngine::new(0.05, Default::default(), params)?;
            let t = Instant::now();
            for f in frames {
                e.add_keyframe(f.clone())?;
            }
            e.finish()?;
            let secs = t.elapsed().as_secs_f64();
            let converged = e.run_until(tolerance, BASE_SWEEPS).converged;
            Ok((e, secs, converged))
        };
        let add = |e: &mut MrfEngine| -> Result<(f64, usize)> {
            let t = Instant::now();
            e.add_keyframe(room[n].clone())?;
            let r = e.run_until(tolerance, DEFAULT_MAX_SWEEPS);
            Ok((t.elapsed().as_secs_f64(), r.tiles))
        };
        let (mut near, full_secs, converged) = build(&room[..n])?;
        let (near_secs, near_tiles) = add(&mut near)?;
        let apart: Vec<Frame> = (0..n).map(|k| render(k, 100.0 * k as f64)).collect();
        let (mut far, _, _) = build(&apart)?;
        let (far_secs, far_tiles) = add(&mut far)?;
        let _ = writeln!(
            report,
            "| {n} | {full_secs:.2} | {converged} | {near_secs:.2} | {far_secs:.2} | {near_tiles} | {far_tiles} |"
        );
        tracing::info!(
            "mrf {n} keyframes: build {full_secs:.2} s, add near {near_secs:.2} s, add apart {far_secs:.2} s"
        );
        full.push((n as f64, full_secs));
        add_near.push((n as f64, near_secs));
        add_far.push((n as f64, far_secs));
    }
    plot(
        &a.output.join("mrf_vs_keyframes.png"),
        "MRF: TIME VS KEYFRAMES (0.05 M)",
        "KEYFRAMES",
        "LOG10 S",
        &[
            ("FULL BUILD".into(), [0, 0, 0], full),
            ("ADD ONE, OVERLAPPING".into(), [214, 39, 40], add_near),
            ("ADD ONE, OTHERS APART".into(), [31, 119, 180], add_far),
        ],
    )?;
    Ok(())
}
