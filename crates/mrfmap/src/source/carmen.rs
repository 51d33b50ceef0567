//! CARMEN laser logs (plain or gzip-compressed): the planar-laser format of Radish and most
//! 2D SLAM benchmarks, read into [`RangeScan`]s at the logged (corrected) laser poses.
//!
//! One message per line; these are read, everything else (`ODOM`, `PARAM`, `NEFF`, `#`
//! comments, ...) is skipped:
//!
//! ```text
//! FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta timestamp host logger_timestamp
//! RLASER (the same layout, the rear laser)
//! ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
//!             n r_1 .. r_n m v_1 .. v_m x y theta robot_x robot_y robot_theta
//!             tv rv forward_safety side_safety turn_axis timestamp host logger_timestamp
//! ```
//!
//! `x y theta` is the laser's pose in the world (metres, radians). `FLASER` / `RLASER` beams
//! run counter-clockwise over 180 degrees from `theta - 90` degrees, `pi / n` apart
//! ([`BeamSpacing::FieldOverN`]) or `pi / (n - 1)` apart so the last beam lands on
//! `theta + 90` ([`BeamSpacing::FieldOverNMinusOne`]); readers disagree, so it is a setting.
//! `ROBOTLASER1` gives its own start angle, step and maximum range. A range at or beyond the
//! maximum is a miss ("free up to the maximum"); a range of exactly 0 is a beam that
//! measured nothing and is dropped (misses can be dropped too, [`Misses`]); negative or non-numeric ranges are errors naming the line.
//! A scan becomes a planar [`RangeScan`] at height `z` (the middle of the map's one layer).

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Translation3, UnitQuaternion};

use crate::error::{Error, Result};
use crate::frames::{Beam, NoiseModel, Pose, RangeScan};

/// Angle between consecutive `FLASER` / `RLASER` beams over their 180-degree field.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BeamSpacing {
    /// `pi / n`: beam `k` at `theta - pi/2 + k pi / n` (the last one short of `+pi/2`).
    #[default]
    FieldOverN,
    /// `pi / (n - 1)`: the first and last beams at `theta -+ pi/2`.
    FieldOverNMinusOne,
}

/// What a beam without a return (range at or beyond the maximum) says.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Misses {
    /// Space along it is free up to the maximum range (OctoMap's reading of a max-range beam).
    #[default]
    Free,
    /// Nothing: the beam is dropped (lasers also miss on glass and dark or grazing surfaces,
    /// where "free up to 80 m" would clear walls).
    Ignore,
}

crate::choice::choice!(BeamSpacing, "beam spacing", FieldOverN => "n", FieldOverNMinusOne => "n-1");

crate::choice::choice!(Misses, "misses", Free => "free", Ignore => "ignore");

/// How a log is read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CarmenOptions {
    /// Beam spacing of `FLASER` / `RLASER`.
    pub spacing: BeamSpacing,
    /// Ranges at or beyond this are misses for `FLASER` / `RLASER` (which do not record their
    /// maximum; SICK scanners report about 81.8 m for "no return").
    pub max_range: f64,
}

impl Default for CarmenOptions {
    fn default() -> Self {
        CarmenOptions { spacing: BeamSpacing::default(), max_range: 80.0 }
    }
}

/// Most beams a scan may have (a corrupt count must not allocate gigabytes).
const MAX_BEAMS: usize = 100_000;

/// One laser message.
#[derive(Clone, Debug, PartialEq)]
pub struct LaserReading {
    /// Line of the log (1-based).
    pub line: usize,
    /// `FLASER`, `RLASER` or `ROBOTLASER1`.
    pub message: &'static str,
    /// The log's timestamp (seconds).
    pub timestamp: f64,
    /// Laser pose in the world: x, y (metres), theta (radians).
    pub pose: [f64; 3],
    /// Angle of the first beam relative to theta.
    pub start_angle: f64,
    /// Angle between beams.
    pub step: f64,
    /// Ranges in metres (0: no measurement).
    pub ranges: Vec<f64>,
    /// Ranges at or beyond this are misses.
    pub max_range: f64,
}

