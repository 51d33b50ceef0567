//! OctoMap files: `.bt` (maximum likelihood, 2 bits per child) and `.ot` (full log-odds per
//! node), readable by OctoMap 1.9 (octovis, RViz's octomap plugin, `convert_octree`), and a
//! reader for both so exports can be checked without OctoMap.
//!
//! OctoMap's tree has depth 16; a voxel with our integer coordinate `i` on an axis has the
//! OctoMap key `i + 32768` (so both cover `[i r, (i + 1) r)`), and a node's child index is
//! `x + 2 y + 4 z` of the key bits at that level. Nodes are written in pre-order.
//!
//! - `.bt`: header `# Octomap OcTree binary file`, `id OcTree`, `size N` (nodes), `res R`,
//!   `data`; then per inner node two bytes (children 0-3, 4-7), two bits per child, bit `2i`
//!   and bit `2i + 1` of the byte: `0, 1` occupied leaf, `1, 0` free leaf, `1, 1` inner
//!   node, `0, 0` unknown.
//!   Written after OctoMap's `toMaxLikelihood()` and `prune()`: 8 leaves of one class merge.
//! - `.ot`: header `# Octomap OcTree file` and the same keys; then per node its log-odds as a
//!   little-endian `f32` and a byte with bit `i` set when child `i` exists. Inner nodes hold
//!   the maximum of their children (OctoMap's `updateInnerOccupancy`). Not pruned.
//!
//! Map voxels are known space: occupied when their occupancy is above 0.5 (OctoMap's default
//! threshold); voxels the map does not have are unknown.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use crate::atomic_file::write_atomic;
use crate::error::{Error, Result};
use crate::map::{Map, VoxelKey};

/// OctoMap's tree depth.
pub const TREE_DEPTH: u32 = 16;
const KEY_OFFSET: i64 = 32768;
const BT_HEADER: &str = "# Octomap OcTree binary file";
const OT_HEADER: &str = "# Octomap OcTree file";

/// Which OctoMap format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OctomapFormat {
    /// `.bt`: occupied / free per leaf, pruned.
    Binary,
    /// `.ot`: log-odds per node.
    Full,
}

/// What an export wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OctomapSummary {
    /// Nodes in the tree (the header's `size`).
    pub nodes: u64,
    /// Leaves (after pruning for `.bt`).
    pub leaves: u64,
}

/// One leaf of a read tree: it covers `8^(16 - depth)` voxels from `key` (OctoMap keys, lower
/// corner) up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OctomapLeaf {
    /// Depth of the leaf (16 for a single voxel).
    pub depth: u32,
    /// OctoMap key of the lowest voxel it covers.
    pub key: [u16; 3],
    /// Log-odds (`.ot`), or `+1` occupied / `-1` free (`.bt`).
    pub value: f32,
}

impl OctomapLeaf {
    /// Every voxel the leaf covers, as our voxel coordinates.
    pub fn voxels(&self) -> impl Iterator<Item = VoxelKey> + '_ {
        let side = 1i64 << (TREE_DEPTH - self.depth);
        let base = self.key.map(|k| k as i64 - KEY_OFFSET);
        (0..side * side * side).map(move |i| {
            let (x, y, z) = (i % side, (i / side) % side, i / (side * side));
            VoxelKey([(base[0] + x) as i32, (base[1] + y) as i32, (base[2] + z) as i32])
        })
    }
}

/// A tree read back from a file.
#[derive(Clone, Debug, PartialEq)]
pub struct OctomapTree {
    /// Format of the file.
    pub format: OctomapFormat,
    /// Voxel edge in metres.
    pub resolution: f64,
    /// Nodes read (equals the header's `size`).
    pub nodes: u64,
    /// Leaves in pre-order.
    pub leaves: Vec<OctomapLeaf>,
}

/// A map voxel ready for the tree: its Morton code (child indices from the root down, 3 bits
/// per level) and its log-odds.
type Entry = (u64, f32);

fn entries(map: &Map) -> Result<Vec<Entry>> {
    let mut out = Vec::with_capacity(map.voxels.len());
    for (key, v) in map.voxels.iter() {
        let k = key.0.map(|i| i as i64 + KEY_OFFSET);
        if k.iter().any(|k| !(0..1 << TREE_DEPTH).contains(k)) {
            return Err(Error::Invalid(format!(
                "voxel {:?} is outside OctoMap's key range (+-32768 voxels from the origin)",
                key.0
            )));
        }
        let mut code = 0u64;
        for bit in (0..TREE_DEPTH).rev() {
            let c = (k[0] >> bit & 1) | (k[1] >> bit & 1) << 1 | (k[2] >> bit & 1) << 2;
            code = code << 3 | c as u64;
        }
        let p = (v.occupancy as f64).clamp(1e-6, 1.0 - 1e-6);
        out.push((code, (p / (1.0 - p)).ln() as f32));
    }
    out.sort_unstable_by_key(|e| e.0);
    Ok(out)
}

