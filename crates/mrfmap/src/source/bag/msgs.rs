//! The ROS messages mrfmap reads from bags, decoded by hand from CDR (ROS 2) or ROS 1's
//! serialisation: a depth image, its
//! camera's intrinsics, transforms and poses. Fields we do not use are read past, not kept.

use super::cdr::{Cdr, CdrResult, Encoding};
use crate::frames::DepthImage;

/// The message types read here, by their ROS 2 names.
pub const TYPES: [&str; 9] = [
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/msg/CameraInfo",
    "tf2_msgs/msg/TFMessage",
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/PointCloud2",
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
];

/// Decodes `data` as a message of `msgtype` (one of [`TYPES`]) and drops it: whether this
/// module can read it, and why not (what the fuzz target and its regression test call).
pub fn check(msgtype: &str, data: &[u8], encoding: Encoding) -> CdrResult<()> {
    match msgtype {
        "sensor_msgs/msg/Image" => depth_image(data, encoding).map(drop),
        "sensor_msgs/msg/CompressedImage" => compressed_depth(data, encoding).map(drop),
        "sensor_msgs/msg/CameraInfo" => camera_info(data, encoding).map(drop),
        "tf2_msgs/msg/TFMessage" => tf_message(data, encoding).map(drop),
        "sensor_msgs/msg/LaserScan" => laser_scan(data, encoding).map(drop),
        "sensor_msgs/msg/PointCloud2" => point_cloud(data, encoding).map(drop),
        "geometry_msgs/msg/PoseStamped" => pose(data, encoding, false).map(drop),
        "nav_msgs/msg/Odometry" | "geometry_msgs/msg/TransformStamped" => pose(data, encoding, true).map(drop),
        other => Err(format!("{other} is not a message type mrfmap reads")),
    }
}

/// [`check`] of a message behind one tag byte (the fuzz target's input, and its kept
/// findings'): `tag % 7` picks the type, the first seven of [`TYPES`] (Odometry for 6 when
/// bit 3 is set), and bit 4 ROS 1's serialisation instead of CDR.
pub fn check_tagged(data: &[u8]) -> CdrResult<()> {
    let Some((&tag, message)) = data.split_first() else { return Err("empty input".into()) };
    let encoding = if tag & 16 != 0 { Encoding::Ros1 } else { Encoding::Cdr };
    let msgtype = match tag % 7 {
        6 if tag & 8 != 0 => "nav_msgs/msg/Odometry",
        k => TYPES[k as usize],
    };
    check(msgtype, message, encoding)
}

/// `std_msgs/Header`: stamp (seconds) and frame id.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Stamp in seconds.
    pub stamp: f64,
    /// Coordinate frame.
    pub frame_id: String,
}

fn header(c: &mut Cdr) -> CdrResult<Header> {
    if c.ros1 {
        c.u32("header.seq")?;
    }
    let sec = c.i32("header.stamp.sec")?;
    let nanosec = c.u32("header.stamp.nanosec")?;
    Ok(Header { stamp: sec as f64 + nanosec as f64 * 1e-9, frame_id: c.string("header.frame_id")? })
}

/// A rigid transform: translation and unit quaternion `[x, y, z, w]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Translation (metres).
    pub translation: [f64; 3],
    /// Rotation as a quaternion `[x, y, z, w]`.
    pub rotation: [f64; 4],
}

fn transform(c: &mut Cdr, what: &str) -> CdrResult<Transform> {
    Ok(Transform { translation: c.f64s::<3>(what)?, rotation: c.f64s::<4>(what)? })
}

/// A depth image decoder: [`depth_image`] or [`compressed_depth`].
pub type DecodeImage = fn(&[u8], Encoding) -> CdrResult<(Header, DepthImage)>;

/// The header of a `sensor_msgs/Image` or `CompressedImage` (both begin with it), without
/// decoding the image.
pub fn image_header(data: &[u8], encoding: Encoding) -> CdrResult<Header> {
    header(&mut Cdr::with(data, encoding)?)
}

