//! 16-bit PNG depth images (TUM / ICL-NUIM: value = z-depth * depth_scale, 0 = no return).
//!
//! A non-interlaced image (every dataset here) is decoded here, row by row: its chunks read
//! ([`Header`], [`Rows`]), its pixel data inflated by `fdeflate` a few rows at a time into a
//! window that keeps what the inflater may copy from again, and its rows unfiltered here.
//! The `png` crate unfilters a Paeth-filtered 16-bit row one pixel after another, each waiting
//! for the one to its left: on icl-livingroom1, whose rows are all Paeth, that was a quarter
//! of a build's time. Here [`paeth_rows`] unfilters several such rows side by side, each a
//! pixel behind the one above. Interlaced images go to the `png` crate whole.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
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
    mut reader: impl BufRead + Seek,
    depth_scale: f64,
    expected: Option<(u32, u32)>,
) -> std::result::Result<DepthImage, String> {
    let start = reader.stream_position().map_err(|e| format!("unreadable PNG: {e}"))?;
    let header = Header::read(&mut reader)?;
    let (width, height) = (header.width, header.height);
    if header.bit_depth != 16 || header.colour != 0 {
        let colour = png::ColorType::from_u8(header.colour)
            .map_or(format!("colour type {}", header.colour), |c| format!("{c:?}"));
        return Err(format!("expected a 16-bit grayscale depth PNG, found {}-bit {colour}", header.bit_depth));
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
    let data = if header.interlaced {
        // (Interlaced rows come in passes of scattered pixels: the image is decoded whole.)
        reader.seek(SeekFrom::Start(start)).map_err(|e| format!("unreadable PNG: {e}"))?;
        let mut reader = png::Decoder::new(reader).read_info().map_err(unreadable)?;
        let mut buf = vec![0u8; reader.output_buffer_size().ok_or("image too large")?];
        reader.next_frame(&mut buf).map_err(unreadable)?;
        metres(&buf, inv).take(w * h).collect()
    } else {
        // Row by row into metres: the image is never held in 16 bits beside its metres (at
        // 640 x 480, 0.6 MB of a build's peak memory while the next frame is read ahead).
        let (row, stride) = (2 * w, 2 * w + 1);
        let mut rows = Rows::new(reader, BATCH * stride)?;
        // The unfiltered row above (zeros above the first), then a batch of rows.
        let mut pixels = vec![0u8; (BATCH + 1) * row];
        let mut data = Vec::with_capacity(w * h);
        for first in (0..h).step_by(BATCH) {
            let n = BATCH.min(h - first);
            let filtered = rows.take(n * stride)?;
            let mut filters = [0u8; BATCH];
            for (j, f) in filters[..n].iter_mut().enumerate() {
                *f = filtered[j * stride];
                pixels[(j + 1) * row..(j + 2) * row].copy_from_slice(&filtered[j * stride + 1..(j + 1) * stride]);
            }
            unfilter(&filters[..n], &mut pixels, row)?;
            for j in 1..=n {
                data.extend(metres(&pixels[j * row..(j + 1) * row], inv));
            }
            pixels.copy_within(n * row..(n + 1) * row, 0);
        }
        rows.finish()?;
        data
    };
    Ok(DepthImage::from_vec(width, height, data).expect("size checked above"))
}

/// Rows unfiltered together where they are all Paeth-filtered ([`paeth_rows`]). Chosen on
/// icl-livingroom1 at 0.05 m, one thread, whole build (decoding in turn with the frames): 2
/// rows took 1.024x the time of 4, and 8 rows (their pixels no longer fit in registers) 1.043x
/// (8 alternating pairs; BENCHMARKS.md, session 42).
const BATCH: usize = 4;

/// What a PNG's header chunk (IHDR) says.
struct Header {
    width: u32,
    height: u32,
    bit_depth: u8,
    colour: u8,
    interlaced: bool,
}

impl Header {
    /// The PNG signature and the header chunk that must follow it, its checksum checked.
    fn read(reader: &mut impl Read) -> std::result::Result<Header, String> {
        let mut signature = [0u8; 8];
        read_exact(reader, &mut signature)?;
        if signature != [137, 80, 78, 71, 13, 10, 26, 10] {
            return Err("unreadable PNG: not a PNG file (its first 8 bytes are not the PNG signature)".into());
        }
        let (len, kind) = chunk_header(reader)?;
        if &kind != b"IHDR" || len != 13 {
            return Err("unreadable PNG: its first chunk is not a 13-byte header (IHDR)".into());
        }
        let mut d = [0u8; 13];
        read_exact(reader, &mut d)?;
        check_crc(reader, crc32fast::hash(&[&kind[..], &d[..]].concat()), "header (IHDR)")?;
        let be = |i: usize| u32::from_be_bytes([d[i], d[i + 1], d[i + 2], d[i + 3]]);
        let (width, height) = (be(0), be(4));
        if width == 0 || height == 0 || width > 1 << 31 || height > 1 << 31 {
            return Err(format!("unreadable PNG: its header gives a size of {width}x{height}"));
        }
        if d[10] != 0 || d[11] != 0 || d[12] > 1 {
            return Err(format!(
                "unreadable PNG: unknown compression, filter or interlace method ({}, {}, {})",
                d[10], d[11], d[12]
            ));
        }
        Ok(Header { width, height, bit_depth: d[8], colour: d[9], interlaced: d[12] == 1 })
    }
}

/// `buf.len()` bytes, or an error saying the file ends early.
fn read_exact(reader: &mut impl Read, buf: &mut [u8]) -> std::result::Result<(), String> {
    reader.read_exact(buf).map_err(|e| match e.kind() {
        std::io::ErrorKind::UnexpectedEof => "unreadable PNG: the file ends early".to_string(),
        _ => format!("unreadable PNG: {e}"),
    })
}

/// A chunk's data length and type.
fn chunk_header(reader: &mut impl Read) -> std::result::Result<(u32, [u8; 4]), String> {
    let mut b = [0u8; 8];
    read_exact(reader, &mut b)?;
    let len = u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
    if len > 1 << 31 {
        return Err(format!("unreadable PNG: a chunk claims {len} bytes"));
    }
    Ok((len, [b[4], b[5], b[6], b[7]]))
}

/// Reads a chunk's stored checksum and compares it with `crc`, computed over its type and data.
fn check_crc(reader: &mut impl Read, crc: u32, what: &str) -> std::result::Result<(), String> {
    let mut b = [0u8; 4];
    read_exact(reader, &mut b)?;
    if u32::from_be_bytes(b) != crc {
        return Err(format!("unreadable PNG: the checksum of its {what} is wrong"));
    }
    Ok(())
}

/// Bytes the inflater may copy from again (deflate's window).
const LOOKBACK: usize = 32 * 1024;

/// Room the window keeps for inflating beyond the bytes it must hold.
const SLACK: usize = 32 * 1024;

/// A non-interlaced PNG's pixel data after its header: the chunks before the first IDAT are
/// skipped, the IDAT chunks read in turn (their checksums checked) and inflated into a window
/// that keeps the last [`LOOKBACK`] bytes inflated as well as those not yet taken.
struct Rows<R> {
    reader: R,
    inflater: fdeflate::Decompressor,
    /// The IDAT chunk being read; `None` after the last.
    chunk: Option<Chunk>,
    window: Vec<u8>,
    /// Inflated bytes end at `filled`; those before `taken` were handed out.
    filled: usize,
    taken: usize,
}

impl<R: BufRead> Rows<R> {
    /// The pixel data of the image `reader` is at, just after its header, taken at most
    /// `most` bytes at a time.
    fn new(mut reader: R, most: usize) -> std::result::Result<Self, String> {
        let chunk = loop {
            let (len, kind) = chunk_header(&mut reader)?;
            match &kind {
                b"IDAT" => break Chunk::idat(len),
                b"IEND" => return Err("unreadable PNG: it has no pixel data (IDAT)".into()),
                // (Other chunks, palette and text alike, do not change 16-bit grey pixels.)
                _ => skip(&mut reader, u64::from(len) + 4)?,
            }
        };
        let mut inflater = fdeflate::Decompressor::new();
        // (As the png crate does: the chunks' checksums already cover the data.)
        inflater.ignore_adler32();
        let window = vec![0; LOOKBACK + most + 2 * SLACK];
        Ok(Rows { reader, inflater, chunk: Some(chunk), window, filled: 0, taken: 0 })
    }

    /// The next `n` bytes of pixel data (at most the `most` of [`Rows::new`]).
    fn take(&mut self, n: usize) -> std::result::Result<&[u8], String> {
        while self.filled - self.taken < n {
            if self.window.len() - self.filled < SLACK {
                // Keep the bytes not taken and those the inflater may copy from.
                let keep = self.taken.min(self.filled.saturating_sub(LOOKBACK));
                self.window.copy_within(keep..self.filled, 0);
                (self.filled, self.taken) = (self.filled - keep, self.taken - keep);
            }
            self.inflate()?;
        }
        self.taken += n;
        Ok(&self.window[self.taken - n..self.taken])
    }

    /// Reads the rest of the pixel data's chunks, checking their checksums (the last rows may
    /// be taken before the end of the last chunk, which holds the stream's own checksum).
    fn finish(mut self) -> std::result::Result<(), String> {
        while let Some(mut chunk) = self.chunk.take() {
            while chunk.left > 0 {
                let n = chunk.piece(&mut self.reader)?.len();
                chunk.consume(&mut self.reader, n);
            }
            self.chunk = chunk.next(&mut self.reader)?;
        }
        Ok(())
    }

    /// Inflates what the reader has of the current chunk, or moves on to the next chunk.
    fn inflate(&mut self) -> std::result::Result<(), String> {
        const SHORT: &str = "unreadable PNG: fewer rows than its header says";
        let corrupt = |e: fdeflate::DecompressionError| format!("unreadable PNG: corrupt pixel data ({e:?})");
        let Rows { reader, inflater, chunk, window, filled, .. } = self;
        if inflater.is_done() {
            return Err(SHORT.into());
        }
        let Some(c) = chunk else {
            // After the last chunk: what the inflater still holds.
            let (_, made) = inflater.read(&[], window, *filled, true).map_err(corrupt)?;
            *filled += made;
            return if made == 0 { Err(SHORT.into()) } else { Ok(()) };
        };
        if c.left == 0 {
            *chunk = chunk.take().expect("matched above").next(reader)?;
            return Ok(());
        }
        let input = c.piece(reader)?;
        let (used, made) = inflater.read(input, window, *filled, false).map_err(corrupt)?;
        if used == 0 && made == 0 && !inflater.is_done() {
            return Err("unreadable PNG: corrupt pixel data (the inflater made no progress)".into());
        }
        c.consume(reader, used);
        *filled += made;
        Ok(())
    }
}

/// An IDAT chunk being read: its data bytes not read yet, and the checksum of its type and
/// the data read.
struct Chunk {
    left: u32,
    crc: crc32fast::Hasher,
}

impl Chunk {
    /// An IDAT chunk of `len` data bytes, none read.
    fn idat(len: u32) -> Chunk {
        let mut crc = crc32fast::Hasher::new();
        crc.update(b"IDAT");
        Chunk { left: len, crc }
    }

    /// What `reader` holds of the chunk's data next (empty once all is read), or an error if
    /// the file ends first.
    fn piece<'r>(&self, reader: &'r mut impl BufRead) -> std::result::Result<&'r [u8], String> {
        if self.left == 0 {
            return Ok(&[]);
        }
        let input = reader.fill_buf().map_err(|e| format!("unreadable PNG: {e}"))?;
        if input.is_empty() {
            return Err("unreadable PNG: fewer rows than its header says (the file ends inside its pixel data)".into());
        }
        Ok(&input[..input.len().min(self.left as usize)])
    }

    /// The first `n` bytes of [`Chunk::piece`] read.
    fn consume(&mut self, reader: &mut impl BufRead, n: usize) {
        if let Ok(input) = reader.fill_buf() {
            self.crc.update(&input[..n]);
        }
        reader.consume(n);
        self.left -= n as u32;
    }

    /// After the chunk's data: checks its checksum and reads the next chunk's header; the next
    /// IDAT chunk, or `None` when another kind follows.
    fn next(self, reader: &mut impl Read) -> std::result::Result<Option<Chunk>, String> {
        check_crc(reader, self.crc.finalize(), "pixel data (IDAT)")?;
        let (len, kind) = chunk_header(reader)?;
        Ok((&kind == b"IDAT").then(|| Chunk::idat(len)))
    }
}