/// Child index of an entry below a node at `depth`.
#[inline]
fn child_of(code: u64, depth: u32) -> usize {
    (code >> (3 * (TREE_DEPTH - 1 - depth)) & 7) as usize
}

/// The (up to 8) child slices of a node at `depth`, by child index.
fn children(slice: &[Entry], depth: u32) -> [&[Entry]; 8] {
    let mut out: [&[Entry]; 8] = [&[]; 8];
    let mut start = 0;
    while start < slice.len() {
        let c = child_of(slice[start].0, depth);
        let end = start + slice[start..].partition_point(|e| child_of(e.0, depth) == c);
        out[c] = &slice[start..end];
        start = end;
    }
    out
}

/// `Some(occupied)` when the subtree at `depth` is full and of one class: OctoMap's pruning
/// turns it into one leaf.
fn uniform(slice: &[Entry], depth: u32) -> Option<bool> {
    let full = 1usize << (3 * (TREE_DEPTH - depth));
    let first = slice.first()?.1 > 0.0;
    (slice.len() == full && slice.iter().all(|e| (e.1 > 0.0) == first)).then_some(first)
}

/// Walks the tree in pre-order, calling `emit` with each node's bytes; returns the number
/// of nodes below this one and the leaves.
fn write_node(slice: &[Entry], depth: u32, format: OctomapFormat, emit: &mut dyn FnMut(&[u8])) -> (u64, u64) {
    let (mut nodes, mut leaves) = (0u64, 0u64);
    match format {
        OctomapFormat::Binary => {
            let kids = children(slice, depth);
            let mut bytes = [0u8; 2];
            let mut inner = [false; 8];
            for (i, kid) in kids.iter().enumerate() {
                if kid.is_empty() {
                    continue;
                }
                let code = match (depth + 1 == TREE_DEPTH).then(|| kid[0].1 > 0.0).or_else(|| uniform(kid, depth + 1)) {
                    Some(true) => 0b10,
                    Some(false) => 0b01,
                    None => {
                        inner[i] = true;
                        0b11
                    }
                };
                bytes[i / 4] |= code << (2 * (i % 4));
                nodes += 1;
                if !inner[i] {
                    leaves += 1;
                }
            }
            emit(&bytes);
            for (i, kid) in kids.iter().enumerate() {
                if inner[i] {
                    let (n, l) = write_node(kid, depth + 1, format, emit);
                    nodes += n;
                    leaves += l;
                }
            }
        }
        OctomapFormat::Full => {
            let max = slice.iter().map(|e| e.1).fold(f32::NEG_INFINITY, f32::max);
            emit(&max.to_le_bytes());
            if depth == TREE_DEPTH {
                emit(&[0]);
                return (0, 1);
            }
            let kids = children(slice, depth);
            let mask = kids.iter().enumerate().fold(0u8, |m, (i, k)| if k.is_empty() { m } else { m | 1 << i });
            emit(&[mask]);
            for kid in kids.iter().filter(|k| !k.is_empty()) {
                let (n, l) = write_node(kid, depth + 1, format, emit);
                nodes += n + 1;
                leaves += l;
            }
        }
    }
    (nodes, leaves)
}

/// Writes `map` as an OctoMap `.bt` or `.ot` file (atomically). Fails on an empty map and on
/// voxels beyond OctoMap's key range.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// use mrfmap::outputs::{OctomapFormat, read_octomap, write_octomap};
/// # let tmp = tempfile::tempdir().unwrap();
/// # let dir = tmp.path();
/// let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
/// map.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// map.voxels.insert(VoxelKey([-1, 2, 3]), MapVoxel { occupancy: 0.2, variance: 0.0 });
/// let path = dir.join("map.bt");
/// let summary = write_octomap(&map, &path, OctomapFormat::Binary).unwrap();
/// let tree = read_octomap(&path).unwrap();
/// assert_eq!((tree.nodes, tree.leaves.len() as u64), (summary.nodes, 2));
/// assert_eq!(tree.leaves.iter().filter(|l| l.value > 0.0).count(), 1);
/// ```
pub fn write_octomap(map: &Map, path: &Path, format: OctomapFormat) -> Result<OctomapSummary> {
    if map.voxels.is_empty() {
        return Err(Error::Invalid(format!("{}: the map is empty: nothing to export", path.display())));
    }
    let entries = entries(map)?;
    // First pass counts nodes for the header; the second writes.
    let (nodes, leaves) = write_node(&entries, 0, format, &mut |_| {});
    let nodes = nodes + 1; // the root
    let header = match format {
        OctomapFormat::Binary => BT_HEADER,
        OctomapFormat::Full => OT_HEADER,
    };
    write_atomic(path, |w| {
        write!(
            w,
            "{header}\n# (written by mrfmap from a {} map)\n#\nid OcTree\nsize {nodes}\nres {}\ndata\n",
            map.engine,
            map.resolution()
        )?;
        let mut err = Ok(());
        write_node(&entries, 0, format, &mut |b| {
            if err.is_ok() {
                err = w.write_all(b);
            }
        });
        err
    })?;
    Ok(OctomapSummary { nodes, leaves })
}

