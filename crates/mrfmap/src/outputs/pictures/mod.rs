//! Pictures a person looks at: accuracy images (PNG), per-ray plots (SVG, so they carry
//! text without a font dependency), map slices and noise-model figures (PNG), all written
//! atomically.

use std::fmt::Write as _;
use std::io::Write;
use std::path::Path;

mod canvas;
mod render;

pub use canvas::{Canvas, PlotArea, Rgb, Series, line_plot, nice_step, write_rgb_png};
pub use render::{Colouring, Up, View, render_grid2d, render_map, slice_map};

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::frames::{NoiseModel, STD_FLOOR};
use crate::map::{Map, VoxelKey};
use crate::outputs::{PixelClass, ProfileStep, RayVerdict, ViewScore, VoxelTruth, mean_sigma, true_occupancy};
use crate::source::Scene;

/// Colours of the accuracy image, as the MRFMap paper's Fig. 7.
pub const ACCURATE_RGB: [u8; 3] = [250, 220, 40]; // yellow
/// Inaccurate pixels.
pub const INACCURATE_RGB: [u8; 3] = [40, 160, 80]; // green
/// Invalid pixels (not counted).
pub const INVALID_RGB: [u8; 3] = [110, 40, 140]; // purple
/// Pixels without held-out depth.
pub const NO_DEPTH_RGB: [u8; 3] = [0, 0, 0];

/// The accuracy image of a scored view: accurate yellow, inaccurate green, invalid purple,
/// no depth black.
pub fn write_accuracy_image(path: &Path, score: &ViewScore) -> Result<()> {
    let rgb: Vec<u8> = score
        .classes
        .iter()
        .flat_map(|c| match c {
            PixelClass::Accurate => ACCURATE_RGB,
            PixelClass::Inaccurate => INACCURATE_RGB,
            PixelClass::Invalid => INVALID_RGB,
            PixelClass::NoDepth => NO_DEPTH_RGB,
        })
        .collect();
    write_rgb_png(path, score.width, score.height, &rgb)
}

/// An SVG plot of `p_occ(s)`, `vis(s)` and `omega(s)` (scaled to peak 1) along one ray,
/// with the held-out range and its `+- tolerance` band and the most likely surface marked.
pub fn ray_plot_svg(title: &str, steps: &[ProfileStep], verdict: &RayVerdict, tolerance: f64) -> String {
    let (w, h, left, right, top, bottom) = (720.0, 360.0, 60.0, 20.0, 40.0, 50.0);
    let s_max = steps.last().map_or(0.0, |s| s.s_out).max(verdict.range + 2.0 * tolerance).max(1e-3);
    let x = |s: f64| left + (w - left - right) * s / s_max;
    let y = |v: f64| top + (h - top - bottom) * (1.0 - v.clamp(0.0, 1.0));
    let omega_max = steps.iter().map(|s| s.alpha * s.visibility).fold(0.0, f64::max).max(1e-12);
    let mut svg = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n\
         <text x=\"{left}\" y=\"20\" font-size=\"14\">{}</text>\n",
        escape(title)
    );
    // Tolerance band and markers.
    let (b0, b1) = (x((verdict.range - tolerance).max(0.0)), x(verdict.range + tolerance));
    let _ = writeln!(
        svg,
        "<rect x=\"{b0:.1}\" y=\"{top}\" width=\"{:.1}\" height=\"{}\" fill=\"purple\" fill-opacity=\"0.15\"/>",
        b1 - b0,
        h - top - bottom
    );
    let vline = |svg: &mut String, s: f64, colour: &str, dash: &str| {
        let _ = writeln!(
            svg,
            "<line x1=\"{0:.1}\" x2=\"{0:.1}\" y1=\"{top}\" y2=\"{1}\" stroke=\"{colour}\" stroke-width=\"2\" stroke-dasharray=\"{dash}\"/>",
            x(s),
            h - bottom
        );
    };
    vline(&mut svg, verdict.range, "purple", "");
    if let Some(p) = verdict.peak {
        vline(&mut svg, p, "blue", "6,3");
    }
    // Curves: occupancy and visibility are piecewise (constant / exponential) per voxel.
    let mut occ = String::new();
    let mut vis = String::new();
    let mut omega = String::new();
    for st in steps {
        let _ = write!(occ, "{:.1},{:.1} {:.1},{:.1} ", x(st.s_in), y(st.occupancy), x(st.s_out), y(st.occupancy));
        let vis_out = st.visibility * (-st.alpha * (st.s_out - st.s_in)).exp();
        let _ = write!(vis, "{:.1},{:.1} {:.1},{:.1} ", x(st.s_in), y(st.visibility), x(st.s_out), y(vis_out));
        let (o_in, o_out) = (st.alpha * st.visibility / omega_max, st.alpha * vis_out / omega_max);
        let _ = write!(omega, "{:.1},{:.1} {:.1},{:.1} ", x(st.s_in), y(o_in), x(st.s_out), y(o_out));
    }
    for (points, colour, label, ly) in
        [(occ, "green", "p_occ(s)", 0), (vis, "red", "vis(s)", 1), (omega, "blue", "omega(s) / max", 2)]
    {
        let _ = writeln!(svg, "<polyline points=\"{points}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.5\"/>");
        let ly = top + 15.0 + 16.0 * ly as f64;
        let _ = writeln!(svg, "<text x=\"{}\" y=\"{ly}\" fill=\"{colour}\">{label}</text>", w - right - 130.0);
    }
    // Axes with ticks.
    let _ =
        writeln!(svg, "<path d=\"M{left},{top} V{0} H{1}\" fill=\"none\" stroke=\"black\"/>", h - bottom, w - right);
    let tick = nice_step(s_max / 8.0);
    let mut s = 0.0;
    while s <= s_max + 1e-9 {
        let _ =
            writeln!(svg, "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{s:.2}</text>", x(s), h - bottom + 16.0);
        s += tick;
    }
    for v in [0.0, 0.5, 1.0] {
        let _ = writeln!(svg, "<text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{v:.1}</text>", left - 6.0, y(v) + 4.0);
    }
    let _ = writeln!(
        svg,
        "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">range along the ray s (m); purple: held-out depth +- tolerance, blue dashed: argmax omega</text>",
        (left + w - right) / 2.0,
        h - 12.0
    );
    svg.push_str("</svg>\n");
    svg
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// Writes a text file atomically (SVG plots, reports).
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, |w| w.write_all(text.as_bytes()))
}

