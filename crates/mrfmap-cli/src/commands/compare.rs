//! `mrfmap compare`: engines side by side on one dataset — leave-one-out accuracy per engine
//! and resolution, accuracy images and a ray plot — written as a Markdown report.

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::{Context, Result};
use mrfmap::inference::EngineKind;
use mrfmap::outputs::PeakRule;
use mrfmap::outputs::pictures::write_text;

use super::eval::{MetricOptions, mean_std, write_view_pictures};
use super::loo::leave_one_out;
use super::options::MapOptions;
use super::protocol::Protocol;
use super::views::Views;
use mrfmap::pipeline::check_indices;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder, or a ROS bag (with --depth-topic and --fixed-frame or --pose-topic).
    dataset: PathBuf,
    #[command(flatten)]
    bag: super::options::BagArgs,
    /// Engines to compare.
    #[arg(long, value_delimiter = ',', default_value = "logodds", value_parser = super::choice::<EngineKind>())]
    engines: Vec<EngineKind>,
    /// Resolutions (m).
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.02])]
    resolutions: Vec<f64>,
    /// Report folder (report.md and pictures).
    #[arg(short, long)]
    output: PathBuf,
    /// Views to hold out in turn (default: all).
    #[arg(long, value_delimiter = ',')]
    views: Vec<usize>,
    /// The held-out view whose pictures go into the report (default: the first of --views).
    #[arg(long)]
    picture_view: Option<usize>,
    /// Pixel "u,v" whose ray is plotted (default: the image centre).
    #[arg(long, value_parser = super::eval::parse_pixel)]
    pixel: Option<(u32, u32)>,
    /// Experiment protocols, each a table per metric: `truth` (the dataset's noise model;
    /// scored against gt_depth/) and/or `reference` (the MRFMap reference implementation's
    /// coffin-world set-up; README, "Protocols").
    #[arg(long, value_enum, value_delimiter = ',', default_value = "truth")]
    protocol: Vec<Protocol>,
    #[command(flatten)]
    options: MapOptions,
    #[command(flatten)]
    metric: MetricOptions,
}

/// The non-default options of this run, as command-line flags (for the report).
fn extra_flags(a: &Args) -> String {
    let mut f = String::new();
    if !a.views.is_empty() {
        let v: Vec<String> = a.views.iter().map(|v| v.to_string()).collect();
        let _ = write!(f, " --views {}", v.join(","));
    }
    if let Some(b) = &a.options.bounds {
        let _ = write!(f, " --bounds={b}");
    }
    if let Some(m) = a.options.max_range {
        let _ = write!(f, " --max-range {m}");
    }
    if let Some(n) = &a.options.noise {
        let _ = write!(f, " --noise {}", n.display());
    }
    if a.metric.sigma != 0.05 {
        let _ = write!(f, " --sigma {}", a.metric.sigma);
    }
    if a.metric.k != 1.0 {
        let _ = write!(f, " --k {}", a.metric.k);
    }
    if a.metric.sigma_model {
        f.push_str(" --sigma-model");
    }
    if a.metric.paper_boundary {
        f.push_str(" --paper-boundary");
    }
    if a.metric.metric != [PeakRule::Entry] {
        let m: Vec<&str> = a.metric.metric.iter().map(|r| r.name()).collect();
        let _ = write!(f, " --metric {}", m.join(","));
    }
    if let Some(v) = a.metric.target.and_then(|t| clap::ValueEnum::to_possible_value(&t)) {
        let _ = write!(f, " --target {}", v.get_name());
    }
    if a.protocol != [Protocol::Truth] {
        let p: Vec<&str> = a.protocol.iter().map(|p| p.name()).collect();
        let _ = write!(f, " --protocol {}", p.join(","));
    }
    f
}