/// Reads an OctoMap `.bt` or `.ot` file (the `OcTree` type only).
pub fn read_octomap(path: &Path) -> Result<OctomapTree> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    decode_octomap(BufReader::new(file)).map_err(|m| Error::file(path, m))
}

/// [`read_octomap`] from any reader; the error says what is wrong with the data.
pub fn decode_octomap(mut r: impl BufRead) -> std::result::Result<OctomapTree, String> {
    let mut line = String::new();
    // Header lines are short: a "line" longer than this is not a header.
    let read_line = |r: &mut dyn BufRead, line: &mut String| -> std::result::Result<bool, String> {
        line.clear();
        let n = r.take(4096).read_line(line).map_err(|e| e.to_string())?;
        Ok(n > 0)
    };
    read_line(&mut r, &mut line)?;
    let format = match line.trim_end() {
        BT_HEADER => OctomapFormat::Binary,
        OT_HEADER => OctomapFormat::Full,
        other => return Err(format!("not an OctoMap file (first line {other:?})")),
    };
    let (mut id, mut size, mut res) = (None, None, None);
    loop {
        if !read_line(&mut r, &mut line)? {
            return Err("header ends before `data`".into());
        }
        let l = line.trim();
        if l.starts_with('#') || l.is_empty() {
            continue;
        }
        let (k, v) = l.split_once(' ').unwrap_or((l, ""));
        match k {
            "id" => id = Some(v.to_string()),
            "size" => size = Some(v.parse::<u64>().map_err(|e| format!("size: {e}"))?),
            "res" => res = Some(v.parse::<f64>().map_err(|e| format!("res: {e}"))?),
            "data" => break,
            other => return Err(format!("unknown header key {other:?}")),
        }
    }
    if id.as_deref() != Some("OcTree") {
        return Err(format!("tree type {id:?} is not OcTree"));
    }
    let (Some(size), Some(resolution)) = (size, res) else {
        return Err("header lacks size or res".into());
    };
    let mut data = Vec::new();
    r.read_to_end(&mut data).map_err(|e| e.to_string())?;
    let mut tree = OctomapTree { format, resolution, nodes: 0, leaves: Vec::new() };
    if size > 0 {
        let mut pos = 0;
        tree.nodes = 1;
        match format {
            OctomapFormat::Binary => read_bt_node(&data, &mut pos, 0, [0; 3], &mut tree),
            OctomapFormat::Full => read_ot_node(&data, &mut pos, 0, [0; 3], &mut tree),
        }
        .map_err(|m| m.to_string())?;
        if pos != data.len() {
            return Err(format!("{} bytes after the tree", data.len() - pos));
        }
    }
    if tree.nodes != size {
        return Err(format!("header says {size} nodes, the data holds {}", tree.nodes));
    }
    Ok(tree)
}

/// Result of reading part of a tree: the error says what is wrong with the data.
type ReadResult = std::result::Result<(), &'static str>;

fn take<'a>(data: &'a [u8], pos: &mut usize, n: usize) -> std::result::Result<&'a [u8], &'static str> {
    let s = data.get(*pos..*pos + n).ok_or("data ends inside the tree")?;
    *pos += n;
    Ok(s)
}

/// Key (lower corner) of child `i` of the node at `depth` whose key is `key`.
fn child_key(key: [u16; 3], depth: u32, i: usize) -> [u16; 3] {
    let bit = TREE_DEPTH - 1 - depth;
    [0, 1, 2].map(|a| key[a] | (((i >> a) & 1) as u16) << bit)
}

/// `.bt`: the inner node at `depth` with key `key` (two bytes of child codes), then its
/// inner children.
fn read_bt_node(data: &[u8], pos: &mut usize, depth: u32, key: [u16; 3], tree: &mut OctomapTree) -> ReadResult {
    if depth >= TREE_DEPTH {
        return Err("tree deeper than 16 levels");
    }
    let b = take(data, pos, 2)?;
    let codes: Vec<u8> = (0..8).map(|i| (b[i / 4] >> (2 * (i % 4))) & 3).collect();
    for (i, &code) in codes.iter().enumerate() {
        if code != 0 {
            tree.nodes += 1;
        }
        if code == 0b10 || code == 0b01 {
            let value = if code == 0b10 { 1.0 } else { -1.0 };
            tree.leaves.push(OctomapLeaf { depth: depth + 1, key: child_key(key, depth, i), value });
        }
    }
    for (i, &code) in codes.iter().enumerate() {
        if code == 0b11 {
            read_bt_node(data, pos, depth + 1, child_key(key, depth, i), tree)?;
        }
    }
    Ok(())
}

