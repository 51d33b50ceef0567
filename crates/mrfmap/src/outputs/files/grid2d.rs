//! 2D occupancy grids in the ROS `map_server` format (what `map_saver` writes and
//! `map_server` / `nav2_map_server` load): an 8-bit binary PGM and a YAML file beside it.
//!
//! Cells are written trinary, as `map_saver` does: occupied 0 (black), free 254, unknown 205.
//! With `negate: 0` the server reads a pixel `v` as `p = (255 - v) / 255` and calls it
//! occupied above `occupied_thresh` (0.65), free below `free_thresh` (0.196), unknown between;
//! the three values land unambiguously in those classes. Our own threshold decides the class.
//! The PGM's first row is the grid's highest `y`; `origin` is the world pose of the lower-left
//! pixel's corner.
//!
//! Optionally a second picture holds the standard deviation per cell (`<stem>-sigma.pgm`,
//! linear from black at 0 to white at 0.5, the largest a probability can have; unknown cells
//! white).

use std::io::Write;
use std::path::{Path, PathBuf};

use yaml_rust2::{Yaml, YamlLoader};

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::map::Grid2d;

/// Pixel values `map_saver` writes.
const OCCUPIED: u8 = 0;
const FREE: u8 = 254;
const UNKNOWN: u8 = 205;
/// The thresholds written to the YAML (`map_saver`'s defaults).
pub const OCCUPIED_THRESH: f64 = 0.65;
/// See [`OCCUPIED_THRESH`].
pub const FREE_THRESH: f64 = 0.196;

/// What [`write_map_server`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid2dFiles {
    /// The occupancy image.
    pub image: PathBuf,
    /// The sigma image, if asked for.
    pub sigma: Option<PathBuf>,
    /// Occupied, free and unknown cells.
    pub counts: [usize; 3],
}

/// Writes `grid` as `yaml` plus `<stem>.pgm` beside it (and `<stem>-sigma.pgm` with `sigma`);
/// a cell is occupied when its occupancy is above `threshold`.
pub fn write_map_server(grid: &Grid2d, yaml: &Path, threshold: f32, sigma: bool) -> Result<Grid2dFiles> {
    let stem = yaml
        .file_stem()
        .and_then(|s| s.to_str())
        .ok_or_else(|| Error::file(yaml, "needs a file name such as map.yaml"))?;
    let dir = yaml.parent().unwrap_or(Path::new(""));
    let image = dir.join(format!("{stem}.pgm"));
    let mut counts = [0; 3];
    let pixels = rows_top_down(grid, |c| match c {
        Some((p, _)) if p > threshold => {
            counts[0] += 1;
            OCCUPIED
        }
        Some(_) => {
            counts[1] += 1;
            FREE
        }
        None => {
            counts[2] += 1;
            UNKNOWN
        }
    });
    write_pgm(&image, grid, &pixels)?;
    let sigma_image = if sigma {
        let path = dir.join(format!("{stem}-sigma.pgm"));
        let pixels = rows_top_down(grid, |c| match c {
            Some((_, s)) => (s.clamp(0.0, 0.5) * 510.0).round() as u8,
            None => 255,
        });
        write_pgm(&path, grid, &pixels)?;
        Some(path)
    } else {
        None
    };
    let text = format!(
        "image: {stem}.pgm\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\n\
         occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n",
        grid.resolution, grid.origin[0], grid.origin[1]
    );
    write_atomic(yaml, |w| w.write_all(text.as_bytes()))?;
    Ok(Grid2dFiles { image, sigma: sigma_image, counts })
}

/// One byte per cell, rows from the highest y down (image order).
fn rows_top_down(grid: &Grid2d, mut pixel: impl FnMut(Option<(f32, f32)>) -> u8) -> Vec<u8> {
    let mut out = Vec::with_capacity(grid.width * grid.height);
    for j in (0..grid.height).rev() {
        out.extend((0..grid.width).map(|i| pixel(grid.cell(i, j))));
    }
    out
}

