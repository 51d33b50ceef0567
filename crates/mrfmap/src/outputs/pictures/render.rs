//! Looking at maps without a viewer: a ray-cast picture of the occupied voxels from any
//! viewpoint ([`render_map`]), coloured by height, sigma or occupancy, and axis-aligned slices
//! of occupancy ([`slice_map`]), and 2D grids with their sigma ([`render_grid2d`]). All return
//! a [`Canvas`] to save as PNG. Pictures stand the world on its [`Up`] axis (`+z` unless told;
//! ICL-NUIM, 7-Scenes and Redwood worlds have `+y` up).

use std::ops::ControlFlow;

use rayon::prelude::*;

use super::canvas::{Canvas, Rgb};
use super::viridis;
use crate::error::{Error, Result};
pub use crate::frames::Up;
use crate::map::Aabb;
use crate::map::{Grid2d, Map, MapVoxel, VoxelKey};
use crate::outputs::mean_sigma;
use crate::rays::for_each_crossing;

/// What the colour of a rendered voxel says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Colouring {
    /// Height (world z) over the map's range, viridis.
    Height,
    /// Standard deviation on [0, 0.5] (the engine's variance, or `sqrt(p (1 - p))`), viridis.
    Sigma,
    /// Occupancy on [0.5, 1], viridis.
    Occupancy,
}

impl std::str::FromStr for Colouring {
    type Err = Error;

    /// `height`, `sigma` (or `variance`), `occupancy`.
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "height" => Ok(Colouring::Height),
            "sigma" | "variance" => Ok(Colouring::Sigma),
            "occupancy" => Ok(Colouring::Occupancy),
            _ => Err(Error::Invalid(format!("unknown colouring {s:?}; use height, sigma or occupancy"))),
        }
    }
}

impl Colouring {
    /// The colour of `voxel` (at `key` in `map`); `heights` is the range of heights along `up`
    /// that `Height` spans, `threshold` the lowest occupancy drawn (where `Occupancy` starts).
    pub fn colour(
        self,
        map: &Map,
        key: VoxelKey,
        voxel: &MapVoxel,
        (up, heights): (Up, (f64, f64)),
        threshold: f32,
    ) -> Rgb {
        let r = map.resolution();
        match self {
            Colouring::Height => viridis((up.height(key.center(r)) - heights.0) / (heights.1 - heights.0).max(r)),
            Colouring::Sigma => viridis(mean_sigma(map, voxel).1 / 0.5),
            Colouring::Occupancy => {
                let t = threshold.clamp(0.0, 0.999) as f64;
                viridis((voxel.occupancy as f64 - t) / (1.0 - t))
            }
        }
    }
}

/// A pinhole view of a map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Camera centre (world, metres).
    pub eye: [f64; 3],
    /// Point looked at.
    pub target: [f64; 3],
    /// Picture size in pixels.
    pub width: u32,
    /// Picture height in pixels.
    pub height: u32,
    /// Horizontal field of view in degrees.
    pub fov_degrees: f64,
    /// Voxels above this occupancy are drawn.
    pub threshold: f32,
    /// Colour scheme.
    pub colouring: Colouring,
    /// The world direction drawn up (and that `Height` colours along).
    pub up: Up,
}

