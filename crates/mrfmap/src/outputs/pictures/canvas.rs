//! A small raster canvas for PNG figures: lines, boxes, a 5x7 bitmap font and line-plot
//! axes with labelled ticks; and the one PNG writer every RGB picture goes through
//! ([`write_rgb_png`]). It exists so that plots (noise curves, scaling curves) carry
//! their numbers without a plotting or font dependency.

use std::path::Path;

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};

/// An RGB colour.
pub type Rgb = [u8; 3];

/// 5x7 glyphs, one byte per row (bit 4 = leftmost column). Lower-case letters are drawn as
/// capitals; anything else unknown as '?'.
const FONT: &[(char, [u8; 7])] = &[
    ('0', [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E]),
    ('1', [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('2', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F]),
    ('3', [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E]),
    ('4', [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02]),
    ('5', [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E]),
    ('6', [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E]),
    ('7', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]),
    ('8', [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E]),
    ('9', [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C]),
    ('A', [0x0E, 0x11, 0x11, 0x11, 0x1F, 0x11, 0x11]),
    ('B', [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E]),
    ('C', [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E]),
    ('D', [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C]),
    ('E', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F]),
    ('F', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10]),
    ('G', [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F]),
    ('H', [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]),
    ('I', [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('J', [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C]),
    ('K', [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11]),
    ('L', [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F]),
    ('M', [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11]),
    ('N', [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11]),
    ('O', [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('P', [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10]),
    ('Q', [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D]),
    ('R', [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11]),
    ('S', [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E]),
    ('T', [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]),
    ('U', [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('V', [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04]),
    ('W', [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A]),
    ('X', [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11]),
    ('Y', [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04]),
    ('Z', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F]),
    (' ', [0; 7]),
    ('.', [0, 0, 0, 0, 0, 0x0C, 0x0C]),
    (',', [0, 0, 0, 0, 0x0C, 0x04, 0x08]),
    (':', [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0]),
    ('-', [0, 0, 0, 0x1F, 0, 0, 0]),
    ('+', [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0]),
    ('=', [0, 0, 0x1F, 0, 0x1F, 0, 0]),
    ('/', [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0]),
    ('(', [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02]),
    (')', [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08]),
    ('%', [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03]),
    ('_', [0, 0, 0, 0, 0, 0, 0x1F]),
    ('?', [0x0E, 0x11, 0x01, 0x02, 0x04, 0, 0x04]),
];

fn glyph(c: char) -> &'static [u8; 7] {
    let c = c.to_ascii_uppercase();
    FONT.iter().find(|(g, _)| *g == c).or_else(|| FONT.iter().find(|(g, _)| *g == '?')).map(|(_, b)| b).unwrap()
}

/// An RGB image being drawn on, white to start with.
///
/// ```
/// use mrfmap::outputs::Canvas;
/// let mut c = Canvas::new(60, 20);
/// c.text(2, 2, "1.5 M", 2, [0, 0, 0]);
/// assert_eq!(c.pixel(2, 2), [255, 255, 255]); // top-left of '1' is blank
/// assert_eq!(c.pixel(6, 2), [0, 0, 0]); // its top stroke
/// ```
#[derive(Clone, Debug)]
pub struct Canvas {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

impl Canvas {
    /// A white canvas.
    pub fn new(width: u32, height: u32) -> Self {
        Canvas { width, height, rgb: vec![255; width as usize * height as usize * 3] }
    }

    /// A canvas from row-major RGB bytes; panics unless there are `width * height * 3`.
    pub fn from_rgb(width: u32, height: u32, rgb: Vec<u8>) -> Self {
        assert_eq!(rgb.len(), width as usize * height as usize * 3, "RGB buffer size");
        Canvas { width, height, rgb }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The colour at `(x, y)` (which must be inside).
    pub fn pixel(&self, x: u32, y: u32) -> Rgb {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Sets one pixel; outside the canvas is ignored.
    pub fn put(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Fills the rectangle `[x0, x1) x [y0, y1)` (clipped).
    pub fn fill(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb) {
        for y in y0.max(0)..y1.min(self.height as i64) {
            for x in x0.max(0)..x1.min(self.width as i64) {
                self.put(x, y, c);
            }
        }
    }

    /// A straight line `width` pixels thick (Bresenham with a square pen).
    pub fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), width: i64, c: Rgb) {
        // Clip to a margin around the canvas so far-away endpoints cost nothing.
        let margin = width as f64 + 2.0;
        let Some(((x0, y0), (x1, y1))) = clip_segment(
            (x0, y0),
            (x1, y1),
            (-margin, -margin),
            (self.width as f64 + margin, self.height as f64 + margin),
        ) else {
            return;
        };
        let (mut x, mut y) = (x0.round() as i64, y0.round() as i64);
        let (xe, ye) = (x1.round() as i64, y1.round() as i64);
        let (dx, dy) = ((xe - x).abs(), -(ye - y).abs());
        let (sx, sy) = (if x < xe { 1 } else { -1 }, if y < ye { 1 } else { -1 });
        let mut err = dx + dy;
        let (lo, hi) = (-(width - 1) / 2, width / 2);
        loop {
            self.fill(x + lo, y + lo, x + hi + 1, y + hi + 1, c);
            if x == xe && y == ye {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Draws `s` with its top-left corner at `(x, y)`, each font pixel `scale` pixels wide.
    /// Characters are `6 * scale` apart.
    pub fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, c: Rgb) {
        for (k, ch) in s.chars().enumerate() {
            let gx = x + 6 * scale * k as i64;
            for (row, bits) in glyph(ch).iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        let (px, py) = (gx + col * scale, y + row as i64 * scale);
                        self.fill(px, py, px + scale, py + scale, c);
                    }
                }
            }
        }
    }

    /// Width in pixels of `s` drawn at `scale`.
    pub fn text_width(s: &str, scale: i64) -> i64 {
        (6 * s.chars().count() as i64 - 1).max(0) * scale
    }

    /// Writes the canvas as a PNG (atomically).
    pub fn save(&self, path: &Path) -> Result<()> {
        write_rgb_png(path, self.width, self.height, &self.rgb)
    }
}

/// Writes 8-bit RGB pixels (row-major, 3 bytes each) as a PNG.
pub fn write_rgb_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    if rgb.len() != width as usize * height as usize * 3 {
        return Err(Error::Invalid(format!("{}: pixel buffer does not match {width}x{height}", path.display())));
    }
    write_atomic(path, |w| {
        let mut enc = png::Encoder::new(w, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(rgb).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)
    })
}

/// The smallest tick step of 1, 2 or 5 times a power of ten that is at least `raw`.
pub fn nice_step(raw: f64) -> f64 {
    if !(raw > 0.0) || !raw.is_finite() {
        return 1.0;
    }
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| *s >= raw).unwrap_or(10.0 * mag)
}

/// Axes drawn on a [`Canvas`] region, mapping data coordinates to pixels.
///
/// ```
/// use mrfmap::outputs::{Canvas, PlotArea};
/// let mut c = Canvas::new(400, 300);
/// let area = PlotArea::new(&mut c, (0, 0, 400, 300), (0.0, 4.0), (0.0, 0.1), "DEPTH (M)", "STD (M)", "NOISE");
/// area.polyline(&mut c, &[(0.0, 0.0), (4.0, 0.1)], [200, 0, 0]);
/// let (x, y) = area.to_pixel(4.0, 0.1);
/// assert_eq!(c.pixel(x.round() as u32, y.round() as u32), [200, 0, 0]);
/// ```
#[derive(Clone, Copy, Debug)]
pub struct PlotArea {
    left: f64,
    top: f64,
    right: f64,
    bottom: f64,
    x: (f64, f64),
    y: (f64, f64),
}

impl PlotArea {
    /// Draws title, axes, ticks with labels and light grid lines in the pixel rectangle
    /// `(x0, y0, x1, y1)` for the data ranges `x` and `y`.
    pub fn new(
        c: &mut Canvas,
        (x0, y0, x1, y1): (i64, i64, i64, i64),
        x: (f64, f64),
        y: (f64, f64),
        x_label: &str,
        y_label: &str,
        title: &str,
    ) -> Self {
        let widen = |(a, b): (f64, f64)| if b > a { (a, b) } else { (a - 0.5, a + 0.5) };
        let (x, y) = (widen(x), widen(y));
        let area = PlotArea {
            left: (x0 + 70) as f64,
            top: (y0 + 30) as f64,
            right: (x1 - 15) as f64,
            bottom: (y1 - 40) as f64,
            x,
            y,
        };
        let black = [0, 0, 0];
        let grey = [225, 225, 225];
        c.text(x0 + 70, y0 + 8, title, 2, black);
        for (lo, hi, horizontal) in [(x.0, x.1, true), (y.0, y.1, false)] {
            let step = nice_step((hi - lo) / 6.0);
            let mut t = (lo / step).ceil() * step;
            while t <= hi + 1e-9 * step {
                let label = format_tick(t, step);
                if horizontal {
                    let (px, _) = area.to_pixel(t, y.0);
                    c.line((px, area.top), (px, area.bottom), 1, grey);
                    let w = Canvas::text_width(&label, 1);
                    c.text(px as i64 - w / 2, area.bottom as i64 + 6, &label, 1, black);
                } else {
                    let (_, py) = area.to_pixel(x.0, t);
                    c.line((area.left, py), (area.right, py), 1, grey);
                    let w = Canvas::text_width(&label, 1);
                    c.text(area.left as i64 - 6 - w, py as i64 - 3, &label, 1, black);
                }
                t += step;
            }
        }
        c.line((area.left, area.top), (area.left, area.bottom), 1, black);
        c.line((area.left, area.bottom), (area.right, area.bottom), 1, black);
        let w = Canvas::text_width(x_label, 1);
        c.text(((area.left + area.right) / 2.0) as i64 - w / 2, y1 - 16, x_label, 1, black);
        c.text(x0 + 4, y0 + 30 - 14, y_label, 1, black);
        area
    }

    /// Pixel position of data point `(x, y)` (not clipped).
    pub fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let px = self.left + (self.right - self.left) * (x - self.x.0) / (self.x.1 - self.x.0);
        let py = self.bottom - (self.bottom - self.top) * (y - self.y.0) / (self.y.1 - self.y.0);
        (px, py)
    }

    /// Joins the points with 2-pixel lines; points outside the y range are clamped to it.
    pub fn polyline(&self, c: &mut Canvas, points: &[(f64, f64)], colour: Rgb) {
        let clamp = |(x, y): (f64, f64)| self.to_pixel(x, y.clamp(self.y.0, self.y.1));
        for w in points.windows(2) {
            c.line(clamp(w[0]), clamp(w[1]), 2, colour);
        }
    }

    /// A legend entry (colour swatch and label) in the top-right corner, `row` lines down.
    pub fn legend(&self, c: &mut Canvas, row: usize, label: &str, colour: Rgb) {
        let w = Canvas::text_width(label, 1);
        let x = self.right as i64 - w - 6;
        let y = self.top as i64 + 6 + 12 * row as i64;
        c.fill(x - 16, y + 2, x - 4, y + 5, colour);
        c.text(x, y, label, 1, [0, 0, 0]);
    }
}

/// The part of segment `a`-`b` inside the box `lo`-`hi` (Liang-Barsky); `None` if none is,
/// or if an endpoint is not finite.
fn clip_segment(a: (f64, f64), b: (f64, f64), lo: (f64, f64), hi: (f64, f64)) -> Option<((f64, f64), (f64, f64))> {
    if ![a.0, a.1, b.0, b.1].iter().all(|v| v.is_finite()) {
        return None;
    }
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [(-dx, a.0 - lo.0), (dx, hi.0 - a.0), (-dy, a.1 - lo.1), (dy, hi.1 - a.1)] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then_some(((a.0 + t0 * dx, a.1 + t0 * dy), (a.0 + t1 * dx, a.1 + t1 * dy)))
}

/// A tick label with as many decimals as the step needs.
fn format_tick(t: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let t = if t.abs() < 1e-12 * step.max(1.0) { 0.0 } else { t };
    format!("{t:.decimals$}")
}

/// One line of a [`line_plot`]: label, colour, points `(x, y)`.
pub type Series = (String, Rgb, Vec<(f64, f64)>);

/// A 720x480 line plot of `series` with a dot at every point; with `log_y` the y axis is
/// log10 of the values (points at or below 0 are left out).
///
/// ```
/// use mrfmap::outputs::line_plot;
/// let series = vec![("MAE".to_string(), [200, 0, 0], vec![(0.0, 0.3), (10.0, 0.1)])];
/// let c = line_plot("MAE OVER TIME", "FRAMES", "MAE", &series, false);
/// assert_eq!((c.width(), c.height()), (720, 480));
/// ```
pub fn line_plot(title: &str, x_label: &str, y_label: &str, series: &[Series], log_y: bool) -> Canvas {
    let y_of = |y: f64| if log_y { (y > 0.0).then(|| y.log10()) } else { Some(y) };
    let shown: Vec<Vec<(f64, f64)>> = series
        .iter()
        .map(|s| {
            s.2.iter()
                .filter_map(|&(x, y)| Some((x, y_of(y)?)))
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .collect()
        })
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in shown.iter().flatten() {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    let y_range = if log_y { (y0.floor(), y1.ceil()) } else { (y0, y1) };
    let mut c = Canvas::new(720, 480);
    let area = PlotArea::new(&mut c, (0, 0, 720, 480), (x0, x1), y_range, x_label, y_label, title);
    for (row, ((label, colour, _), points)) in series.iter().zip(&shown).enumerate() {
        area.polyline(&mut c, points, *colour);
        for &(x, y) in points {
            let (px, py) = area.to_pixel(x, y);
            c.fill(px as i64 - 3, py as i64 - 3, px as i64 + 4, py as i64 + 4, *colour);
        }
        area.legend(&mut c, row, label, *colour);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glyphs_are_distinct_and_fit_five_columns() {
        for (i, (a, ga)) in FONT.iter().enumerate() {
            assert!(ga.iter().all(|r| r & !0x1F == 0), "{a}");
            for (b, gb) in &FONT[i + 1..] {
                assert!(a == b || ga != gb, "{a} and {b} look alike");
                assert_ne!(a, b, "{a} defined twice");
            }
        }
        assert_eq!(glyph('m'), glyph('M'));
        assert_eq!(glyph('~'), glyph('?'));
    }

    #[test]
    fn ticks_and_lines() {
        assert_eq!(nice_step(0.013), 0.02);
        assert_eq!(nice_step(0.27), 0.5);
        assert_eq!(nice_step(4.0), 5.0);
        assert_eq!(format_tick(0.30000000000000004, 0.1), "0.3");
        assert_eq!(format_tick(-1e-17, 0.1), "0.0");
        let mut c = Canvas::new(10, 10);
        c.line((0.0, 0.0), (9.0, 9.0), 1, [1, 2, 3]);
        assert!((0..10).all(|i| c.pixel(i, i) == [1, 2, 3]));
        assert_eq!(c.pixel(0, 9), [255; 3]);
        c.line((-1e9, 5.0), (1e9, 5.0), 1, [9, 9, 9]); // far outside: terminates
    }
}