/// Skips `n` bytes, or says the file ends first.
fn skip(reader: &mut impl Read, n: u64) -> std::result::Result<(), String> {
    let skipped =
        std::io::copy(&mut reader.take(n), &mut std::io::sink()).map_err(|e| format!("unreadable PNG: {e}"))?;
    if skipped < n {
        return Err("unreadable PNG: the file ends early".into());
    }
    Ok(())
}

/// Unfilters rows `1..=filters.len()` of `pixels` (rows of `row` bytes, 16-bit grey: two
/// bytes a pixel), row 0 being the unfiltered row above the first.
fn unfilter(filters: &[u8], pixels: &mut [u8], row: usize) -> std::result::Result<(), String> {
    if filters.len() == BATCH && filters.iter().all(|&f| f == 4) {
        paeth_rows::<BATCH>(pixels, row);
        return Ok(());
    }
    for (j, &f) in filters.iter().enumerate() {
        let (above, rest) = pixels[j * row..].split_at_mut(row);
        let cur = &mut rest[..row];
        match f {
            0 => {}
            1 => (2..row).for_each(|i| cur[i] = cur[i].wrapping_add(cur[i - 2])),
            2 => cur.iter_mut().zip(above.iter()).for_each(|(c, a)| *c = c.wrapping_add(*a)),
            3 => (0..row).for_each(|i| {
                let left = if i >= 2 { cur[i - 2] } else { 0 };
                cur[i] = cur[i].wrapping_add(((u16::from(left) + u16::from(above[i])) / 2) as u8)
            }),
            4 => (0..row).for_each(|i| {
                let (left, corner) = if i >= 2 { (cur[i - 2], above[i - 2]) } else { (0, 0) };
                cur[i] = cur[i].wrapping_add(paeth(left, above[i], corner))
            }),
            _ => return Err(format!("unreadable PNG: unknown row filter type {f}")),
        }
    }
    Ok(())
}