fn write_pgm(path: &Path, grid: &Grid2d, pixels: &[u8]) -> Result<()> {
    write_atomic(path, |w| {
        write!(
            w,
            "P5\n# mrfmap occupancy grid, {} m per cell\n{} {}\n255\n",
            grid.resolution, grid.width, grid.height
        )?;
        w.write_all(pixels)
    })
}

/// A map read back as `map_server` reads it: per cell (row-major from the lowest y)
/// `Some(true)` occupied, `Some(false)` free, `None` unknown; with resolution and origin.
#[derive(Clone, Debug, PartialEq)]
pub struct MapServerGrid {
    /// Metres per cell.
    pub resolution: f64,
    /// `(x, y, yaw)` of the lower-left corner.
    pub origin: [f64; 3],
    /// Cells per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Classified cells.
    pub cells: Vec<Option<bool>>,
}

/// Reads a `map_server` YAML and its PGM, classifying pixels with the file's thresholds and
/// `negate` as `map_server` does in trinary mode.
pub fn read_map_server(yaml: &Path) -> Result<MapServerGrid> {
    let text = std::fs::read_to_string(yaml).map_err(|e| Error::io(yaml, e))?;
    let bad = |m: String| Error::file(yaml, m);
    let docs = YamlLoader::load_from_str(&text).map_err(|e| bad(format!("not YAML: {e}")))?;
    let doc = docs.first().filter(|d| d.as_hash().is_some()).ok_or_else(|| bad("not a map_server YAML file".into()))?;
    let field = |name: &str| -> Result<&Yaml> {
        let v = &doc[name];
        if v.is_badvalue() { Err(bad(format!("missing `{name}`"))) } else { Ok(v) }
    };
    // YAML writes 1 and 1.0 as different types; map_server reads both as numbers.
    let as_number = |v: &Yaml| v.as_f64().or_else(|| v.as_i64().map(|i| i as f64));
    let number = |name: &str| -> Result<f64> {
        let v = field(name)?;
        as_number(v).ok_or_else(|| bad(format!("`{name}` is not a number: {v:?}")))
    };
    let origin: Vec<f64> = field("origin")?
        .as_vec()
        .and_then(|v| v.iter().map(as_number).collect())
        .ok_or_else(|| bad("`origin` must be [x, y, yaw]".into()))?;
    let origin: [f64; 3] = origin.try_into().map_err(|_| bad("`origin` must be [x, y, yaw]".into()))?;
    // `negate` is 0 or 1 in map_server's files; a YAML boolean means the same.
    let negate = match field("negate")? {
        Yaml::Boolean(b) => *b,
        v => as_number(v).ok_or_else(|| bad(format!("`negate` is not 0, 1 or a boolean: {v:?}")))? != 0.0,
    };
    let (occ, free, resolution) = (number("occupied_thresh")?, number("free_thresh")?, number("resolution")?);
    let image = field("image")?.as_str().ok_or_else(|| bad("`image` is not a file name".into()))?;
    let image = yaml.parent().unwrap_or(Path::new("")).join(image);
    let bytes = std::fs::read(&image).map_err(|e| Error::io(&image, e))?;
    let (width, height, pixels) = parse_pgm(&bytes).map_err(|m| Error::file(&image, m))?;
    let mut cells = vec![None; width * height];
    for (row, line) in pixels.chunks(width).enumerate() {
        let j = height - 1 - row;
        for (i, &v) in line.iter().enumerate() {
            let v = if negate { v as f64 } else { 255.0 - v as f64 };
            let p = v / 255.0;
            cells[j * width + i] = if p > occ {
                Some(true)
            } else if p < free {
                Some(false)
            } else {
                None
            };
        }
    }
    Ok(MapServerGrid { resolution, origin, width, height, cells })
}