impl LaserReading {
    /// This reading as a planar range scan at height `z`, keeping every `beams_every`-th beam
    /// (1: all), starting with the first; misses are kept as "free up to the maximum range"
    /// when `misses` says so, dropped otherwise. `noise` is the range noise model.
    pub fn to_scan(
        &self,
        index: usize,
        z: f64,
        beams_every: usize,
        misses: Misses,
        noise: Option<Arc<NoiseModel>>,
    ) -> Result<RangeScan> {
        let [x, y, theta] = self.pose;
        let pose = Pose::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(0.0, 0.0, theta));
        let beams = self
            .ranges
            .iter()
            .enumerate()
            .step_by(beams_every.max(1))
            .filter(|(_, r)| **r != 0.0 && (misses == Misses::Free || **r < self.max_range))
            .map(|(k, &r)| {
                let a = self.start_angle + k as f64 * self.step;
                Beam { dir: [a.cos(), a.sin(), 0.0], range: (r < self.max_range).then_some(r) }
            })
            .collect();
        RangeScan::new(index, pose, beams, self.max_range, noise)
    }
}

/// A CARMEN log's laser readings, in file order.
#[derive(Clone, Debug)]
pub struct CarmenLog {
    /// The file.
    pub path: PathBuf,
    /// The laser messages.
    pub readings: Vec<LaserReading>,
}

impl CarmenLog {
    /// Reads `path` (gzip-compressed when it starts with the gzip magic bytes).
    pub fn open(path: &Path, options: CarmenOptions) -> Result<Self> {
        if !(options.max_range > 0.0 && options.max_range.is_finite()) {
            return Err(Error::Invalid(format!("laser max range must be positive, got {}", options.max_range)));
        }
        let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut magic = [0u8; 16];
        let n = file.read(&mut magic).map_err(|e| Error::io(path, e))?;
        if let Some(what) = known_file(&magic[..n]) {
            return Err(Error::file(
                path,
                format!(
                    "{what}, not a laser log: build reads a dataset folder (depth/ of PNGs with camera.toml \
                     and groundtruth.txt), a CARMEN laser log or a ROS bag"
                ),
            ));
        }
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let reader: Box<dyn BufRead> = if n >= 2 && magic[..2] == [0x1f, 0x8b] {
            Box::new(BufReader::new(flate2::read::MultiGzDecoder::new(file)))
        } else {
            Box::new(BufReader::new(file))
        };
        let readings = parse_carmen(reader, options).map_err(|m| Error::file(path, m))?;
        if readings.is_empty() {
            return Err(Error::file(path, "no FLASER, RLASER or ROBOTLASER1 messages: not a CARMEN laser log?"));
        }
        Ok(CarmenLog { path: path.to_path_buf(), readings })
    }
}

/// What a file that starts with `head` is, if it is one of the binary files users hand to
/// `build` by mistake (maps, pictures, point clouds, bags named otherwise).
fn known_file(head: &[u8]) -> Option<&'static str> {
    [
        (&b"\x89MRFMAP\n"[..], "an mrfmap map file (mrfmap info or view read it)"),
        (b"\x89PNG", "a PNG image (a dataset's depth/ holds these)"),
        (b"# Octomap OcTree", "an OctoMap file"),
        (b"ply\n", "a PLY file"),
        (b"\x89MCAP", "an MCAP file (name it .mcap to read it as a bag)"),
        (b"#ROSBAG V2.0", "a ROS 1 bag (name it .bag to read it as one)"),
        (b"SQLite format 3", "an SQLite file (a ROS 2 bag is read as .db3)"),
    ]
    .into_iter()
    .find(|(magic, _)| head.starts_with(magic))
    .map(|(_, what)| what)
}

/// Laser readings of a log read from `reader` (decompressed), or a message naming the line
/// that is wrong.
pub fn parse_carmen(reader: impl BufRead, options: CarmenOptions) -> std::result::Result<Vec<LaserReading>, String> {
    let mut out = Vec::new();
    for (i, line) in reader.split(b'\n').enumerate() {
        let n = i + 1;
        let bytes = line.map_err(|e| format!("line {n}: {e} (a truncated or corrupt gzip file?)"))?;
        let text = String::from_utf8_lossy(&bytes);
        let fields: Vec<&str> = text.split_whitespace().collect();
        let reading = match fields.first() {
            Some(&"FLASER") => laser(&fields, "FLASER", options),
            Some(&"RLASER") => laser(&fields, "RLASER", options),
            Some(&"ROBOTLASER1") => robot_laser(&fields),
            _ => continue,
        };
        let mut r = reading.map_err(|m| format!("line {n}: {m}"))?;
        r.line = n;
        out.push(r);
    }
    Ok(out)
}

/// Field `i` as a finite number.
fn number(fields: &[&str], i: usize, what: &str) -> std::result::Result<f64, String> {
    let text = fields.get(i).ok_or_else(|| format!("{}: line ends before {what}", fields[0]))?;
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("{}: {what} is {text:?}, not a finite number", fields[0])),
    }
}