/// The Paeth predictor of a byte from its left (`a`), upper (`b`) and upper-left (`c`)
/// neighbours: whichever is nearest `a + b - c`, ties going to `a`, then `b`. Written without
/// branches (the nearest of the three by where `3c - a - b` lies against `min(a, b)` and
/// `max(a, b)`, as stb_image does): with the spec's comparisons the unpredictable branches
/// made Paeth rows slower than the png crate's. Tested against the spec's form on every input.
#[inline(always)]
fn paeth(a: u8, b: u8, c: u8) -> u8 {
    let (a, b, c) = (i16::from(a), i16::from(b), i16::from(c));
    let threshold = 3 * c - (a + b);
    let (lo, hi) = (a.min(b), a.max(b));
    let nearer = if hi <= threshold { lo } else { c };
    (if threshold <= lo { hi } else { nearer }) as u8
}

/// Unfilters rows `1..=K` of `pixels` (rows of `row` bytes, 16-bit grey), all filtered with
/// Paeth, row 0 being the unfiltered row above. Each pixel waits for its left neighbour, so
/// one row is a chain as long as the row; here the `K` rows go side by side, row `j` a pixel
/// behind row `j - 1` (whose pixels at and left of its own it needs), so that the `K` pixels
/// of one step are independent and the processor overlaps their chains. Each row's last two
/// pixels stay in registers: read back from memory, every link of a chain waited for a store.
fn paeth_rows<const K: usize>(pixels: &mut [u8], row: usize) {
    let width = row / 2;
    let (above, rows) = pixels[..(K + 1) * row].split_at_mut(row);
    // Row `j + 1`'s last pixel and the one before it (zeros left of its first).
    let (mut last, mut before) = ([[0u8; 2]; K], [[0u8; 2]; K]);
    // Step `s` takes row `j`'s pixel `x = s + 1 - j`, rows from the last up, so that row `j`
    // reads row `j - 1`'s pixels `x` and `x - 1` before row `j - 1` moves on. The first and
    // last steps, where some rows have no pixel, go apart from the others, whose loop over the
    // rows has no test and is unrolled: the rows' pixels stay in registers.
    let edge = |step: usize| (1..=K).rev().filter(move |&j| step + 1 >= j && step + 1 - j < width);
    for step in 0..K {
        edge(step).for_each(|j| paeth_pixel(above, rows, row, (j, step + 1 - j), &mut last, &mut before));
    }
    (last, before) = paeth_steps(above, rows, row, K..width, (last, before));
    for step in K.max(width)..width + K - 1 {
        edge(step).for_each(|j| paeth_pixel(above, rows, row, (j, step + 1 - j), &mut last, &mut before));
    }
}