/// `sensor_msgs/Image` holding depth: `16UC1` (millimetres) or `32FC1` (metres).
pub fn depth_image(data: &[u8], encoding: Encoding) -> CdrResult<(Header, DepthImage)> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    let height = c.u32("height")?;
    let width = c.u32("width")?;
    let encoding = c.string("encoding")?;
    let big = c.u8("is_bigendian")? != 0;
    let step = c.u32("step")? as usize;
    let pixels = c.byte_seq("data")?;
    let (bytes_per, scale) = match encoding.as_str() {
        "16UC1" | "mono16" => (2, 1e-3),
        "32FC1" => (4, 1.0),
        other => return Err(format!("depth image encoding {other:?} is not 16UC1 (mm) or 32FC1 (m)")),
    };
    let (w, h_px) = (width as usize, height as usize);
    if w == 0 || h_px == 0 || w > crate::frames::MAX_SIDE as usize || h_px > crate::frames::MAX_SIDE as usize {
        return Err(format!("image size {width}x{height} is not a depth image's"));
    }
    if step < w * bytes_per || pixels.len() < step * (h_px - 1) + w * bytes_per {
        return Err(format!(
            "{width}x{height} {encoding} image with step {step} needs more than its {} bytes",
            pixels.len()
        ));
    }
    let mut out = Vec::with_capacity(w * h_px);
    for row in 0..h_px {
        let line = &pixels[row * step..row * step + w * bytes_per];
        for px in line.chunks_exact(bytes_per) {
            let z = if bytes_per == 2 {
                let v = if big { u16::from_be_bytes([px[0], px[1]]) } else { u16::from_le_bytes([px[0], px[1]]) };
                v as f32 * scale as f32
            } else {
                let b = [px[0], px[1], px[2], px[3]];
                if big { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) }
            };
            // NaN, infinity and 0 are "no return", as in the dataset reader.
            out.push(if z.is_finite() && z > 0.0 { z } else { 0.0 });
        }
    }
    let image = DepthImage::from_vec(width, height, out).ok_or("image size does not match its data")?;
    Ok((h, image))
}

/// A decoded `sensor_msgs/LaserScan`: header, `(angle, range or None for a miss)` per beam,
/// and `range_max`.
pub type LaserScan = (Header, Vec<(f64, Option<f64>)>, f64);

/// `sensor_msgs/LaserScan` as beams in the scan's frame: `(angle, range or None for no
/// return)`; readings below `range_min` (or NaN) measured nothing and are dropped, readings at
/// or beyond `range_max` (or infinite) are misses. Also `range_max`.
pub fn laser_scan(data: &[u8], encoding: Encoding) -> CdrResult<LaserScan> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    let angle_min = c.f32("angle_min")? as f64;
    c.f32("angle_max")?;
    let increment = c.f32("angle_increment")? as f64;
    c.f32("time_increment")?;
    c.f32("scan_time")?;
    let (range_min, range_max) = (c.f32("range_min")? as f64, c.f32("range_max")? as f64);
    if !(range_max > 0.0 && range_max.is_finite() && increment.is_finite() && angle_min.is_finite()) {
        return Err(format!(
            "range_max {range_max}, angle_min {angle_min} or angle_increment {increment} is not usable"
        ));
    }
    let n = c.count(4, "ranges")?;
    let mut beams = Vec::with_capacity(n);
    for k in 0..n {
        let r = c.f32("ranges")? as f64;
        let angle = angle_min + k as f64 * increment;
        if r >= range_max {
            beams.push((angle, None));
        } else if r >= range_min && r > 0.0 {
            beams.push((angle, Some(r)));
        }
    }
    Ok((h, beams, range_max))
}

