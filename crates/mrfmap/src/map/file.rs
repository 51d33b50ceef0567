//! The binary map file (`.mrfmap`), version 1. All integers little-endian.
//!
//! ```text
//! magic    8 bytes   "\x89MRFMAP\n"   (the high byte and newline catch text-mode mangling)
//! version  u32       1
//! header   u32 length + UTF-8 TOML: engine, resolution, has_variance, bricks, voxels, [params]
//! bricks   sorted by key; per brick: i32 x, y, z; 8 x u64 allocation mask;
//!          per allocated voxel in slot order: f32 occupancy, then f32 variance if has_variance
//! crc32    u32       CRC-32 (IEEE) of every byte before it
//! ```

use super::EngineKind;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{BrickKey, Grid, Map, MapVoxel, mask_slots};
use crate::error::{Error, Result};

const MAGIC: &[u8; 8] = b"\x89MRFMAP\n";
const VERSION: u32 = 1;

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Header {
    engine: EngineKind,
    resolution: f64,
    has_variance: bool,
    bricks: u64,
    voxels: u64,
    params: BTreeMap<String, String>,
}

pub(super) fn save(map: &Map, path: &Path) -> Result<()> {
    save_converted(map, &map.voxels, |v| *v, path).map(|_| ())
}

/// Saves the map that `meta` (engine, parameters, has_variance; its voxels are not read)
/// would be with `grid`'s voxels made map voxels by `convert`, each brick converted as it is
/// written; returns how many voxels are occupied. The same file as the map saved whole, and
/// neither the map's voxels nor its bytes are ever all in memory (an engine's grid saved this
/// way needs no finished copy beside it: for a log-odds map, that copy was over half of a
/// build's peak).
pub(super) fn save_converted<V: Copy + Default>(
    meta: &Map,
    grid: &Grid<V>,
    convert: impl Fn(&V) -> MapVoxel,
    path: &Path,
) -> Result<usize> {
    let mut occupied = 0;
    crate::atomic_file::write_atomic(path, |w| {
        occupied = encode_into(meta, grid, &convert, w)?;
        Ok(())
    })?;
    Ok(occupied)
}

#[cfg(test)]
fn encode(map: &Map) -> Vec<u8> {
    let mut out = Vec::new();
    encode_into(map, &map.voxels, |v| *v, &mut out).expect("writing to memory");
    out
}

/// Writes the map `meta` describes, with `grid`'s voxels through `convert`, in the file format
/// to `out`, the checksum last; returns how many voxels are occupied.
fn encode_into<V: Copy + Default>(
    meta: &Map,
    grid: &Grid<V>,
    convert: impl Fn(&V) -> MapVoxel,
    out: &mut impl Write,
) -> std::io::Result<usize> {
    let header = Header {
        engine: meta.engine,
        resolution: grid.resolution(),
        has_variance: meta.has_variance,
        bricks: grid.brick_count() as u64,
        voxels: grid.len() as u64,
        params: meta.params.clone(),
    };
    let header = toml::to_string(&header).expect("header is plain data");
    // (crc32fast, which png already builds: SIMD, where a byte at a time with a table was a
    // third of saving a map.)
    let mut crc = crc32fast::Hasher::new();
    let mut buf = Vec::with_capacity(64 + header.len());
    buf.extend_from_slice(MAGIC);
    buf.extend_from_slice(&VERSION.to_le_bytes());
    buf.extend_from_slice(&(header.len() as u32).to_le_bytes());
    buf.extend_from_slice(header.as_bytes());
    crc.update(&buf);
    out.write_all(&buf)?;
    let mut occupied = 0;
    // Written as encoded, a brick at a time: a map's bytes are never all in memory at once
    // (for a large map they were an eighth of a build's peak).
    for key in grid.sorted_brick_keys() {
        let brick = grid.brick(key).expect("key from this grid");
        buf.clear();
        for c in key.0 {
            buf.extend_from_slice(&c.to_le_bytes());
        }
        for w in brick.mask() {
            buf.extend_from_slice(&w.to_le_bytes());
        }
        let per_voxel = if meta.has_variance { 8 } else { 4 };
        buf.reserve(per_voxel * brick.mask().iter().map(|w| w.count_ones() as usize).sum::<usize>());
        brick.for_each_value(|v| {
            let v = convert(v);
            occupied += usize::from(v.is_occupied());
            buf.extend_from_slice(&v.occupancy.to_le_bytes());
            if meta.has_variance {
                buf.extend_from_slice(&v.variance.to_le_bytes());
            }
        });
        crc.update(&buf);
        out.write_all(&buf)?;
    }
    out.write_all(&crc.finalize().to_le_bytes())?;
    Ok(occupied)
}