impl View {
    /// A view of the map's occupied voxels (above 0.5; all voxels where none is) from above one
    /// corner (a third of the way up along `up`), 1024x768, 60 degrees, occupancy above 0.5,
    /// coloured by height. `None` for an empty map. Framing what is drawn, not every voxel:
    /// free space reaches as far as the rays did (6 m around a 4 m scene on coffin-world),
    /// and framed it left the scene a small picture in the middle.
    pub fn overview(map: &Map, up: Up) -> Option<View> {
        let r = map.resolution();
        let occupied = map.voxels.iter().filter(|(_, v)| v.occupancy > 0.5).fold(None, |b, (k, _)| {
            let (lo, hi) = b.unwrap_or((k.0, k.0));
            Some(([0, 1, 2].map(|a| lo[a].min(k.0[a])), [0, 1, 2].map(|a| hi[a].max(k.0[a]))))
        });
        let (lo, hi) = match occupied {
            Some((lo, hi)) => (lo.map(|i| i as f64 * r), hi.map(|i| (i + 1) as f64 * r)),
            None => map.bounds()?,
        };
        let c = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
        let (width, height, fov_degrees) = (1024, 768, 60.0f64);
        // Far enough that the box's bounding sphere fits the narrower field of view (the
        // vertical one), so the whole box shows, as large as that allows.
        let radius = 0.5 * (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
        let half_vertical = ((0.5 * fov_degrees).to_radians().tan() * height as f64 / width as f64).atan();
        let distance = radius / half_vertical.sin();
        // For +z: back 0.9 along x, 1.2 along y, 0.9 up; the two level axes follow up's cyclically.
        let norm = (0.9f64 * 0.9 + 1.2 * 1.2 + 0.9 * 0.9).sqrt();
        let mut eye = c;
        eye[(up.axis + 1) % 3] -= 0.9 / norm * distance;
        eye[(up.axis + 2) % 3] -= 1.2 / norm * distance;
        eye[up.axis] += 0.9 / norm * distance * up.vector()[up.axis];
        Some(View { eye, target: c, width, height, fov_degrees, threshold: 0.5, colouring: Colouring::Height, up })
    }
}

/// Ray-casts `map` from `view`: each pixel shows the first voxel above the threshold on its
/// ray, shaded by the face it enters (so shapes read without lighting), white where there is
/// none.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{Up, View, render_map};
/// let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// let view = View { eye: [0.05, 0.05, 3.0], target: [0.05, 0.05, 0.0], width: 64, height: 48, ..View::overview(&map, Up::Z).unwrap() };
/// let picture = render_map(&map, &view).unwrap();
/// assert_ne!(picture.pixel(32, 24), [255, 255, 255]); // the voxel, seen from above
/// assert_eq!(picture.pixel(0, 0), [255, 255, 255]);
/// ```
pub fn render_map(map: &Map, view: &View) -> Result<Canvas> {
    let (lo, hi) = map.bounds().ok_or_else(|| Error::Invalid("the map is empty: nothing to render".into()))?;
    let v = view;
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let norm = |a: [f64; 3]| {
        let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        (n > 1e-12 && n.is_finite()).then(|| a.map(|x| x / n))
    };
    let forward = norm(sub(v.target, v.eye)).ok_or_else(|| Error::Invalid("eye and target coincide".into()))?;
    // Looking straight along up has no "right": any level direction will do.
    let level = Up { axis: (v.up.axis + 1) % 3, negative: false };
    let right = norm(cross(forward, v.up.vector())).or_else(|| norm(cross(forward, level.vector()))).expect("unit");
    let up = cross(right, forward);
    if !(v.width > 0 && v.height > 0 && v.fov_degrees > 0.0 && v.fov_degrees < 179.0) {
        return Err(Error::Invalid(format!(
            "bad view: {}x{} pixels and a {} degree field of view; need at least 1x1 pixels and a field of view \
             between 0 and 179 degrees (exclusive)",
            v.width, v.height, v.fov_degrees
        )));
    }
    let focal = 0.5 * v.width as f64 / (0.5 * v.fov_degrees.to_radians()).tan();
    let r = map.resolution();
    let bounds = Aabb::new(lo, hi)?;
    let (zmin, zmax) = v.up.heights(lo, hi);
    let colour_of = |key: VoxelKey| -> Rgb {
        v.colouring.colour(map, key, map.voxels.get(key).expect("hit voxels exist"), (v.up, (zmin, zmax)), v.threshold)
    };
    let w = v.width as usize;
    let mut rgb = vec![255u8; w * v.height as usize * 3];
    rgb.par_chunks_mut(w * 3).enumerate().for_each(|(py, row)| {
        for px in 0..w {
            let (x, y) =
                ((px as f64 + 0.5 - 0.5 * w as f64) / focal, (0.5 * v.height as f64 - py as f64 - 0.5) / focal);
            let Some(dir) = norm([0, 1, 2].map(|a| forward[a] + x * right[a] + y * up[a])) else { continue };
            let Some((s0, s1)) = bounds.clip(v.eye, dir, 0.0, f64::MAX) else { continue };
            let mut hit = None;
            for_each_crossing(v.eye, dir, s0, s1, r, |c| {
                if map.voxels.get(c.key).is_some_and(|vox| vox.occupancy > v.threshold) {
                    hit = Some(c);
                    return ControlFlow::Break(());
                }
                ControlFlow::Continue(())
            });
            let Some(c) = hit else { continue };
            // The face the ray entered through: the axis whose voxel boundary is nearest the
            // entry point.
            let p = [0, 1, 2].map(|a| v.eye[a] + c.s_in * dir[a]);
            let face = (0..3)
                .map(|a| {
                    let t = p[a] / r - c.key.0[a] as f64;
                    (a, t.min(1.0 - t).abs())
                })
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map_or(2, |f| f.0);
            let shade = [0.8, 0.65, 1.0][face];
            let base = colour_of(c.key);
            row[px * 3..px * 3 + 3].copy_from_slice(&base.map(|ch| (ch as f64 * shade) as u8));
        }
    });
    let mut canvas = Canvas::from_rgb(v.width, v.height, rgb);
    let label = match v.colouring {
        Colouring::Height => format!("COLOUR: HEIGHT ({}) {zmin:.2} TO {zmax:.2} M", v.up).to_uppercase(),
        Colouring::Sigma => "COLOUR: SIGMA 0 TO 0.5".to_string(),
        Colouring::Occupancy => format!("COLOUR: OCCUPANCY {} TO 1", v.threshold),
    };
    canvas.text(8, 8, &label, 2, [0, 0, 0]);
    Ok(canvas)
}

/// The voxels of `map` in the plane `axis = value` (axis 0, 1, 2 = x, y, z), coloured by
/// occupancy (viridis on [0, 1]; unknown light grey), each voxel a square of pixels (at least
/// 600 pixels across), the first remaining axis to the right and the second up.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 5]), MapVoxel { occupancy: 1.0, variance: 0.0 });
/// map.voxels.insert(VoxelKey([3, 2, 5]), MapVoxel { occupancy: 0.0, variance: 0.0 });
/// let c = mrfmap::outputs::slice_map(&map, 2, 0.55).unwrap();
/// assert_eq!(c.pixel(10, c.height() - 10), mrfmap::outputs::pictures::viridis(1.0));
/// assert!(mrfmap::outputs::slice_map(&map, 2, 3.0).is_err()); // no voxel at z = 3
/// ```
pub fn slice_map(map: &Map, axis: usize, value: f64) -> Result<Canvas> {
    let names = ["x", "y", "z"];
    if axis > 2 {
        return Err(Error::Invalid(format!("slice axis must be 0, 1 or 2, got {axis}")));
    }
    let r = map.resolution();
    let k = (value / r).floor() as i32;
    let (a, b) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let in_plane: Vec<(VoxelKey, f32)> =
        map.voxels.iter().filter(|(key, _)| key.0[axis] == k).map(|(key, v)| (key, v.occupancy)).collect();
    if in_plane.is_empty() {
        return Err(Error::Invalid(format!("the map has no voxels at {} = {value}", names[axis])));
    }
    let (mut lo, mut hi) = ([i32::MAX; 2], [i32::MIN; 2]);
    for (key, _) in &in_plane {
        for (j, ax) in [a, b].into_iter().enumerate() {
            lo[j] = lo[j].min(key.0[ax]);
            hi[j] = hi[j].max(key.0[ax]);
        }
    }
    let (nw, nh) = ((hi[0] as i64 - lo[0] as i64 + 1) as u64, (hi[1] as i64 - lo[1] as i64 + 1) as u64);
    // One pixel per voxel at least: a sparse map whose voxels lie kilometres apart would ask
    // for a picture no machine holds.
    if nw * nh > MAX_SLICE_PIXELS {
        return Err(Error::Invalid(format!(
            "the slice spans {nw} x {nh} voxels, more than a picture of {MAX_SLICE_PIXELS} pixels holds: crop the map first \
             (`mrfmap crop`)"
        )));
    }
    let (nw, nh) = (nw as u32, nh as u32);
    let scale = (600 / nw.max(nh)).max(1) as i64;
    let top = 28i64;
    let legend = format!("{} = {value}: OCCUPANCY 0 TO 1, UNKNOWN GREY", names[axis].to_uppercase());
    let mut c =
        Canvas::new((nw * scale as u32).max(Canvas::text_width(&legend, 1) as u32), nh * scale as u32 + top as u32);
    c.text(0, 8, &legend, 1, [0, 0, 0]);
    c.fill(0, top, nw as i64 * scale, top + nh as i64 * scale, [215, 215, 215]);
    for (key, p) in in_plane {
        let x = (key.0[a] - lo[0]) as i64 * scale;
        let y = top + (hi[1] - key.0[b]) as i64 * scale;
        c.fill(x, y, x + scale, y + scale, viridis(p as f64));
    }
    Ok(c)
}

/// Most voxels a slice picture may show (one pixel each at least).
const MAX_SLICE_PIXELS: u64 = 1 << 26;

/// A 2D occupancy grid as a picture: occupancy (viridis 0 to 1) and sigma (viridis 0 to 0.5)
/// side by side, unknown grey, north up. Grids larger than `max_side` cells on a side are
/// shown in blocks, each pixel the most occupied (and most uncertain) cell of its block, so
/// thin walls stay visible.
pub fn render_grid2d(grid: &Grid2d, max_side: u32) -> Canvas {
    let block = grid.width.max(grid.height).div_ceil(max_side.max(1) as usize).max(1);
    let (w, h) = (grid.width.div_ceil(block), grid.height.div_ceil(block));
    let scale = (600 / w.max(h)).clamp(1, 8) as i64;
    let (pw, ph) = (w as i64 * scale, h as i64 * scale);
    let (top, gap) = (28i64, 16i64);
    let mut c = Canvas::new((2 * pw + gap) as u32, (ph + top) as u32);
    c.text(0, 8, "OCCUPANCY 0 TO 1", 1, [0, 0, 0]);
    c.text(pw + gap, 8, "SIGMA 0 TO 0.5", 1, [0, 0, 0]);
    for bj in 0..h {
        for bi in 0..w {
            // The block's most occupied and most uncertain known cells.
            let mut cell: Option<(f32, f32)> = None;
            for j in bj * block..((bj + 1) * block).min(grid.height) {
                for i in bi * block..((bi + 1) * block).min(grid.width) {
                    if let Some((p, s)) = grid.cell(i, j) {
                        cell = Some(cell.map_or((p, s), |(q, t)| (q.max(p), t.max(s))));
                    }
                }
            }
            let (x, y) = (bi as i64 * scale, top + (h - 1 - bj) as i64 * scale);
            let (occ, sig) = match cell {
                Some((p, s)) => (viridis(p as f64), viridis(s as f64 / 0.5)),
                None => ([215, 215, 215], [215, 215, 215]),
            };
            c.fill(x, y, x + scale, y + scale, occ);
            c.fill(pw + gap + x, y, pw + gap + x + scale, y + scale, sig);
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::EngineKind;

    /// The extent (columns, rows) of what a picture draws, label rows left out.
    fn drawn(c: &Canvas) -> (u32, u32) {
        let (mut x0, mut x1, mut y0, mut y1) = (u32::MAX, 0, u32::MAX, 0);
        for y in 30..c.height() {
            for x in 0..c.width() {
                if c.pixel(x, y) != [255, 255, 255] {
                    (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
                }
            }
        }
        (x1.saturating_sub(x0), y1.saturating_sub(y0))
    }

    #[test]
    fn a_pole_along_the_up_axis_stands_upright() {
        // A pole along y, on a small base so the map is not one voxel wide.
        let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        for y in 0..20 {
            map.voxels.insert(VoxelKey([0, y, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        }
        for (x, z) in [(-2, -2), (2, 2), (-2, 2), (2, -2)] {
            map.voxels.insert(VoxelKey([x, 0, z]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        }
        let up: Up = "+y".parse().unwrap();
        let (w, h) =
            drawn(&render_map(&map, &View { width: 200, height: 200, ..View::overview(&map, up).unwrap() }).unwrap());
        assert!(h > 2 * w, "+y up: the pole is tall ({w}x{h})");
        // Upside down it still stands, and with +z up the pole lies across the picture.
        let down: Up = "-y".parse().unwrap();
        let (w, h) =
            drawn(&render_map(&map, &View { width: 200, height: 200, ..View::overview(&map, down).unwrap() }).unwrap());
        assert!(h > 2 * w, "-y up ({w}x{h})");
        let (w, h) = drawn(
            &render_map(&map, &View { width: 200, height: 200, ..View::overview(&map, Up::Z).unwrap() }).unwrap(),
        );
        assert!(h < 2 * w, "+z up ({w}x{h})");
        // Heights along up: the pole's top is the highest voxel.
        assert_eq!(up.heights([0.0, -1.0, 0.0], [1.0, 2.0, 3.0]), (-1.0, 2.0));
        assert_eq!(down.heights([0.0, -1.0, 0.0], [1.0, 2.0, 3.0]), (-2.0, 1.0));
    }

    #[test]
    fn the_overview_frames_what_it_draws_not_the_free_space_around_it() {
        // A 1 m cube of occupied voxels in 12 m of free space.
        let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        for x in -60..60 {
            for y in -60..60 {
                map.voxels.insert(VoxelKey([x, y, 0]), MapVoxel { occupancy: 0.2, variance: 0.0 });
            }
        }
        for k in 0..1000 {
            map.voxels.insert(VoxelKey([k % 10, k / 10 % 10, 1 + k / 100]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        }
        let near = |a: [f64; 3], b: [f64; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9);
        let view = View::overview(&map, Up::Z).unwrap();
        assert!(near(view.target, [0.5, 0.5, 0.6]), "{:?}", view.target);
        let (w, h) = drawn(&render_map(&map, &view).unwrap());
        // The cube fills a good part of the 1024 x 768 picture (it was 1/12 of the width).
        assert!(w > 400 && h > 400, "{w}x{h}");
        // And whole: nothing drawn on the picture's edges.
        let picture = render_map(&map, &view).unwrap();
        let (pw, ph) = (picture.width(), picture.height());
        let edge = (0..pw).flat_map(|x| [(x, 30), (x, ph - 1)]).chain((30..ph).flat_map(|y| [(0, y), (pw - 1, y)]));
        assert!(edge.into_iter().all(|(x, y)| picture.pixel(x, y) == [255, 255, 255]), "{w}x{h} touches the edge");
        // Nothing occupied: the free voxels are framed.
        let mut free = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        free.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.2, variance: 0.0 });
        free.voxels.insert(VoxelKey([9, 0, 0]), MapVoxel { occupancy: 0.2, variance: 0.0 });
        assert!(near(View::overview(&free, Up::Z).unwrap().target, [0.5, 0.05, 0.05]));
    }

    #[test]
    fn up_axes_parse_and_print() {
        for (text, axis, negative) in [("+x", 0, false), ("-y", 1, true), ("z", 2, false), (" +z ", 2, false)] {
            let up: Up = text.parse().unwrap();
            assert_eq!((up.axis, up.negative), (axis, negative), "{text}");
            assert_eq!(up.to_string().parse::<Up>().unwrap(), up);
        }
        for bad in ["", "+w", "y+", "--y", "+"] {
            assert!(bad.parse::<Up>().is_err(), "{bad:?}");
        }
    }
}