/// `sensor_msgs/PointCloud2`: the points' `x y z` (float32 fields, at any offsets, either
/// byte order), NaN and infinite points dropped.
pub fn point_cloud(data: &[u8], encoding: Encoding) -> CdrResult<(Header, Vec<[f64; 3]>)> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    let (height, width) = (c.u32("height")? as usize, c.u32("width")? as usize);
    let nf = c.count(13, "fields")?;
    let mut offsets = [None; 3];
    for _ in 0..nf {
        let name = c.string("field name")?;
        let offset = c.u32("field offset")? as usize;
        let datatype = c.u8("field datatype")?;
        c.u32("field count")?;
        if let Some(axis) = ["x", "y", "z"].iter().position(|a| *a == name) {
            if datatype != 7 {
                return Err(format!("field {name} has datatype {datatype}, not FLOAT32 (7)"));
            }
            offsets[axis] = Some(offset);
        }
    }
    let [Some(ox), Some(oy), Some(oz)] = offsets else { return Err("the cloud has no x, y and z fields".into()) };
    let big = c.u8("is_bigendian")? != 0;
    let point_step = c.u32("point_step")? as usize;
    let row_step = c.u32("row_step")? as usize;
    let bytes = c.byte_seq("data")?;
    let last = ox.max(oy).max(oz) + 4;
    if point_step < last || row_step < width.saturating_mul(point_step) {
        return Err(format!("point_step {point_step} / row_step {row_step} cannot hold fields up to byte {last}"));
    }
    if height.saturating_mul(row_step) > bytes.len() {
        return Err(format!(
            "{width}x{height} points of {point_step} bytes need more than the {} bytes sent",
            bytes.len()
        ));
    }
    let f = |b: &[u8], o: usize| {
        let a = [b[o], b[o + 1], b[o + 2], b[o + 3]];
        (if big { f32::from_be_bytes(a) } else { f32::from_le_bytes(a) }) as f64
    };
    let mut points = Vec::with_capacity(width * height);
    for row in 0..height {
        for i in 0..width {
            let p = &bytes[row * row_step + i * point_step..];
            let xyz = [f(p, ox), f(p, oy), f(p, oz)];
            if xyz.iter().all(|v| v.is_finite()) {
                points.push(xyz);
            }
        }
    }
    Ok((h, points))
}

/// `sensor_msgs/CompressedImage` in `compressedDepth` format (`compressed_depth_image_transport`):
/// a 12-byte header (format, and the two parameters of 32FC1's inverse-depth quantisation),
/// then a 16-bit PNG or an RVL stream (`cols`, `rows` as u32, then the RVL words). 16UC1
/// images hold millimetres; 32FC1 ones quantised inverse depth, `z = a / (v - b)`.
pub fn compressed_depth(data: &[u8], encoding: Encoding) -> CdrResult<(Header, DepthImage)> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    let format = c.string("format")?;
    let payload = c.byte_seq("data")?;
    let lower = format.to_ascii_lowercase();
    if !lower.contains("compresseddepth") {
        return Err(format!("CompressedImage format {format:?} is not compressedDepth"));
    }
    let inverse = format.starts_with("32FC1");
    if !inverse && !format.starts_with("16UC1") {
        return Err(format!("compressedDepth of {format:?}: only 16UC1 and 32FC1 are read"));
    }
    if payload.len() < 12 {
        return Err("compressedDepth payload shorter than its header".into());
    }
    let param = |i: usize| f32::from_le_bytes(payload[4 + 4 * i..8 + 4 * i].try_into().expect("4 bytes")) as f64;
    let (a, b) = (param(0), param(1));
    let body = &payload[12..];
    let (width, height, raw): (u32, u32, Vec<u16>) = if lower.contains("rvl") {
        rvl(body)?
    } else {
        let img = crate::source::decode_depth_png(std::io::Cursor::new(body), 1.0, None)?;
        (img.width(), img.height(), img.data().iter().map(|v| *v as u16).collect())
    };
    let depth: Vec<f32> = raw
        .iter()
        .map(|&v| match (v, inverse) {
            (0, _) => 0.0,
            (v, false) => v as f32 * 1e-3,
            (v, true) => {
                let z = a / (v as f64 - b);
                if z.is_finite() && z > 0.0 { z as f32 } else { 0.0 }
            }
        })
        .collect();
    let image = DepthImage::from_vec(width, height, depth).ok_or("image size does not match its data")?;
    Ok((h, image))
}