pub(super) fn load(path: &Path) -> Result<Map> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode(&bytes).map_err(|m| Error::file(path, m))
}

/// A cursor that turns running out of bytes into a message.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> std::result::Result<&'a [u8], String> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.bytes.len()).ok_or("file is truncated")?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u32(&mut self) -> std::result::Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn i32(&mut self) -> std::result::Result<i32, String> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> std::result::Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn f32(&mut self) -> std::result::Result<f32, String> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
}

pub(super) fn decode(bytes: &[u8]) -> std::result::Result<Map, String> {
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not an mrfmap map file (bad magic bytes)".into());
    }
    if bytes.len() < MAGIC.len() + 8 {
        return Err("file is truncated".into());
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap());
    if version != VERSION {
        return Err(format!("map format version {version} is not supported (this build reads version {VERSION})"));
    }
    let (body, tail) = bytes.split_at(bytes.len() - 4);
    if crc32(body) != u32::from_le_bytes(tail.try_into().unwrap()) {
        return Err("checksum mismatch: the file is corrupt or truncated".into());
    }
    let mut r = Reader { bytes: body, pos: 12 };
    let header_len = r.u32()? as usize;
    let header = std::str::from_utf8(r.take(header_len)?).map_err(|_| "header is not UTF-8")?;
    let header: Header = toml::from_str(header).map_err(|e| format!("bad header: {e}"))?;
    let mut map = Map::new(header.engine, header.resolution).map_err(|e| format!("bad header: {e}"))?;
    map.params = header.params;
    map.has_variance = header.has_variance;
    // Every brick takes at least 76 + 4 bytes of file: a header claiming more bricks than the
    // file can hold fails here, before anything is allocated, and the memory the bricks will
    // take (read off their masks) is checked against the limit.
    let min_brick = 80 + 4 * header.has_variance as u64;
    if header.bricks.saturating_mul(min_brick) > (body.len() - r.pos) as u64 {
        return Err(format!(
            "header says {} bricks, more than the file's {} bytes can hold",
            header.bricks,
            body.len()
        ));
    }
    let needed = memory_needed(Reader { bytes: body, pos: r.pos }, header.bricks, 4 + 4 * header.has_variance as usize);
    crate::limits::check_memory("loading the map", needed, "crop it on a larger machine").map_err(|e| e.to_string())?;
    let mut previous: Option<BrickKey> = None;
    for _ in 0..header.bricks {
        let key = BrickKey([r.i32()?, r.i32()?, r.i32()?]);
        if previous.is_some_and(|p| p >= key) {
            return Err(format!("bricks are not sorted by key (brick {:?} after {:?})", key.0, previous.unwrap().0));
        }
        previous = Some(key);
        let mut mask = [0u64; 8];
        for w in &mut mask {
            *w = r.u64()?;
        }
        if mask == [0; 8] {
            return Err(format!("brick {:?} has no voxels", key.0));
        }
        let brick = map.voxels.brick_or_insert(key);
        for slot in mask_slots(&mask) {
            let occupancy = r.f32()?;
            let variance = if header.has_variance { r.f32()? } else { 0.0 };
            brick.get_or_insert(slot, MapVoxel { occupancy, variance });
        }
    }
    if r.pos != body.len() {
        return Err(format!("{} unexpected bytes after the last brick", body.len() - r.pos));
    }
    if map.voxels.len() as u64 != header.voxels {
        return Err(format!("header says {} voxels, file holds {}", header.voxels, map.voxels.len()));
    }
    Ok(map)
}

/// The memory `bricks` bricks read from `r` take in a [`Map`]: per brick its own size and its
/// hash table entry (at most twice over, as the table grows), per layer holding voxels 64
/// voxels. Counts what a truncated file holds (the read proper then says where it stops).
fn memory_needed(mut r: Reader, bricks: u64, bytes_per_voxel: usize) -> f64 {
    let (mut counted, mut layers) = (0u64, 0u64);
    while counted < bricks {
        let Ok(mask) = r.take(12).and_then(|_| r.take(64)) else { break };
        let words = mask.chunks_exact(8).map(|w| u64::from_le_bytes(w.try_into().unwrap()));
        let (voxels, held) = words.fold((0, 0), |(v, l), w| (v + w.count_ones() as usize, l + (w != 0) as u64));
        layers += held;
        counted += 1;
        if r.take(voxels * bytes_per_voxel).is_err() {
            break;
        }
    }
    let brick = 2 * (std::mem::size_of::<(BrickKey, crate::map::Brick<MapVoxel>)>() + 1);
    counted as f64 * brick as f64 + layers as f64 * 64.0 * std::mem::size_of::<MapVoxel>() as f64
}

