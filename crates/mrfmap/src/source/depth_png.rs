//! 16-bit PNG depth images (TUM / ICL-NUIM: value = z-depth * depth_scale, 0 = no return).

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use crate::error::{Error, Result};
use crate::frames::{DepthImage, MAX_PIXELS, MAX_SIDE};

/// Reads a 16-bit grayscale depth PNG into metres, checking its size against the camera's
/// when `expected` is given.
///
/// 8-bit, colour or paletted PNGs are refused with a message naming the file: silently
/// reading them as depth would build a wrong map.
pub fn read_depth_png(path: &Path, depth_scale: f64, expected: Option<(u32, u32)>) -> Result<DepthImage> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    decode_depth_png(BufReader::new(file), depth_scale, expected).map_err(|m| Error::file(path, m))
}

/// [`read_depth_png`] from any reader; the error says what is wrong with the image.
pub fn decode_depth_png(
    reader: impl std::io::BufRead + std::io::Seek,
    depth_scale: f64,
    expected: Option<(u32, u32)>,
) -> std::result::Result<DepthImage, String> {
    let mut reader = png::Decoder::new(reader).read_info().map_err(|e| format!("unreadable PNG: {e}"))?;
    let info = reader.info();
    let (width, height) = (info.width, info.height);
    if info.bit_depth != png::BitDepth::Sixteen || info.color_type != png::ColorType::Grayscale {
        return Err(format!(
            "expected a 16-bit grayscale depth PNG, found {:?}-bit {:?}",
            info.bit_depth as u8, info.color_type
        ));
    }
    if let Some((ew, eh)) = expected.filter(|&e| e != (width, height)) {
        return Err(format!("image is {width}x{height} but camera.toml says {ew}x{eh}"));
    }
    // The header's size is checked before the pixel buffer is allocated from it.
    if width > MAX_SIDE || height > MAX_SIDE || width as usize * height as usize > MAX_PIXELS {
        return Err(format!("image is {width}x{height}, larger than any depth sensor's"));
    }
    let inv = (1.0 / depth_scale) as f32;
    fn metres(bytes: &[u8], inv: f32) -> impl Iterator<Item = f32> + '_ {
        bytes.chunks_exact(2).map(move |b| u16::from_be_bytes([b[0], b[1]]) as f32 * inv)
    }
    let unreadable = |e: png::DecodingError| format!("unreadable PNG: {e}");
    let (w, h) = (width as usize, height as usize);
    let data = if reader.info().interlaced {
        // (Interlaced rows come in passes of scattered pixels: the image is decoded whole.)
        let mut buf = vec![0u8; reader.output_buffer_size().ok_or("image too large")?];
        reader.next_frame(&mut buf).map_err(unreadable)?;
        metres(&buf, inv).take(w * h).collect()
    } else {
        // Row by row into metres: the image is never held in 16 bits beside its metres (at
        // 640 x 480, 0.6 MB of a build's peak memory while the next frame is read ahead).
        let mut row = vec![0u8; reader.output_line_size(width).ok_or("image too large")?];
        let mut data = Vec::with_capacity(w * h);
        for _ in 0..h {
            reader.read_row(&mut row).map_err(unreadable)?.ok_or("unreadable PNG: fewer rows than its header says")?;
            data.extend(metres(&row, inv).take(w));
        }
        data
    };
    Ok(DepthImage::from_vec(width, height, data).expect("size checked above"))
}

/// Writes metres as a 16-bit depth PNG (atomically). Depths that do not fit in 16 bits
/// at this scale, and invalid ones, are written as 0 (no return).
pub fn write_depth_png(path: &Path, depth: &DepthImage, depth_scale: f64) -> Result<()> {
    let mut bytes = Vec::with_capacity(depth.data().len() * 2);
    for &z in depth.data() {
        bytes.extend_from_slice(&units(z, depth_scale).to_be_bytes());
    }
    crate::atomic_file::write_atomic(path, |w| {
        let mut enc = png::Encoder::new(w, depth.width(), depth.height());
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        enc.set_compression(png::Compression::Fast);
        let mut writer = enc.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(&bytes).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)
    })
}

/// `depth` as a 16-bit depth PNG at `depth_scale` stores it (what reading it back gives):
/// whole steps of `1 / depth_scale`, 0 where [`write_depth_png`] writes 0.
pub fn quantise_depth(depth: &DepthImage, depth_scale: f64) -> DepthImage {
    let data = depth.data().iter().map(|&z| (f64::from(units(z, depth_scale)) / depth_scale) as f32).collect();
    DepthImage::from_vec(depth.width(), depth.height(), data).expect("same size")
}

/// The 16-bit value stored for `z` metres.
fn units(z: f32, depth_scale: f64) -> u16 {
    let q = (f64::from(z) * depth_scale).round();
    if z > 0.0 && q.is_finite() && q <= f64::from(u16::MAX) { q as u16 } else { 0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_quantises_to_scale() {
        let mut img = DepthImage::new(5, 3);
        img.set(0, 0, 1.23456);
        img.set(4, 2, 6.5);
        img.set(2, 1, 20.0); // beyond 65535 / 5000 m: stored as no return
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("rt.png");
        write_depth_png(&p, &img, 5000.0).unwrap();
        let back = read_depth_png(&p, 5000.0, Some((5, 3))).unwrap();
        assert!((back.get(0, 0).unwrap() - 1.2346).abs() < 1e-6);
        assert_eq!(back.get(4, 2), Some(6.5));
        assert_eq!(back.get(2, 1), None);
        let e = read_depth_png(&p, 5000.0, Some((640, 480))).unwrap_err().to_string();
        assert!(e.contains("rt.png") && e.contains("5x3") && e.contains("640x480"), "{e}");
    }

    /// A file cut short inside its pixel data is an error naming the file, not a panic or an
    /// image with rows of zeros.
    #[test]
    fn refuses_a_truncated_image() {
        let tmp = tempfile::tempdir().unwrap();
        let mut img = DepthImage::new(64, 48);
        for v in 0..48 {
            for u in 0..64 {
                img.set(u, v, 0.5 + (u * 7 + v * 13) as f32 * 0.01);
            }
        }
        let p = tmp.path().join("whole.png");
        write_depth_png(&p, &img, 5000.0).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(read_depth_png(&p, 5000.0, None).unwrap().data().len(), 64 * 48);
        let cut = tmp.path().join("cut.png");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_depth_png(&cut, 5000.0, None).unwrap_err().to_string();
        assert!(e.contains("cut.png") && e.contains("unreadable PNG"), "{e}");
    }

    #[test]
    fn refuses_8_bit_and_garbage() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("eight.png");
        let f = std::fs::File::create(&p).unwrap();
        let mut enc = png::Encoder::new(f, 2, 2);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header().unwrap().write_image_data(&[0; 12]).unwrap();
        let e = read_depth_png(&p, 5000.0, Some((2, 2))).unwrap_err().to_string();
        assert!(e.contains("eight.png") && e.contains("16-bit"), "{e}");
        let g = tmp.path().join("garbage.png");
        std::fs::write(&g, b"not a png at all").unwrap();
        let e = read_depth_png(&g, 5000.0, Some((2, 2))).unwrap_err().to_string();
        assert!(e.contains("garbage.png") && e.contains("unreadable PNG"), "{e}");
    }
}