/// Decodes `cols`, `rows` and an RVL stream (Wilson 2017: runs of zeros and of non-zero values
/// coded as zigzag deltas, in 4-bit groups, most significant nibble of each u32 word first).
fn rvl(body: &[u8]) -> CdrResult<(u32, u32, Vec<u16>)> {
    if body.len() < 8 {
        return Err("RVL payload shorter than its size".into());
    }
    let cols = u32::from_le_bytes(body[0..4].try_into().expect("4 bytes"));
    let rows = u32::from_le_bytes(body[4..8].try_into().expect("4 bytes"));
    let n = cols as usize * rows as usize;
    // A few bytes of RVL can describe a huge image of zeros: the size is checked first.
    if cols == 0
        || rows == 0
        || cols > crate::frames::MAX_SIDE
        || rows > crate::frames::MAX_SIDE
        || n > crate::frames::MAX_PIXELS
    {
        return Err(format!("RVL image size {cols}x{rows} is not a depth image's"));
    }
    let words: Vec<u32> =
        body[8..].chunks_exact(4).map(|w| u32::from_le_bytes(w.try_into().expect("4 bytes"))).collect();
    let (mut word, mut left, mut next) = (0u32, 0, 0usize);
    let mut nibble = || -> CdrResult<u32> {
        if left == 0 {
            word = *words.get(next).ok_or("RVL stream ends early")?;
            next += 1;
            left = 8;
        }
        let v = word >> 28;
        word <<= 4;
        left -= 1;
        Ok(v)
    };
    let mut vle = || -> CdrResult<u64> {
        let (mut value, mut shift) = (0u64, 0);
        loop {
            let n = nibble()?;
            value |= ((n & 7) as u64) << shift;
            shift += 3;
            if n & 8 == 0 || shift > 60 {
                return Ok(value);
            }
        }
    };
    let mut out = Vec::new();
    let mut previous: i64 = 0;
    while out.len() < n {
        let zeros = vle()? as usize;
        if zeros > n - out.len() {
            return Err("RVL run longer than the image".into());
        }
        out.resize(out.len() + zeros, 0);
        if out.len() == n {
            break;
        }
        let values = vle()? as usize;
        if values > n - out.len() {
            return Err("RVL run longer than the image".into());
        }
        for _ in 0..values {
            let positive = vle()? as i64;
            let delta = (positive >> 1) ^ -(positive & 1);
            // A corrupt stream can hold deltas near i64's range: saturate, the clamp follows.
            previous = previous.saturating_add(delta);
            out.push(previous.clamp(0, u16::MAX as i64) as u16);
        }
    }
    Ok((cols, rows, out))
}

/// `sensor_msgs/CameraInfo`: size and the intrinsic matrix `K` (row-major 3x3).
pub fn camera_info(data: &[u8], encoding: Encoding) -> CdrResult<(Header, u32, u32, [f64; 9])> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    let height = c.u32("height")?;
    let width = c.u32("width")?;
    c.string("distortion_model")?;
    let n = c.count(8, "d")?;
    for _ in 0..n {
        c.f64("d")?;
    }
    let k = c.f64s::<9>("k")?;
    Ok((h, width, height, k))
}

/// `tf2_msgs/TFMessage`: `(header, child_frame_id, transform)` per entry.
pub fn tf_message(data: &[u8], encoding: Encoding) -> CdrResult<Vec<(Header, String, Transform)>> {
    let mut c = Cdr::with(data, encoding)?;
    // A TransformStamped takes at least 4 + 4 + 4 + 4 + 56 bytes.
    let n = c.count(72, "transforms")?;
    (0..n)
        .map(|_| {
            let h = header(&mut c)?;
            let child = c.string("child_frame_id")?;
            Ok((h, child, transform(&mut c, "transform")?))
        })
        .collect()
}