/// A beam count at field `i`, bounded.
fn count(fields: &[&str], i: usize, what: &str) -> std::result::Result<usize, String> {
    let text = fields.get(i).ok_or_else(|| format!("{}: line ends before {what}", fields[0]))?;
    match text.parse::<usize>() {
        Ok(v) if v <= MAX_BEAMS => Ok(v),
        Ok(v) => Err(format!("{}: {what} {v} is more than {MAX_BEAMS}", fields[0])),
        Err(_) => Err(format!("{}: {what} is {text:?}, not a count", fields[0])),
    }
}

/// `n` ranges from field `first`: finite and not negative.
fn ranges(fields: &[&str], first: usize, n: usize) -> std::result::Result<Vec<f64>, String> {
    (0..n)
        .map(|k| {
            let r = number(fields, first + k, &format!("range {k}"))?;
            if r < 0.0 {
                return Err(format!("{}: range {k} is negative ({r})", fields[0]));
            }
            Ok(r)
        })
        .collect()
}

/// Checks the field count: `expected` fields in all.
fn expect_len(fields: &[&str], expected: usize, layout: &str) -> std::result::Result<(), String> {
    if fields.len() != expected {
        return Err(format!("{}: {} fields where {layout} makes {expected}", fields[0], fields.len()));
    }
    Ok(())
}

fn laser(fields: &[&str], message: &'static str, options: CarmenOptions) -> std::result::Result<LaserReading, String> {
    let n = count(fields, 1, "the beam count")?;
    expect_len(fields, n + 11, &format!("{n} ranges"))?;
    let ranges = ranges(fields, 2, n)?;
    let p = n + 2;
    let pose = [number(fields, p, "x")?, number(fields, p + 1, "y")?, number(fields, p + 2, "theta")?];
    let step = match options.spacing {
        BeamSpacing::FieldOverN => std::f64::consts::PI / n.max(1) as f64,
        BeamSpacing::FieldOverNMinusOne => std::f64::consts::PI / n.saturating_sub(1).max(1) as f64,
    };
    Ok(LaserReading {
        line: 0,
        message,
        timestamp: number(fields, p + 6, "timestamp")?,
        pose,
        start_angle: -std::f64::consts::FRAC_PI_2,
        step,
        ranges,
        max_range: options.max_range,
    })
}