/// `.ot`: the node at `depth` with key `key` (value, child mask), then its children.
fn read_ot_node(data: &[u8], pos: &mut usize, depth: u32, key: [u16; 3], tree: &mut OctomapTree) -> ReadResult {
    let b = take(data, pos, 5)?;
    let value = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let mask = b[4];
    if mask == 0 {
        tree.leaves.push(OctomapLeaf { depth, key, value });
        return Ok(());
    }
    if depth >= TREE_DEPTH {
        return Err("tree deeper than 16 levels");
    }
    for i in (0..8).filter(|i| mask >> i & 1 == 1) {
        tree.nodes += 1;
        read_ot_node(data, pos, depth + 1, child_key(key, depth, i), tree)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::EngineKind;
    use crate::map::MapVoxel;
    use crate::random::Rng;

    fn random_map(seed: u64) -> Map {
        let mut rng = Rng::new(seed);
        let mut map = Map::new(EngineKind::LogOdds, 0.05).unwrap();
        for _ in 0..3000 {
            let k = [0; 3].map(|_| (rng.next_u64() % 40) as i32 - 20);
            map.voxels.insert(VoxelKey(k), MapVoxel { occupancy: rng.range(0.01, 0.99) as f32, variance: 0.0 });
        }
        // A full free 8x8x8 block and a full occupied 2x2x2 block: both prune in .bt.
        for i in 0..512 {
            let k = [64 + (i % 8), 64 + (i / 8 % 8), 64 + i / 64];
            map.voxels.insert(VoxelKey(k), MapVoxel { occupancy: 0.2, variance: 0.0 });
        }
        for i in 0..8 {
            let k = [-100 + (i % 2), -100 + (i / 2 % 2), -100 + i / 4];
            map.voxels.insert(VoxelKey(k), MapVoxel { occupancy: 0.8, variance: 0.0 });
        }
        map
    }

    #[test]
    fn round_trips_voxel_for_voxel() {
        let map = random_map(4);
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        for format in [OctomapFormat::Binary, OctomapFormat::Full] {
            let path = d.join(if format == OctomapFormat::Binary { "t.bt" } else { "t.ot" });
            let s = write_octomap(&map, &path, format).unwrap();
            let tree = read_octomap(&path).unwrap();
            assert_eq!((tree.nodes, tree.leaves.len() as u64, tree.resolution), (s.nodes, s.leaves, 0.05));
            let mut seen = 0;
            for leaf in &tree.leaves {
                for key in leaf.voxels() {
                    let v = map.voxels.get(key).unwrap_or_else(|| panic!("{format:?}: {key:?} not in the map"));
                    let l = (v.occupancy as f64 / (1.0 - v.occupancy as f64)).ln() as f32;
                    match format {
                        OctomapFormat::Binary => assert_eq!(leaf.value > 0.0, v.occupancy > 0.5),
                        OctomapFormat::Full => assert!((leaf.value - l).abs() < 1e-5),
                    }
                    seen += 1;
                }
            }
            assert_eq!(seen, map.voxels.len(), "{format:?}: every voxel exactly once");
            if format == OctomapFormat::Binary {
                assert!(tree.leaves.iter().any(|l| l.depth == 13), "the free 8x8x8 block is one leaf");
                assert!(tree.leaves.iter().any(|l| l.depth == 15 && l.value > 0.0), "the occupied 2x2x2 block too");
            }
        }
    }

    #[test]
    fn bad_maps_and_files_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        let empty = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        let e = write_octomap(&empty, &d.join("e.bt"), OctomapFormat::Binary).unwrap_err().to_string();
        assert!(e.contains("empty") && !d.join("e.bt").exists(), "{e}");
        let mut far = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        far.voxels.insert(VoxelKey([40_000, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        assert!(
            write_octomap(&far, &d.join("f.bt"), OctomapFormat::Binary).unwrap_err().to_string().contains("key range")
        );
        let p = d.join("x.bt");
        std::fs::write(&p, "# Octomap OcTree binary file\nid OcTree\nsize 5\nres 0.1\ndata\n\x03\x00").unwrap();
        let e = read_octomap(&p).unwrap_err().to_string();
        assert!(e.contains("x.bt") && e.contains("data ends"), "{e}");
        std::fs::write(&p, "hello\n").unwrap();
        assert!(read_octomap(&p).unwrap_err().to_string().contains("not an OctoMap file"));
    }
}