/// `geometry_msgs/PoseStamped`, `nav_msgs/Odometry` or `geometry_msgs/TransformStamped`: the
/// header and the pose (with `odometry`, the message has a `child_frame_id` before it: Odometry
/// and TransformStamped; the pose is the child's in the header's frame).
pub fn pose(data: &[u8], encoding: Encoding, odometry: bool) -> CdrResult<(Header, Transform)> {
    let mut c = Cdr::with(data, encoding)?;
    let h = header(&mut c)?;
    if odometry {
        c.string("child_frame_id")?;
    }
    Ok((h, transform(&mut c, "pose")?))
}

#[cfg(test)]
pub(crate) mod tests {
    /// A little-endian CDR message built field by field, aligned as CDR aligns.
    #[derive(Default)]
    pub struct Writer(pub Vec<u8>);

    impl Writer {
        pub fn new() -> Self {
            Writer(vec![0, 1, 0, 0])
        }
        fn align(&mut self, n: usize) {
            while !(self.0.len() - 4).is_multiple_of(n) {
                self.0.push(0);
            }
        }
        pub fn u8(&mut self, v: u8) -> &mut Self {
            self.0.push(v);
            self
        }
        pub fn u32(&mut self, v: u32) -> &mut Self {
            self.align(4);
            self.0.extend_from_slice(&v.to_le_bytes());
            self
        }
        pub fn f64(&mut self, v: f64) -> &mut Self {
            self.align(8);
            self.0.extend_from_slice(&v.to_le_bytes());
            self
        }
        pub fn string(&mut self, s: &str) -> &mut Self {
            self.u32(s.len() as u32 + 1);
            self.0.extend_from_slice(s.as_bytes());
            self.0.push(0);
            self
        }
        pub fn bytes(&mut self, b: &[u8]) -> &mut Self {
            self.u32(b.len() as u32);
            self.0.extend_from_slice(b);
            self
        }
        pub fn header(&mut self, sec: i32, nsec: u32, frame: &str) -> &mut Self {
            self.u32(sec as u32).u32(nsec).string(frame)
        }
    }

    use super::*;

    #[test]
    fn depth_images_in_both_encodings_and_bad_ones() {
        let mut w = Writer::new();
        w.header(10, 500_000_000, "cam").u32(1).u32(2).string("16UC1").u8(0).u32(4);
        w.bytes(&[0xE8, 0x03, 0, 0]); // 1000 mm, 0 (no return)
        let (h, img) = depth_image(&w.0, Encoding::Cdr).unwrap();
        assert_eq!((h.stamp, h.frame_id.as_str()), (10.5, "cam"));
        assert_eq!((img.get(0, 0), img.get(1, 0)), (Some(1.0), None));
        let mut w = Writer::new();
        w.header(0, 0, "cam").u32(1).u32(1).string("32FC1").u8(1).u32(4);
        w.bytes(&2.5f32.to_be_bytes());
        assert_eq!(depth_image(&w.0, Encoding::Cdr).unwrap().1.get(0, 0), Some(2.5));
        let mut w = Writer::new();
        w.header(0, 0, "cam").u32(1).u32(1).string("rgb8").u8(0).u32(3).bytes(&[1, 2, 3]);
        assert!(depth_image(&w.0, Encoding::Cdr).unwrap_err().contains("rgb8"));
        let mut w = Writer::new();
        w.header(0, 0, "cam").u32(2).u32(2).string("16UC1").u8(0).u32(4).bytes(&[0; 6]);
        assert!(depth_image(&w.0, Encoding::Cdr).unwrap_err().contains("needs more than"));
        assert!(depth_image(&w.0[..20], Encoding::Cdr).unwrap_err().contains("message ends inside"));
    }