/// Width, height and pixels of an 8-bit binary PGM (comments allowed in the header).
fn parse_pgm(bytes: &[u8]) -> std::result::Result<(usize, usize, &[u8]), String> {
    let mut pos = 0;
    let mut token = || -> std::result::Result<&[u8], String> {
        loop {
            while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
                pos += 1;
            }
            if bytes.get(pos) == Some(&b'#') {
                while pos < bytes.len() && bytes[pos] != b'\n' {
                    pos += 1;
                }
                continue;
            }
            break;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        (pos > start).then(|| &bytes[start..pos]).ok_or_else(|| "truncated PGM header".to_string())
    };
    if token()? != b"P5" {
        return Err("not a binary PGM (P5)".into());
    }
    let mut num = || -> std::result::Result<usize, String> {
        std::str::from_utf8(token()?)
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| "bad PGM header number".to_string())
    };
    let (w, h, max) = (num()?, num()?, num()?);
    if max != 255 {
        return Err(format!("only 8-bit PGMs are read, this one has maxval {max}"));
    }
    let start = pos + 1; // one whitespace byte ends the header
    let need = w.checked_mul(h).ok_or("PGM size overflows")?;
    let data = bytes.get(start..).filter(|d| d.len() >= need).ok_or("PGM pixel data is truncated")?;
    Ok((w, h, &data[..need]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_server_reads_what_we_write() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let cells = vec![Some((0.9, 0.1)), Some((0.2, 0.3)), None, Some((0.5, 0.5)), None, Some((0.51, 0.0))];
        let grid = Grid2d { resolution: 0.05, origin: [-1.0, 2.5], width: 3, height: 2, cells };
        let files = write_map_server(&grid, &dir.join("m.yaml"), 0.5, true).unwrap();
        assert_eq!(files.counts, [2, 2, 2]);
        let back = read_map_server(&dir.join("m.yaml")).unwrap();
        assert_eq!((back.width, back.height, back.resolution, back.origin), (3, 2, 0.05, [-1.0, 2.5, 0.0]));
        assert_eq!(back.cells, vec![Some(true), Some(false), None, Some(false), None, Some(true)]);
        let sigma = std::fs::read(files.sigma.unwrap()).unwrap();
        let (_, _, px) = parse_pgm(&sigma).unwrap();
        // Top row is y row 1: sigma 0.5 -> 255, unknown -> 255, 0 -> 0.
        assert_eq!(px, &[255, 255, 0, 51, 153, 255]);
        // What other tools write: quoted names, comments, integers, a boolean, other keys in
        // another order (the line-prefix reader took `image: "m.pgm"  # x` as a file name).
        let other = "# saved by hand\nmode: trinary\nnegate: false\norigin: [-1, 2.5, 0]  # x, y, yaw\n\
                     image: \"m.pgm\"  # the picture\nresolution: 0.05\noccupied_thresh: 0.65\nfree_thresh: 0.196\n";
        std::fs::write(dir.join("m.yaml"), other).unwrap();
        let again = read_map_server(&dir.join("m.yaml")).unwrap();
        assert_eq!((again.origin, again.cells.clone()), (back.origin, back.cells.clone()));
        // Broken files name what is wrong.
        std::fs::write(dir.join("m.yaml"), "image: [m.pgm\n").unwrap();
        assert!(read_map_server(&dir.join("m.yaml")).unwrap_err().to_string().contains("not YAML"));
        let fine = other.replace("resolution: 0.05", "resolution: fine");
        std::fs::write(dir.join("m.yaml"), fine).unwrap();
        let e = read_map_server(&dir.join("m.yaml")).unwrap_err().to_string();
        assert!(e.contains("m.yaml") && e.contains("`resolution` is not a number"), "{e}");
        std::fs::write(dir.join("m.yaml"), "image: m.pgm\nresolution: 0.05\n").unwrap();
        assert!(read_map_server(&dir.join("m.yaml")).unwrap_err().to_string().contains("missing `origin`"));
        assert!(parse_pgm(b"P2\n1 1\n255\n0").unwrap_err().contains("not a binary PGM"));
        assert!(parse_pgm(b"P5\n4 4\n255\n\x00").unwrap_err().contains("truncated"));
        assert!(parse_pgm(b"P5\n1 1\n65535\n\x00\x00").unwrap_err().contains("8-bit"));
    }
}