/// A perceptually ordered colour map (viridis, 5 anchors linearly interpolated) for `t` in [0, 1].
pub fn viridis(t: f64) -> [u8; 3] {
    const ANCHORS: [[f64; 3]; 5] =
        [[68.0, 1.0, 84.0], [59.0, 82.0, 139.0], [33.0, 145.0, 140.0], [94.0, 201.0, 98.0], [253.0, 231.0, 37.0]];
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 0.0 } * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f64;
    [0, 1, 2].map(|c| (ANCHORS[i][c] * (1.0 - f) + ANCHORS[i + 1][c] * f).round() as u8)
}

/// Horizontal slices of a map against its scene at height `z`: four PNGs in `dir` named
/// `slice_z{z}_{mean,sigma,abs_error,ic}.png` over the map's x-y bounds (world +y up), each
/// voxel a square of pixels (at least 600 pixels across), unallocated voxels grey, values on the viridis scale (mean, sigma and |error| on
/// [0, 1], sigma on [0, 0.5], I_c with gamma 0.5 on [0, 1]). Returns the files written.
pub fn write_truth_slices(map: &Map, scene: &Scene, z: f64, dir: &Path) -> Result<Vec<std::path::PathBuf>> {
    let r = map.resolution();
    let Some((lo, hi)) = map.voxels.key_bounds() else {
        return Err(Error::Invalid("the map is empty: nothing to slice".into()));
    };
    let kz = (z / r).floor() as i32;
    let (w, h) = ((hi.0[0] - lo.0[0] + 1) as u32, (hi.0[1] - lo.0[1] + 1) as u32);
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    type Quantity = (&'static str, fn(&VoxelTruth) -> f64);
    let quantities: [Quantity; 4] = [
        ("mean", |t| t.mean),
        ("sigma", |t| t.sigma * 2.0),
        ("abs_error", |t| t.error().abs()),
        ("ic", |t| t.inconsistency(0.5)),
    ];
    let scale = (600 / w.max(h)).max(1);
    let (iw, ih) = (w * scale, h * scale);
    let mut written = Vec::new();
    for (name, value) in quantities {
        let mut rgb = vec![128u8; iw as usize * ih as usize * 3];
        for py in 0..h {
            for px in 0..w {
                // Image rows go down; world y goes up.
                let key = VoxelKey([lo.0[0] + px as i32, hi.0[1] - py as i32, kz]);
                let Some(v) = map.voxels.get(key) else { continue };
                let (mean, sigma) = mean_sigma(map, v);
                let colour = viridis(value(&VoxelTruth { truth: true_occupancy(scene, key, r), mean, sigma }));
                for y in py * scale..(py + 1) * scale {
                    for x in px * scale..(px + 1) * scale {
                        let i = (y as usize * iw as usize + x as usize) * 3;
                        rgb[i..i + 3].copy_from_slice(&colour);
                    }
                }
            }
        }
        let path = dir.join(format!("slice_z{z}_{name}.png"));
        write_rgb_png(&path, iw, ih, &rgb)?;
        written.push(path);
    }
    Ok(written)
}

/// The noise model as a figure (MRFMap Fig. 5): bias and std against true depth over
/// `depths` for the aggregate model (black) and four patches (the ones with the lowest and
/// highest std at `at_depth`, the centre one and the top-left one), plus a map of every
/// patch's std at `at_depth` (viridis, scale in millimetres).
///
/// ```
/// use mrfmap::frames::{NoiseModel, Poly};
/// let m = NoiseModel::aggregate(Poly([0.0, 0.0, 0.004]), Poly([0.002, 0.0, 0.0035]));
/// let c = mrfmap::outputs::pictures::noise_figure(&m, (0.3, 5.0), 2.0);
/// assert_eq!(c.pixel(0, 0), [255, 255, 255]);
/// ```
pub fn noise_figure(model: &NoiseModel, depths: (f64, f64), at_depth: f64) -> Canvas {
    const COLOURS: [Rgb; 4] = [[31, 119, 180], [214, 39, 40], [44, 160, 44], [148, 103, 189]];
    let mut c = Canvas::new(1260, 440);
    let samples: Vec<f64> = (0..=100).map(|i| depths.0 + (depths.1 - depths.0) * i as f64 / 100.0).collect();
    // Chosen patches: (label, pixel inside it).
    let mut chosen: Vec<(String, (u32, u32))> = Vec::new();
    if let Some(p) = &model.patches {
        let n = (p.rows * p.cols) as usize;
        let std_at = |i: usize| p.std[i].eval(at_depth);
        let lo = (0..n).min_by(|&a, &b| std_at(a).total_cmp(&std_at(b))).unwrap_or(0);
        let hi = (0..n).max_by(|&a, &b| std_at(a).total_cmp(&std_at(b))).unwrap_or(0);
        let centre = ((p.rows / 2) * p.cols + p.cols / 2) as usize;
        for i in [lo, hi, centre, 0] {
            let (r, col) = (i as u32 / p.cols, i as u32 % p.cols);
            if !chosen.iter().any(|(_, px)| *px == (col * p.size, r * p.size)) {
                chosen.push((format!("PATCH {r},{col}"), (col * p.size, r * p.size)));
            }
        }
    }
    type Curve = fn(&NoiseModel, u32, u32, f64) -> f64;
    let panels: [(&str, &str, Curve, Curve); 2] = [
        ("BIAS VS DEPTH", "BIAS (M)", |m, u, v, z| m.bias_std(u, v, z).0, |m, _, _, z| m.bias.eval(z)),
        ("STD VS DEPTH", "STD (M)", |m, u, v, z| m.bias_std(u, v, z).1, |m, _, _, z| m.std.eval(z)),
    ];
    for (k, (title, y_label, per_patch, aggregate)) in panels.into_iter().enumerate() {
        type Line = (String, Rgb, Vec<(f64, f64)>);
        let mut curves: Vec<Line> = Vec::new();
        let line = |f: &dyn Fn(f64) -> f64| samples.iter().map(|&z| (z, f(z))).collect::<Vec<_>>();
        curves.push(("AGGREGATE".into(), [0, 0, 0], line(&|z| aggregate(model, 0, 0, z))));
        for (j, (label, (u, v))) in chosen.iter().enumerate() {
            curves.push((label.clone(), COLOURS[j % 4], line(&|z| per_patch(model, *u, *v, z))));
        }
        let ys = curves.iter().flat_map(|c| c.2.iter().map(|p| p.1));
        let (ymin, ymax) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), y| (a.min(y), b.max(y)));
        let x0 = 420 * k as i64;
        let area = PlotArea::new(
            &mut c,
            (x0, 0, x0 + 420, 440),
            depths,
            (ymin.min(0.0), ymax),
            "TRUE DEPTH (M)",
            y_label,
            title,
        );
        for (row, (label, colour, points)) in curves.iter().enumerate() {
            area.polyline(&mut c, points, *colour);
            area.legend(&mut c, row, label, *colour);
        }
    }
    // Patch map of std at `at_depth`.
    let black = [0, 0, 0];
    c.text(850, 8, &format!("STD AT {at_depth:.1} M (MM)"), 2, black);
    match &model.patches {
        None => c.text(850, 200, "NO PER-PATCH MODEL", 2, black),
        Some(p) => {
            let values: Vec<f64> = p.std.iter().map(|s| s.eval(at_depth).max(STD_FLOOR) * 1e3).collect();
            let (lo, hi) = values.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
            let cell = (360 / p.cols.max(p.rows)).max(1) as i64;
            let (ox, oy) = (850, 40);
            for (i, v) in values.iter().enumerate() {
                let (r, col) = ((i as u32 / p.cols) as i64, (i as u32 % p.cols) as i64);
                let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
                c.fill(ox + col * cell, oy + r * cell, ox + (col + 1) * cell, oy + (r + 1) * cell, viridis(t));
            }
            // Colour bar under the map.
            let y = oy + p.rows as i64 * cell + 16;
            for x in 0..300 {
                c.fill(ox + x, y, ox + x + 1, y + 12, viridis(x as f64 / 299.0));
            }
            c.text(ox, y + 18, &format!("{lo:.1}"), 1, black);
            let label = format!("{hi:.1}");
            c.text(ox + 300 - Canvas::text_width(&label, 1), y + 18, &label, 1, black);
        }
    }
    c
}