    #[test]
    fn corrupt_rvl_streams_found_by_fuzzing() {
        // A delta near i64::MAX (overflowed `previous`), and a 65535 x 65535 image of zeros
        // (allocated gigabytes before its size was checked).
        let mut body = vec![];
        body.extend_from_slice(&2u32.to_le_bytes());
        body.extend_from_slice(&1u32.to_le_bytes());
        body.extend_from_slice(&[0x1F, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]);
        let _ = rvl(&body);
        let mut huge = vec![];
        huge.extend_from_slice(&65535u32.to_le_bytes());
        huge.extend_from_slice(&65535u32.to_le_bytes());
        huge.extend_from_slice(&[0; 8]);
        assert!(rvl(&huge).unwrap_err().contains("not a depth image's"));
        // Decoding against an independent encoder: the CLI test's Python RVL bag.
    }

    #[test]
    fn laser_scans() {
        let mut w = Writer::new();
        w.header(5, 0, "laser");
        for v in [-1.0f32, 1.0, 0.5, 0.0, 0.1, 0.2, 10.0] {
            w.u32(v.to_bits());
        }
        w.u32(5);
        for r in [1.0f32, f32::NAN, 0.1, 10.0, f32::INFINITY] {
            w.u32(r.to_bits());
        }
        w.u32(0);
        let (h, beams, max) = laser_scan(&w.0, Encoding::Cdr).unwrap();
        assert_eq!((h.frame_id.as_str(), max), ("laser", 10.0));
        assert_eq!(beams, vec![(-1.0, Some(1.0)), (0.5, None), (1.0, None)]);
    }

    #[test]
    fn point_clouds_at_any_offsets() {
        let mut w = Writer::new();
        w.header(1, 0, "lidar").u32(1).u32(3).u32(3);
        for (name, offset) in [("y", 8u32), ("x", 4), ("z", 12)] {
            w.string(name).u32(offset).u8(7).u32(1);
        }
        w.u8(0).u32(16).u32(48);
        let mut data = Vec::new();
        for p in [[1.0f32, 2.0, 3.0], [f32::NAN, 0.0, 0.0], [4.0, 5.0, 6.0]] {
            data.extend_from_slice(&[0u8; 4]);
            for v in [p[0], p[1], p[2]] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        w.bytes(&data).u8(0);
        let (_, pts) = point_cloud(&w.0, Encoding::Cdr).unwrap();
        assert_eq!(pts, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    }

    #[test]
    fn camera_info_tf_and_poses() {
        let mut w = Writer::new();
        w.header(1, 0, "cam").u32(480).u32(640).string("plumb_bob").u32(5);
        for _ in 0..5 {
            w.f64(0.0);
        }
        for v in [525.0, 0.0, 319.5, 0.0, 525.0, 239.5, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        let (_, width, height, k) = camera_info(&w.0, Encoding::Cdr).unwrap();
        assert_eq!((width, height, k[0], k[2], k[5]), (640, 480, 525.0, 319.5, 239.5));
        let mut w = Writer::new();
        w.u32(1).header(2, 0, "map").string("base");
        for v in [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        let tf = tf_message(&w.0, Encoding::Cdr).unwrap();
        assert_eq!((tf[0].0.frame_id.as_str(), tf[0].1.as_str()), ("map", "base"));
        assert_eq!(tf[0].2.translation, [1.0, 2.0, 3.0]);
        let mut w = Writer::new();
        w.u32(1_000_000).header(2, 0, "map");
        assert!(tf_message(&w.0, Encoding::Cdr).unwrap_err().contains("do not fit"));
        let mut w = Writer::new();
        w.header(3, 0, "odom").string("base");
        for v in [4.0, 5.0, 6.0, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        assert_eq!(pose(&w.0, Encoding::Cdr, true).unwrap().1.translation, [4.0, 5.0, 6.0]);
    }
}