/// CRC-32 (IEEE 802.3, as zlib and PNG) of `data`.
fn crc32(data: &[u8]) -> u32 {
    crc32fast::hash(data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::VoxelKey;
    use crate::random::Rng;

    fn sample_map(variance: bool) -> Map {
        let mut map = Map::new(EngineKind::LogOdds, 0.02).unwrap();
        map.has_variance = variance;
        map.params.insert("p_hit".into(), "0.7".into());
        let mut rng = Rng::new(1);
        for _ in 0..3000 {
            let k = VoxelKey([0; 3].map(|_| (rng.next_u64() % 100) as i32 - 50));
            map.voxels.insert(k, MapVoxel { occupancy: rng.uniform() as f32, variance: rng.uniform() as f32 });
        }
        map
    }

    #[test]
    fn crc_known_vector() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn round_trip_is_exact_and_deterministic() {
        for variance in [false, true] {
            let map = sample_map(variance);
            let bytes = encode(&map);
            let back = decode(&bytes).unwrap();
            assert_eq!(encode(&back), bytes);
            assert_eq!(back.voxels.len(), map.voxels.len());
            for (k, v) in map.voxels.iter() {
                let w = back.voxels.get(k).unwrap();
                assert_eq!(w.occupancy, v.occupancy);
                assert_eq!(w.variance, if variance { v.variance } else { 0.0 });
            }
            assert_eq!(back.params["p_hit"], "0.7");
        }
    }

    #[test]
    fn corruption_is_detected() {
        let bytes = encode(&sample_map(false));
        let mut flipped = bytes.clone();
        flipped[bytes.len() / 2] ^= 0x10;
        assert!(decode(&flipped).unwrap_err().contains("checksum"));
        assert!(decode(&bytes[..bytes.len() - 100]).unwrap_err().contains("checksum"));
        assert!(decode(b"ply\nformat ascii 1.0\n").unwrap_err().contains("not an mrfmap"));
        let mut future = bytes.clone();
        future[8] = 9;
        assert!(decode(&future).unwrap_err().contains("version 9"));
        assert!(decode(&bytes[..10]).is_err());
    }

    /// A file with a hand-written header and brick records, checksummed.
    fn forged(header: &str, bricks: &[([i32; 3], [u64; 8])]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        for (key, mask) in bricks {
            key.iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
            mask.iter().for_each(|w| out.extend_from_slice(&w.to_le_bytes()));
            for _ in 0..mask.iter().map(|w| w.count_ones()).sum::<u32>() {
                out.extend_from_slice(&0.5f32.to_le_bytes());
            }
        }
        let crc = crc32(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    #[test]
    fn forged_headers_and_bricks_fail_before_allocating() {
        let header = |bricks: u64, voxels: u64| {
            format!(
                "engine = \"logodds\"\nresolution = 0.05\nhas_variance = false\nbricks = {bricks}\nvoxels = {voxels}\n[params]\n"
            )
        };
        let one = [1, 0, 0, 0, 0, 0, 0, 0];
        assert!(decode(&forged(&header(1, 1), &[([0, 0, 0], one)])).is_ok());
        let e = decode(&forged(&header(u64::MAX / 2, 1), &[([0, 0, 0], one)])).unwrap_err();
        assert!(e.contains("more than the file"), "{e}");
        // An empty brick (76 bytes) followed by one of two voxels (84) to pass the size check.
        let e =
            decode(&forged(&header(2, 2), &[([0, 0, 0], [0; 8]), ([1, 0, 0], [3, 0, 0, 0, 0, 0, 0, 0])])).unwrap_err();
        assert!(e.contains("no voxels"), "{e}");
        let e = decode(&forged(&header(2, 2), &[([1, 0, 0], one), ([0, 0, 0], one)])).unwrap_err();
        assert!(e.contains("not sorted"), "{e}");
        let e = decode(&forged(&header(2, 2), &[([0, 0, 0], one), ([0, 0, 0], one)])).unwrap_err();
        assert!(e.contains("not sorted"), "{e}");
        // A map of an engine this build does not know is refused by name.
        let foreign = header(1, 1).replace("logodds", "octomap");
        let e = decode(&forged(&foreign, &[([0, 0, 0], one)])).unwrap_err();
        assert!(e.contains("unknown engine \"octomap\"") && e.contains("logodds, mrf, crm"), "{e}");
    }
}