pub fn run(a: Args) -> Result<()> {
    let kinds = a.engines.clone();
    let dataset = Views::open(&a.dataset, a.options.noise.as_deref(), &a.bag)?;
    let views = if a.views.is_empty() { (0..dataset.len()).collect() } else { a.views.clone() };
    check_indices(dataset.len(), &views)?;
    let picture_view = a.picture_view.unwrap_or(views[0]);
    let cam = dataset.camera();
    let pixel = a.pixel.unwrap_or((cam.width / 2, cam.height / 2));
    std::fs::create_dir_all(&a.output).with_context(|| format!("creating {}", a.output.display()))?;
    let frames = dataset.frames()?;

    // One table per protocol and metric: engines down, resolutions across.
    let header = {
        let mut h = String::from("| engine |");
        for r in &a.resolutions {
            let _ = write!(h, " {r} m |");
        }
        h.push_str("\n|---|");
        h.push_str(&"---|".repeat(a.resolutions.len()));
        h.push('\n');
        h
    };
    let mut tables = vec![vec![header; a.metric.metric.len()]; a.protocol.len()];
    let mut pictures = String::new();
    for (p, &protocol) in a.protocol.iter().enumerate() {
        for &kind in &kinds {
            for t in &mut tables[p] {
                let _ = write!(t, "| {kind} |");
            }
            for &r in &a.resolutions {
                let prefix = format!("{}_{kind}_{r}_", protocol.name());
                let target = a.metric.target(protocol);
                let mut files = Vec::new();
                let by_metric = leave_one_out(
                    &dataset,
                    &frames,
                    &views,
                    (kind, r),
                    protocol,
                    &a.options,
                    &a.metric,
                    |view, scorer, s| {
                        if view == picture_view {
                            let judged = (a.metric.tolerance(), target);
                            files = write_view_pictures(
                                &a.output,
                                &prefix,
                                scorer,
                                &dataset,
                                (view, s),
                                Some(pixel),
                                judged,
                            )?;
                        }
                        Ok(())
                    },
                )?;
                for (m, (rule, scores)) in by_metric.iter().enumerate() {
                    let accs: Vec<f64> = scores.iter().filter_map(|(_, s)| s.accuracy()).collect();
                    let cell = mean_std(&accs).map_or("-".into(), |(m, sd)| format!("{m:.3} +- {sd:.3}"));
                    let _ = write!(tables[p][m], " {cell} |");
                    println!("{} protocol, {} metric, {kind} {r} m: {cell}", protocol.name(), rule.name());
                }
                if !files.is_empty() {
                    let _ = writeln!(pictures, "\n### {kind}, {r} m, {} protocol\n", protocol.name());
                    for f in files {
                        let name = f.file_name().unwrap().to_string_lossy();
                        let _ = write!(pictures, "![{name}]({name}) ");
                    }
                    pictures.push('\n');
                }
            }
            for t in &mut tables[p] {
                t.push('\n');
            }
        }
    }
    let mut table = String::new();
    for (p, protocol) in a.protocol.iter().enumerate() {
        for (m, rule) in a.metric.metric.iter().enumerate() {
            let _ = writeln!(
                table,
                "### {} protocol, {} metric ({})\n\n{}",
                protocol.name(),
                rule.name(),
                match rule {
                    PeakRule::Entry => "docs/ALGORITHMS.md 6.1, peak at voxel entry",
                    PeakRule::Exit => "the reference implementation's rule, peak at voxel exit, z-depth",
                },
                tables[p][m]
            );
        }
    }
    let report = format!(
        "# mrfmap comparison: {ds}\n\n\
         Leave-one-out accuracy: each view is held out in turn, a map is built from the other views'\n\
         `depth/`, and the held-out view is scored; mean +- sample std over {n} views. Tolerance {k} x\n\
         {sigma}; boundary rule: {rule}. Views: {views:?}. Protocols (README, \"Protocols\"): `truth`\n\
         builds with the dataset's noise model and scores against `gt_depth/` (or `depth/`);\n\
         `reference` builds as the MRFMap reference implementation's coffin-world set-up and scores\n\
         against `gt_depth/` plus the model's bias.\n\n{table}\n\
         ## Pictures: view {picture_view}, ray of pixel ({pu}, {pv}), first metric\n\n\
         Accuracy images: yellow accurate, green inaccurate, purple invalid, black no depth. Ray plots: occupancy,\n\
         visibility and generating-surface density along the ray; purple line and band: held-out depth +- tolerance;\n\
         blue dashed: the map's most likely surface.\n{pictures}\n\
         Command: `mrfmap compare {ds} --engines {engines} --resolutions {res} -o {out}{extra}`\n",
        ds = a.dataset.display(),
        n = views.len(),
        k = a.metric.k,
        sigma = if a.metric.sigma_model {
            "the noise model's std at the peak".to_string()
        } else {
            format!("{} m", a.metric.sigma)
        },
        rule = if a.metric.paper_boundary {
            "the paper's (unstopped rays ending beyond the map are accurate)"
        } else {
            "docs/ALGORITHMS.md 6.1 (unstopped rays ending beyond the map are invalid)"
        },
        pu = pixel.0,
        pv = pixel.1,
        engines = a.engines.iter().map(|k| k.name()).collect::<Vec<_>>().join(","),
        res = a.resolutions.iter().map(|r| r.to_string()).collect::<Vec<_>>().join(","),
        out = a.output.display(),
        extra = extra_flags(&a),
    );
    let path = a.output.join("report.md");
    write_text(&path, &report)?;
    println!("report: {}", path.display());
    Ok(())
}