/// [`paeth_rows`]' steps `steps`, where every row has a pixel with a left neighbour, from
/// and to the rows' last two pixels. (A function of its own: with the edges' rows picked at
/// run time in the same function, the rows' pixels stayed in memory, each step waiting for
/// the stores of the one before.)
#[inline(never)]
fn paeth_steps<const K: usize>(
    above: &[u8],
    rows: &mut [u8],
    row: usize,
    steps: std::ops::Range<usize>,
    (mut last, mut before): ([[u8; 2]; K], [[u8; 2]; K]),
) -> ([[u8; 2]; K], [[u8; 2]; K]) {
    for step in steps {
        // (A loop the compiler unrolls, each row's `j` a constant: `(1..=K).rev()` was not.)
        for r in 0..K {
            let j = K - r;
            paeth_pixel(above, rows, row, (j, step + 1 - j), &mut last, &mut before);
        }
    }
    (last, before)
}

/// [`paeth_rows`]' step for row `j`'s pixel `x`, `rows` holding rows `1..=K` after `above`.
#[inline(always)]
fn paeth_pixel<const K: usize>(
    above: &[u8],
    rows: &mut [u8],
    row: usize,
    (j, x): (usize, usize),
    last: &mut [[u8; 2]; K],
    before: &mut [[u8; 2]; K],
) {
    let (up, corner) = match j {
        1 => ([above[2 * x], above[2 * x + 1]], if x > 0 { [above[2 * x - 2], above[2 * x - 1]] } else { [0; 2] }),
        _ => (last[j - 2], before[j - 2]),
    };
    let (i, left) = ((j - 1) * row + 2 * x, last[j - 1]);
    // (Two lines, not `array::map`, which stayed a function call.)
    let new = [
        rows[i].wrapping_add(paeth(left[0], up[0], corner[0])),
        rows[i + 1].wrapping_add(paeth(left[1], up[1], corner[1])),
    ];
    rows[i..i + 2].copy_from_slice(&new);
    (before[j - 1], last[j - 1]) = (left, new);
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
    use crate::random::Rng;
    use std::io::{Cursor, Write};

    /// 16-bit grey pixels: smooth ramps with noise and holes (0), so that every Paeth branch and
    /// every filter's carries come up.
    fn pixels(width: u32, height: u32, seed: u64) -> Vec<u16> {
        let mut rng = Rng::new(seed);
        (0..width * height)
            .map(|i| {
                let (u, v) = (i % width, i / width);
                match rng.next_u64() % 8 {
                    0 => 0,
                    1 => rng.next_u64() as u16,
                    _ => (1000 + 37 * u + 291 * v + (rng.next_u64() % 5) as u32) as u16,
                }
            })
            .collect()
    }

    /// `values` as a PNG written by the png crate with row filter `filter`, its pixel data in
    /// IDAT chunks of at most `chunk` bytes, with a text chunk before them.
    fn encode(width: u32, height: u32, values: &[u16], filter: png::Filter, chunk: usize) -> Vec<u8> {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        enc.set_filter(filter);
        enc.add_text_chunk("Software".into(), "mrfmap test".into()).unwrap();
        let mut writer = enc.write_header().unwrap();
        let mut stream = writer.stream_writer_with_size(chunk).unwrap();
        stream.write_all(&bytes).unwrap();
        stream.finish().unwrap();
        writer.finish().unwrap();
        out
    }

    /// A PNG made by hand: `rows` (each with its filter byte) deflated into IDAT chunks of
    /// `chunk` bytes, the chunks' checksums right.
    fn by_hand(width: u32, height: u32, interlace: u8, rows: &[u8], chunk: usize) -> Vec<u8> {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        z.write_all(rows).unwrap();
        let data = z.finish().unwrap();
        let mut out = vec![137, 80, 78, 71, 13, 10, 26, 10];
        let mut put = |kind: &[u8; 4], body: &[u8]| {
            out.extend((body.len() as u32).to_be_bytes());
            out.extend(kind);
            out.extend(body);
            out.extend(crc32fast::hash(&[&kind[..], body].concat()).to_be_bytes());
        };
        let mut ihdr = [width.to_be_bytes(), height.to_be_bytes()].concat();
        ihdr.extend([16, 0, 0, 0, interlace]);
        put(b"IHDR", &ihdr);
        put(b"IDAT", &[]);
        data.chunks(chunk).for_each(|c| put(b"IDAT", c));
        put(b"IEND", &[]);
        out
    }

    fn decode(bytes: &[u8]) -> std::result::Result<DepthImage, String> {
        decode_depth_png(Cursor::new(bytes), 1.0, None)
    }

    /// Every row filter, one and several IDAT chunks, widths and heights around the batch of
    /// Paeth rows: the same values as the png crate's own decoding, bit for bit.
    #[test]
    fn decodes_every_row_filter_as_the_png_crate_does() {
        use png::Filter::*;
        let mut seed = 0;
        for filter in [NoFilter, Sub, Up, Avg, Paeth, Adaptive] {
            for (width, height) in [(1, 1), (1, 9), (3, 4), (17, 5), (64, 13), (640, 8)] {
                for chunk in [7, 1 << 20] {
                    seed += 1;
                    let values = pixels(width, height, seed);
                    let bytes = encode(width, height, &values, filter, chunk);
                    let ours = decode(&bytes).unwrap();
                    let mut theirs = png::Decoder::new(Cursor::new(&bytes)).read_info().unwrap();
                    let mut buf = vec![0u8; theirs.output_buffer_size().unwrap()];
                    theirs.next_frame(&mut buf).unwrap();
                    let want: Vec<f32> = buf.chunks(2).map(|b| u16::from_be_bytes([b[0], b[1]]) as f32).collect();
                    assert_eq!(ours.data(), &want[..], "{filter:?} {width}x{height}, IDAT chunks of {chunk}");
                    let direct: Vec<f32> = values.iter().map(|&v| v as f32).collect();
                    assert_eq!(ours.data(), &direct[..], "{filter:?} {width}x{height}");
                }
            }
        }
    }

    /// The branch-free predictor is the spec's on every one of the 2^24 inputs.
    #[test]
    fn paeth_is_the_specs_predictor() {
        for a in 0..=255u8 {
            for b in 0..=255u8 {
                for c in 0..=255u8 {
                    let p = i16::from(a) + i16::from(b) - i16::from(c);
                    let (pa, pb, pc) = ((p - i16::from(a)).abs(), (p - i16::from(b)).abs(), (p - i16::from(c)).abs());
                    let spec = if pa <= pb && pa <= pc {
                        a
                    } else if pb <= pc {
                        b
                    } else {
                        c
                    };
                    assert_eq!(paeth(a, b, c), spec, "{a} {b} {c}");
                }
            }
        }
    }

    /// Bad pixel data is an error that says so: a flipped bit (checksum), an unknown row filter,
    /// too few rows, and an interlaced image goes to the png crate.
    #[test]
    fn refuses_bad_pixel_data_and_reads_interlaced_images() {
        let values = pixels(8, 6, 99);
        let bytes = encode(8, 6, &values, png::Filter::Paeth, 1 << 20);
        let idat = bytes.windows(4).position(|w| w == b"IDAT").unwrap();
        let len = u32::from_be_bytes(bytes[idat - 4..idat].try_into().unwrap()) as usize;
        // A bit flipped in the pixel data, then in the stored checksum.
        for at in [idat + 10, idat + 4 + len + 2] {
            let mut bad = bytes.clone();
            bad[at] ^= 1;
            let e = decode(&bad).unwrap_err();
            assert!(e.contains("unreadable PNG") && (e.contains("checksum") || e.contains("corrupt")), "{e}");
        }
        // Row filter 5 does not exist.
        let mut rows = vec![0u8; 3 * 5];
        rows[5] = 5;
        let e = decode(&by_hand(2, 3, 0, &rows, 100)).unwrap_err();
        assert!(e.contains("row filter type 5"), "{e}");
        // Two rows where the header says three.
        let e = decode(&by_hand(2, 3, 0, &rows[..10], 3)).unwrap_err();
        assert!(e.contains("fewer rows"), "{e}");
        // The same rows, valid, in chunks of 3 bytes (and an empty first one).
        rows[5] = 1;
        rows[6..8].copy_from_slice(&[1, 2]);
        rows[8..10].copy_from_slice(&[0, 3]);
        let img = decode(&by_hand(2, 3, 0, &rows, 3)).unwrap();
        assert_eq!(img.data()[2..4], [258.0, 261.0]);
        // A 1 x 1 interlaced image: its one pixel is Adam7's first pass.
        let img = decode(&by_hand(1, 1, 1, &[0, 1, 44], 100)).unwrap();
        assert_eq!(img.data(), &[300.0]);
    }

    /// A broken header or chunk layout is an error that names it: a size of zero, an unknown
    /// interlace method, a chunk claiming more than 2^31 bytes, an image with no pixel data.
    #[test]
    fn refuses_broken_headers_and_chunks() {
        let good = by_hand(2, 1, 0, &[0, 0, 1, 0, 2], 100);
        assert_eq!(decode(&good).unwrap().data(), &[1.0, 2.0]);
        let e = decode(&by_hand(0, 1, 0, &[0], 100)).unwrap_err();
        assert!(e.contains("size of 0x1"), "{e}");
        let e = decode(&by_hand(2, 1, 2, &[0, 0, 1, 0, 2], 100)).unwrap_err();
        assert!(e.contains("interlace method"), "{e}");
        // The first IDAT's length (just after the 8-byte signature and the 25-byte IHDR).
        let mut huge = good.clone();
        huge[33..37].copy_from_slice(&u32::MAX.to_be_bytes());
        let e = decode(&huge).unwrap_err();
        assert!(e.contains("a chunk claims 4294967295 bytes"), "{e}");
        // The signature and header, then the end.
        let mut empty = good[..33].to_vec();
        empty.extend([0, 0, 0, 0]);
        empty.extend(b"IEND");
        empty.extend(crc32fast::hash(b"IEND").to_be_bytes());
        let e = decode(&empty).unwrap_err();
        assert!(e.contains("no pixel data"), "{e}");
    }

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