fn robot_laser(fields: &[&str]) -> std::result::Result<LaserReading, String> {
    let start_angle = number(fields, 2, "start angle")?;
    let step = number(fields, 4, "angular resolution")?;
    let max_range = number(fields, 5, "maximum range")?;
    if !(max_range > 0.0) {
        return Err(format!("ROBOTLASER1: maximum range {max_range} is not positive"));
    }
    let n = count(fields, 8, "the beam count")?;
    let ranges = ranges(fields, 9, n)?;
    let m = count(fields, 9 + n, "the remission count")?;
    let p = 10 + n + m;
    expect_len(fields, p + 14, &format!("{n} ranges and {m} remissions"))?;
    let pose = [number(fields, p, "x")?, number(fields, p + 1, "y")?, number(fields, p + 2, "theta")?];
    Ok(LaserReading {
        line: 0,
        message: "ROBOTLASER1",
        timestamp: number(fields, p + 11, "timestamp")?,
        pose,
        start_angle,
        step,
        ranges,
        max_range,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &str, options: CarmenOptions) -> std::result::Result<Vec<LaserReading>, String> {
        parse_carmen(text.as_bytes(), options)
    }

    const LOG: &str = "# a comment\nPARAM robot_frontlaser_offset 0.0 nohost 0\nODOM 0 0 0 0 0 0 0.1 h 0.1\n\
        FLASER 4 1.0 0 90.0 2.5 1.0 2.0 1.5707963267948966 0 0 0 12.5 host 12.5\nNEFF 15\n\
        ROBOTLASER1 0 -1.5 3.0 1.0 5.0 0.01 0 3 1.0 6.0 2.0 0 3.0 4.0 0.0 3.0 4.0 0.0 0 0 0 0 0 7.0 h 7.0\n";

    #[test]
    fn reads_flaser_and_robotlaser_lines() {
        let r = read(LOG, CarmenOptions::default()).unwrap();
        assert_eq!(r.len(), 2);
        let f = &r[0];
        assert_eq!(
            (f.line, f.message, f.timestamp, f.pose),
            (4, "FLASER", 12.5, [1.0, 2.0, std::f64::consts::FRAC_PI_2])
        );
        assert!((f.step - std::f64::consts::PI / 4.0).abs() < 1e-15);
        let scan = f.to_scan(0, 0.025, 1, Misses::Free, None).unwrap();
        // Beam 1 (range 0) is dropped; beam 2 (90 m) is a miss; beam 0 points along
        // theta - 90 degrees = world +x.
        assert_eq!(scan.beams.len(), 3);
        assert_eq!(scan.beams.iter().map(|b| b.range).collect::<Vec<_>>(), vec![Some(1.0), None, Some(2.5)]);
        let world = scan.pose.rotation * nalgebra::Vector3::from(scan.beams[0].dir);
        assert!((world.x - 1.0).abs() < 1e-12 && world.y.abs() < 1e-12);
        assert_eq!(scan.pose.translation.vector.z, 0.025);
        // Every second beam: 0 and 2 (1 and 3 skipped).
        let every2: Vec<_> = f.to_scan(0, 0.0, 2, Misses::Free, None).unwrap().beams.iter().map(|b| b.range).collect();
        assert_eq!(every2, vec![Some(1.0), None]);
        let g = &r[1];
        assert_eq!((g.message, g.start_angle, g.step, g.max_range), ("ROBOTLASER1", -1.5, 1.0, 5.0));
        assert_eq!((g.ranges.clone(), g.pose, g.timestamp), (vec![1.0, 6.0, 2.0], [3.0, 4.0, 0.0], 7.0));
        let s = g.to_scan(1, 0.0, 1, Misses::Free, None).unwrap();
        assert_eq!(s.beams.iter().map(|b| b.range).collect::<Vec<_>>(), vec![Some(1.0), None, Some(2.0)]);
        let kept: Vec<_> = g.to_scan(1, 0.0, 1, Misses::Ignore, None).unwrap().beams.iter().map(|b| b.range).collect();
        assert_eq!(kept, vec![Some(1.0), Some(2.0)]);
        let spaced =
            read(LOG, CarmenOptions { spacing: BeamSpacing::FieldOverNMinusOne, ..Default::default() }).unwrap();
        assert!((spaced[0].step - std::f64::consts::PI / 3.0).abs() < 1e-15);
    }

    #[test]
    fn bad_lines_name_the_line_and_the_problem() {
        let cases = [
            ("FLASER 3 1 2 0 0 0 0 0 0 1 h 1\n", "line 1: FLASER: 13 fields where 3 ranges makes 14"),
            ("\nFLASER 2 1 nan 0 0 0 0 0 0 1 h 1\n", "line 2: FLASER: range 1 is \"nan\""),
            ("FLASER 2 1 -2 0 0 0 0 0 0 1 h 1\n", "range 1 is negative"),
            ("FLASER -3 1\n", "not a count"),
            ("FLASER 999999 1\n", "more than 100000"),
            ("RLASER 1 1 0 0 x 0 0 0 1 h 1\n", "theta is \"x\""),
            ("ROBOTLASER1 0 -1.5 3.0 1.0 0 0.01 0 1 1.0 0\n", "maximum range 0 is not positive"),
        ];
        for (text, needle) in cases {
            let e = read(text, CarmenOptions::default()).unwrap_err();
            assert!(e.contains(needle), "{text:?}: {e}");
        }
    }

    #[test]
    fn gzip_logs_and_truncated_gzip() {
        use std::io::Write;
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        for _ in 0..200 {
            gz.write_all(LOG.as_bytes()).unwrap();
        }
        let bytes = gz.finish().unwrap();
        let path = dir.join("log.gz");
        std::fs::write(&path, &bytes).unwrap();
        let log = CarmenLog::open(&path, CarmenOptions::default()).unwrap();
        assert_eq!(log.readings.len(), 400);
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let e = CarmenLog::open(&path, CarmenOptions::default()).unwrap_err().to_string();
        assert!(e.contains("log.gz") && e.contains("truncated or corrupt gzip"), "{e}");
        std::fs::write(&path, "ODOM 0 0 0\n").unwrap();
        let e = CarmenLog::open(&path, CarmenOptions::default()).unwrap_err().to_string();
        assert!(e.contains("not a CARMEN laser log"), "{e}");
        // Maps and pictures handed to build by mistake are named for what they are.
        for (bytes, what) in [(&b"\x89MRFMAP\nxxxx"[..], "mrfmap map file"), (b"\x89PNG\r\n\x1a\n", "PNG image")] {
            std::fs::write(&path, bytes).unwrap();
            let e = CarmenLog::open(&path, CarmenOptions::default()).unwrap_err().to_string();
            assert!(e.contains("log.gz") && e.contains(what) && e.contains("dataset folder"), "{e}");
        }
    }
}
