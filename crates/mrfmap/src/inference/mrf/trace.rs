//! Tracing tiles: every ray of a tile with its cavities, the ray factor's messages
//! ([`super::ray_log_messages`], two rays' at a time), and the tile's new entries, damped
//! against its old ones; then their changes applied to the sums in tile order.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::MrfEngine;
use super::messages::{RayFactor, ray_log_messages_pair};
use super::schedule::RunReport;
use super::tiles::{CALM_TRACES, Entry, Keyframe, MAX_DAMPING_LEVEL, Tile, f32_at_most};
use super::{MAX_LOG_ODDS, ray_log_messages};
use crate::frames::{Intervals, RayLikelihood};
use crate::inference::Engine;
use crate::inference::{logit, sigmoid};
use crate::map::{BRICK_VOXELS, Brick, BrickKey, Grid, SlotMask, VoxelKey, mask_set, mask_slots};
use crate::rays::{CameraRays, FrameRays, PixelRay, Segment, Walk};
use crate::vecmath::{VECTOR_LANES, exp};

/// One tile's trace, before it is applied.
struct Traced {
    /// Which tile, and what it becomes (without its epoch).
    index: usize,
    tile: Tile,
    /// Per entry of `tile`, the change it makes to `S`: its new message minus its old one.
    changes: Vec<f32>,
    /// The changes to voxels the tile's rays no longer reach (minus their old messages).
    gone: Vec<(VoxelKey, f32)>,
    rays: usize,
}

/// Messages are kept away from 0 and 1 so that their log-odds stay finite.
const MSG_EPS: f64 = 1e-6;

/// Crossings shorter than this many voxel edges are rounding slivers at brick faces (see
/// [`MrfEngine::trace_tile`]); real ones are longer than a micrometre in a metre-sized voxel.
const SLIVER: f64 = 1e-9;

/// Largest pixel stride of [`MrfParams::ray_spacing`] (a divisor of [`TILE`]).
const MAX_STRIDE: u32 = 8;

/// A voxel a tile's rays reach, while the tile is traced.
#[derive(Clone, Copy)]
struct VoxelAcc {
    /// The tile's old message per voxel edge of length (a ray's own share per edge of it).
    own: f32,
    /// Summed lengths (voxel edges) and length-weighted log-odds messages of this trace.
    length: f64,
    sum: f64,
}

/// Per-tile buffers of the tile's voxels, reused across the tiles a thread traces.
struct TileScratch<'a> {
    voxels: Vec<VoxelAcc>,
    /// Per voxel of `voxels`, what only the tile's end reads: its key and the tile's old entry,
    /// if it had one. (Apart, so that what each crossing reads and writes takes 24 bytes.)
    keys: Vec<(VoxelKey, Option<Entry>)>,
    /// Per brick the tile's rays cross, its index in `tables` ([`UNALLOCATED`] for none).
    /// A tile's rays cross mostly the same bricks: this small table answers where the map's
    /// large one cost a cache miss per brick of every ray (13% of a trace).
    bricks: FxHashMap<BrickKey, u32>,
    /// A direct-mapped cache in front of `bricks` (key, value), by a hash of the key. At
    /// 0.01 m a ray crosses dozens of bricks and a tile's rays share most of them: probing
    /// `bricks` for each was a fifth of a trace's profile.
    recent: Box<[(BrickKey, u32); RECENT]>,
    /// The first `used` are in use (the rest are kept for reuse).
    tables: Vec<SlotTable<'a>>,
    used: usize,
    /// Per table, a block of [`BRICK_VOXELS`]: per slot of its brick, the voxel's index in
    /// `voxels` (`u32::MAX` for none). (One array for all tables: a crossing finds its voxel
    /// with one load fewer than through a block of the table's own.)
    index: Vec<u32>,
}

/// A thread's buffers for tracing tiles: the tile's voxels, and two rays' buffers apart from
/// them (so that a walk can write a ray's while it looks up the tile's).
struct Scratch<'a> {
    tile: TileScratch<'a>,
    /// A ray whose messages wait for the next one's ([`RayScratch::ready`]), and the ray
    /// being walked.
    rays: [RayScratch; 2],
    /// The most crossings a ray's buffers are first made room for ([`MAX_ROOM`]; a test sets
    /// it small, so that walks are walked again).
    max_room: usize,
}

/// [`Scratch::max_room`]. A ray's bound on its crossings grows with its range over the
/// resolution; past this many its walk counts them first (and is walked again), so that no
/// bound makes room for more than the ray crosses.
const MAX_ROOM: usize = 1 << 16;

impl Default for Scratch<'_> {
    fn default() -> Self {
        Scratch { tile: TileScratch::default(), rays: Default::default(), max_room: MAX_ROOM }
    }
}

/// [`TileScratch::bricks`] value of a brick that is not allocated.
const UNALLOCATED: u32 = u32::MAX;

/// Entries of [`TileScratch::recent`] (a power of two).
const RECENT: usize = 512;

/// A [`TileScratch::recent`] entry holding no brick (a brick coordinate is an `i32` voxel
/// coordinate `>> 3`, never `i32::MIN`).
const NO_BRICK: BrickKey = BrickKey([i32::MIN; 3]);

/// [`TileScratch::recent`]'s slot of brick `key`.
#[inline]
fn recent_slot(key: BrickKey) -> usize {
    let [x, y, z] = key.0.map(|c| c as u32);
    let h = x.wrapping_mul(0x9E37_79B1) ^ y.wrapping_mul(0x85EB_CA77) ^ z.wrapping_mul(0xC2B2_AE3D);
    (h >> (32 - RECENT.trailing_zeros())) as usize
}

/// One brick's voxels among a tile's: its sums, and which slots are set (their indices in
/// [`TileScratch::voxels`] are the table's block of [`TileScratch::index`]). A ray is traced
/// brick by brick, so its voxels are found by one brick lookup and array indexing (a hash
/// lookup per voxel was a tenth of a trace, and sorting the voxels afterwards another 7%).
struct SlotTable<'a> {
    key: BrickKey,
    sums: Option<&'a [f32; BRICK_VOXELS]>,
    set: SlotMask,
}

impl Default for TileScratch<'_> {
    fn default() -> Self {
        TileScratch {
            voxels: Vec::new(),
            keys: Vec::new(),
            bricks: FxHashMap::default(),
            recent: Box::new([(NO_BRICK, 0); RECENT]),
            tables: Vec::new(),
            used: 0,
            index: Vec::new(),
        }
    }
}

impl<'a> TileScratch<'a> {
    fn clear(&mut self) {
        for (table, index) in self.tables[..self.used].iter_mut().zip(self.index.chunks_exact_mut(BRICK_VOXELS)) {
            for slot in mask_slots(&table.set) {
                index[slot] = u32::MAX;
            }
            table.set = [0; 8];
        }
        self.used = 0;
        self.bricks.clear();
        self.recent.fill((NO_BRICK, 0));
        self.voxels.clear();
        self.keys.clear();
    }

    /// The table of brick `key` with its sums in `grid`, `None` if the brick is not allocated
    /// (and has no table).
    /// (Inlined: a ray crosses about 19 bricks at 0.02 m, mostly unallocated ones that
    /// `recent` answers, and the call was a third of such a step.)
    #[inline(always)]
    fn table_of(&mut self, key: BrickKey, grid: &'a Grid<f32>) -> Option<(usize, Option<&'a [f32; BRICK_VOXELS]>)> {
        let slot = recent_slot(key);
        let t = match self.recent[slot] {
            (k, t) if k == key => t,
            _ => self.table_missed(key, grid, slot),
        };
        (t != UNALLOCATED).then(|| (t as usize, self.tables[t as usize].sums))
    }

    /// [`TileScratch::table_of`] of a brick that is not in `recent` (at `slot`): its table
    /// index, found or made, or [`UNALLOCATED`].
    #[inline(never)]
    fn table_missed(&mut self, key: BrickKey, grid: &'a Grid<f32>, slot: usize) -> u32 {
        match self.bricks.get(&key) {
            Some(&t) => {
                self.recent[slot] = (key, t);
                t
            }
            None => {
                // (The MRF's bricks are dense: every voxel is allocated when its brick is.)
                let t = match grid.brick(key).and_then(Brick::dense) {
                    Some(sums) => self.add_table(key, Some(sums)),
                    None => UNALLOCATED,
                };
                self.remember(key, t);
                t
            }
        }
    }

    /// Records brick `key`'s table index `t` (or [`UNALLOCATED`]).
    fn remember(&mut self, key: BrickKey, t: u32) {
        self.bricks.insert(key, t);
        self.recent[recent_slot(key)] = (key, t);
    }

    fn add_table(&mut self, key: BrickKey, sums: Option<&'a [f32; BRICK_VOXELS]>) -> u32 {
        if self.used == self.tables.len() {
            self.tables.push(SlotTable { key, sums, set: [0; 8] });
            self.index.resize(self.tables.len() * BRICK_VOXELS, u32::MAX);
        }
        let table = &mut self.tables[self.used];
        (table.key, table.sums) = (key, sums);
        self.used += 1;
        (self.used - 1) as u32
    }

    /// The table of brick `key`, made if there is none (even if `grid` no longer holds the
    /// brick: a tile's old messages in it must still go).
    fn table_or_new(&mut self, key: BrickKey, grid: &'a Grid<f32>) -> usize {
        match self.table_of(key, grid) {
            Some((t, _)) => t,
            None => {
                let t = self.add_table(key, None);
                self.remember(key, t);
                t as usize
            }
        }
    }

    /// The index of voxel `key` of table `t`'s brick, added with the tile's `old` entry if new.
    #[inline]
    fn voxel_in(&mut self, t: usize, key: VoxelKey, old: Option<Entry>) -> usize {
        let slot = key.slot();
        let at = t * BRICK_VOXELS + slot;
        let i = self.index[at];
        if i != u32::MAX {
            return i as usize;
        }
        let own = old.map_or(0.0, |e| if e.edges() > 0.0 { e.message() / e.edges() } else { 0.0 });
        let i = self.voxels.len();
        self.index[at] = i as u32;
        mask_set(&mut self.tables[t].set, slot);
        self.voxels.push(VoxelAcc { own, length: 0.0, sum: 0.0 });
        self.keys.push((key, old));
        i
    }

    /// [`TileScratch::voxel_in`] by slot of table `t`'s brick, for a voxel no old entry names.
    #[inline]
    fn voxel_at(&mut self, t: usize, slot: usize) -> usize {
        match self.index[t * BRICK_VOXELS + slot] {
            u32::MAX => self.voxel_in(t, self.tables[t].key.voxel(slot), None),
            i => i as usize,
        }
    }

    /// The voxels' indices by brick, then slot, each with its `S` as traced (0 in a brick
    /// no longer in the map, whose voxels no ray reached).
    fn sorted(&self) -> impl Iterator<Item = (usize, f32)> + '_ {
        let mut order: Vec<(&SlotTable, &[u32])> =
            self.tables[..self.used].iter().zip(self.index.chunks_exact(BRICK_VOXELS)).collect();
        order.sort_unstable_by_key(|(t, _)| t.key);
        order.into_iter().flat_map(|(t, index)| {
            mask_slots(&t.set).map(|slot| (index[slot] as usize, t.sums.map_or(0.0, |sums| sums[slot])))
        })
    }
}

/// Per-ray buffers: one entry per voxel the ray crosses, in order.
#[derive(Default)]
struct RayScratch {
    /// Voxels crossed: the first `n` values of the four buffers below, which only grow
    /// ([`RayScratch::room`]).
    n: usize,
    /// The voxel's index in [`TileScratch::voxels`].
    slots: Vec<u32>,
    /// Where the ray enters and leaves the voxel (camera z-depth, m). (Its length inside is
    /// their difference over the ray's `cz`: one buffer fewer to fill per crossing.)
    z0: Vec<f64>,
    z1: Vec<f64>,
    /// The cavity (log-odds), then its odds.
    cavity: Vec<f64>,
    nu: Intervals,
    out: Vec<f64>,
    /// Set once the cavities are odds and the likelihood is known (`nu`): where it starts
    /// (the voxels before get `free`), the likelihood beyond the last voxel, and the lengths'
    /// weight per metre of z-depth.
    ready: bool,
    first: usize,
    free: f64,
    beyond: f64,
    per_z: f64,
}

impl RayScratch {
    fn clear(&mut self) {
        self.n = 0;
        self.ready = false;
    }

    /// Makes the buffers at least `len` long (doubling).
    fn room(&mut self, len: usize) {
        if self.slots.len() < len {
            let len = len.max(2 * self.slots.len());
            self.slots.resize(len, 0);
            for v in [&mut self.z0, &mut self.z1, &mut self.cavity] {
                v.resize(len, 0.0);
            }
        }
    }

    /// The ray's factor from the first voxel with any likelihood on (of a `ready` ray).
    #[inline(always)]
    fn factor(&mut self) -> RayFactor<'_> {
        let (first, n) = (self.first, self.n);
        RayFactor {
            odds: &self.cavity[first..n],
            nu: &self.nu.density[first..],
            nu_beyond: self.beyond,
            out: &mut self.out,
        }
    }
}

impl MrfEngine {
    /// The pixel stride of tile `cols` x `rows` of `kf`: the largest power of two up to
    /// [`MAX_STRIDE`] whose rays, at the tile's nearest depth, lie at most
    /// [`MrfParams::ray_spacing`] voxel edges apart (1 with `ray_spacing` 0).
    fn tile_stride(&self, kf: &Keyframe, cols: &std::ops::Range<u32>, rows: &std::ops::Range<u32>) -> u32 {
        let spacing = self.params.ray_spacing * self.resolution();
        if spacing <= 0.0 {
            return 1;
        }
        let mut z_min = f32::INFINITY;
        for v in rows.clone() {
            for u in cols.clone() {
                if let Some(z) = kf.frame.depth.get(u, v) {
                    z_min = z_min.min(z);
                }
            }
        }
        // Pixel pitch at depth z: z / f (the camera's larger focal length, its finer pitch).
        let f = kf.frame.camera.fx.abs().max(kf.frame.camera.fy.abs());
        let mut stride = 1;
        while stride < MAX_STRIDE && (2 * stride) as f64 * z_min as f64 / f <= spacing {
            stride *= 2;
        }
        stride
    }

    /// Traces tiles `tiles` (ascending) of keyframe `i` against the current sums, then
    /// replaces their messages in the sums in tile order.
    pub(super) fn update_tiles(&mut self, i: usize, tiles: &[usize]) -> RunReport {
        let mut report = RunReport::default();
        if tiles.is_empty() {
            return report;
        }
        report.keyframe_updates = 1;
        report.tiles = tiles.len();
        // All traced against the same sums, then applied in tile order: the same sums
        // whatever the number of threads. (Held at once: a keyframe's new tiles with a change
        // per entry, 14 bytes per entry on top of what its tiles already hold.)
        let kf = &self.keyframes[i];
        // (The camera's rays per column and row: a ray then takes no division of `pixel_ray`.)
        let mut camera = CameraRays::default();
        let rays = FrameRays::with_camera_rays(&kf.frame, &mut camera);
        let pending: Vec<Traced> =
            tiles.par_iter().map_init(Scratch::default, |scratch, &t| self.trace_tile(kf, &rays, t, scratch)).collect();
        self.epoch += 1;
        for mut tr in pending {
            report.rays += tr.rays;
            for n in 0..tr.tile.runs.len() {
                let start = tr.tile.runs[n].1 as usize;
                let run = tr.tile.run(n).iter().zip(&tr.changes[start..]);
                self.apply_run(tr.tile.runs[n].0, run.map(|(e, d)| (e.slot(), *d)));
            }
            self.apply(&tr.gone);
            tr.tile.traced_at = self.epoch;
            self.keyframes[i].tiles[tr.index] = tr.tile;
        }
        report
    }

    /// Traces tile `t` of keyframe `kf`: every ray with its cavities, and the tile's new
    /// entries (damped against its old ones) and the changes they make to the sums. On a
    /// processor with AVX2 the trace runs in its copy compiled for it
    /// ([`MrfEngine::trace_tile_avx2`]).
    fn trace_tile<'a>(&'a self, kf: &Keyframe, rays: &FrameRays<'_>, t: usize, scratch: &mut Scratch<'a>) -> Traced {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the processor has AVX2 and FMA, checked just above.
            return unsafe { self.trace_tile_avx2(kf, rays, t, scratch) };
        }
        self.trace_tile_baseline(kf, rays, t, scratch)
    }
}

/// Defines a tile trace under `$name` (documented by `$doc`), and the two parts of its rays'
/// messages under `$prep` and `$msgs`, all with the attributes `$attr`: one source for the copy
/// built for the binary's baseline (SSE2 on x86-64) and the copy built for AVX2, picked at run time by
/// [`MrfEngine::trace_tile`]. The closures in a `target_feature` function are compiled with its
/// features; a body shared through an inlined function would keep its closures (the voxel
/// walk's, half of a trace) in the baseline's copy.
macro_rules! tile_trace {
    ($(#[$doc:meta])* $name:ident, $prep:ident, $msgs:ident, [$(#[$attr:meta])*]) => {
        impl MrfEngine {
            $(#[$doc])*
            $(#[$attr])*
            fn $name<'a>(
                &'a self,
                kf: &Keyframe,
                rays: &FrameRays<'_>,
                t: usize,
                all: &mut Scratch<'a>,
            ) -> Traced {
                let tile = &kf.tiles[t];
                let r = self.resolution();
                let inv_r = 1.0 / r;
                // The tile's voxels: old ones first (their message per metre is the rays' own share).
                let (scratch, bufs, max_room) = (&mut all.tile, &mut all.rays, all.max_room);
                scratch.clear();
                bufs.iter_mut().for_each(RayScratch::clear);
                for (n, &(brick, _)) in tile.runs.iter().enumerate() {
                    let t = scratch.table_or_new(brick, &self.sums);
                    for e in tile.run(n) {
                        scratch.voxel_in(t, brick.voxel(e.slot()), Some(*e));
                    }
                }
                let (cols, rows) = kf.tile_pixels(t);
                let (mut z_max, mut traced) = (0.0f64, 0usize);
                // The nearest camera z where a ray enters an allocated brick (the tile's next
                // `z_near`), and where this trace's walks start: a voxel before the tile's bound,
                // so that rounding where a walk starts cannot skip into a brick's first voxel.
                let mut z_first = f64::INFINITY;
                let z_near = tile.z_near as f64 - r;
                let depth = &kf.frame.depth;
                let stride = self.tile_stride(kf, &cols, &rows);
                for v0 in rows.clone().step_by(stride as usize) {
                    for u0 in cols.clone().step_by(stride as usize) {
                        // One ray, of the first valid pixel, stands for the valid pixels of its
                        // stride x stride block. (Plain loops: as iterator adapters they were
                        // calls compiled for the baseline, 3% of a trace.)
                        let (mut first, mut valid) = (None, 0u32);
                        for v in v0..(v0 + stride).min(rows.end) {
                            for u in u0..(u0 + stride).min(cols.end) {
                                if depth.get(u, v).is_some() {
                                    first = first.or(Some((u, v)));
                                    valid += 1;
                                }
                            }
                        }
                        let Some((u, v)) = first else { continue };
                        let weight = valid as f64;
                        let Some(ray) = rays.ray(u, v) else { continue };
                        let Some(seg) = self.limits.forward_model_segment(&ray, &kf.noise) else { continue };
                        traced += 1;
                        z_max = z_max.max(seg.end * ray.cz);
                        let (measured, cz) = (ray.range * ray.cz, ray.cz);
                        let mut likelihood = kf.noise.along_ray(ray.u, ray.v, measured);
                        // First the voxels, each with its cavity: everything it heard but this ray's
                        // own message. Then the likelihood of each, and the messages: each step in a
                        // loop of its own, which the processor overlaps across voxels (interleaved,
                        // each step of a voxel waited for the last).
                        // (Into the buffer that holds no ray waiting for its messages.)
                        let w = usize::from(bufs[0].ready);
                        // (A walk fails only for a non-finite ray, which has no voxels.)
                        let Some(walk) = Walk::new(ray.origin, ray.dir, r) else { continue };
                        // (No allocated brick lies before `z_near`: the walk starts there. Bricks
                        // that are not allocated are skipped, as the reference does.)
                        let (s_start, s_end) = (seg.start.max(z_near / cz), seg.end);
                        // The crossings go into buffers long enough for all of them (one per
                        // voxel face the segment passes, and some for rounding), apart from
                        // `scratch`: one bound check per crossing, where a push to each of four
                        // buffers inside `scratch` loaded and stored its length and capacity
                        // (0.89x the time of an ICL build, session 37). A walk that finds more
                        // crossings is walked again with room for them (the same crossings).
                        let buf = &mut bufs[w];
                        let faces = (s_end - s_start).max(0.0) * inv_r * ray.dir.iter().map(|d| d.abs()).sum::<f64>();
                        let mut room = (faces as usize).min(max_room) + 8;
                        buf.n = loop {
                            buf.room(room);
                            let (slots, z0, z1, cavities) =
                                (&mut buf.slots[..room], &mut buf.z0[..room], &mut buf.z1[..room], &mut buf.cavity[..room]);
                            let mut n = 0;
                            walk.crossings_in_bricks(
                                s_start,
                                s_end,
                                scratch,
                                |scratch, key, s| {
                                    let (table, sums) = scratch.table_of(key, &self.sums)?;
                                    let sums = sums?; // (a table kept for old entries in a freed brick)
                                    z_first = z_first.min(s * cz);
                                    Some((table, sums))
                                },
                                |scratch, (table, sums), slot, s_in, s_out| {
                                    // A crossing shorter than 1e-9 voxel edges (a ray within rounding
                                    // of a voxel's edge, or where a walk starts again at a brick face)
                                    // carries no length: it is skipped.
                                    let edges = (s_out - s_in) * inv_r;
                                    if edges < SLIVER {
                                        return;
                                    }
                                    let s = sums[slot];
                                    let i = scratch.voxel_at(table, slot);
                                    let cavity = (s - scratch.voxels[i].own * edges as f32) as f64;
                                    if n < room {
                                        slots[n] = i as u32;
                                        z0[n] = s_in * cz;
                                        z1[n] = s_out * cz;
                                        cavities[n] = cavity;
                                    }
                                    n += 1;
                                },
                            );
                            if n <= room {
                                break n;
                            }
                            room = n;
                        };
                        self.$prep(kf, &ray, &seg, &mut likelihood, weight, buf);
                        // A ray's messages wait for the next ray's, so that the two are
                        // computed side by side (a ray that met no voxel leaves it waiting).
                        if bufs.iter().all(|r| r.ready) {
                            self.$msgs(&mut scratch.voxels, bufs, 1 - w, true);
                        }
                    }
                }
                if let Some(w) = bufs.iter().position(|r| r.ready) {
                    self.$msgs(&mut scratch.voxels, bufs, w, false);
                }
                // New entries, damped in log-odds: part of the old message stays (a tile's first
                // message to a voxel goes in whole). A message whose change reverses direction from
                // one trace to the next is oscillating (voxels competing for one surface can cycle
                // under any fixed damping): the share of its change that goes in is halved, and
                // doubled back after `CALM_TRACES` traces in a row without a reversal (after one, a
                // period-four cycle, two reversals in four traces, was never damped). Damping changes
                // how a fixed point is approached, not where it is. Voxels its rays no longer reach
                // lose its message.
                let keep = self.params.damping;
                // The new tile by brick and slot, with each entry's change of the sum; voxels no ray
                // reaches any more lose the tile's message (`gone`, rare, in the same order, applied
                // after).
                let mut new = Tile { z_max: z_max as f32, z_near: f32_at_most(z_first), ..Tile::default() };
                new.entries.reserve_exact(scratch.voxels.len());
                let mut changes = Vec::with_capacity(scratch.voxels.len());
                let mut gone = Vec::new();
                for (i, seen) in scratch.sorted() {
                    let (voxel, (key, old_entry)) = (&scratch.voxels[i], scratch.keys[i]);
                    let old = old_entry.map_or(0.0, |e| e.message());
                    if voxel.length > 0.0 {
                        let mut entry = Entry::new(key.slot());
                        entry.set_edges(voxel.length);
                        entry.set_seen(seen);
                        match old_entry {
                            Some(e) => {
                                let change = voxel.sum - e.message() as f64;
                                let (level, calm) = if change * e.step_sign() < 0.0 {
                                    ((e.level() + 1).min(MAX_DAMPING_LEVEL), 0)
                                } else if e.calm() + 1 >= CALM_TRACES {
                                    (e.level().saturating_sub(1), 0)
                                } else {
                                    (e.level(), e.calm() + 1)
                                };
                                let step = (1.0 - keep) * change / (1u32 << level) as f64;
                                entry.set_message((e.message() as f64 + step) as f32);
                                entry.set_damping(level, calm, step);
                                if step != change {
                                    // The voxel's `S` after this update, and where the whole step would take it.
                                    let after = seen as f64 + step;
                                    let rest = (sigmoid(after + change - step) - sigmoid(after)).abs();
                                    new.held_back = new.held_back.max(rest as f32);
                                }
                            }
                            None => entry.set_message(voxel.sum as f32),
                        }
                        new.push(key, entry);
                        changes.push(entry.message() - old);
                    } else if old != 0.0 {
                        gone.push((key, -old));
                    }
                }
                new.entries.shrink_to_fit(); // (voxels no longer reached leave room)
                new.runs.shrink_to_fit();
                Traced { index: t, tile: new, changes, gone, rays: traced }
            }

            /// The first part of one walked ray's messages (its crossings in `buf`): its
            /// likelihood, and its cavities as odds. The ray is then `ready`, unless it has no
            /// voxels. Not inlined into the tile's trace, one very large function: with it
            /// inlined a build of coffin3 at 0.02 m took 1.04x the time (on coffin-world on
            /// two threads the two are within noise; BENCHMARKS.md, "MRF engine", session 33).
            $(#[$attr])*
            #[inline(never)]
            fn $prep(
                &self,
                kf: &Keyframe,
                ray: &PixelRay,
                seg: &Segment,
                likelihood: &mut RayLikelihood,
                weight: f64,
                buf: &mut RayScratch,
            ) {
                let (r, cz, n) = (self.resolution(), ray.cz, buf.n);
                if n == 0 {
                    return;
                }
                // The chance the surface lies past the segment (outside the map where the
                // bounds cut the ray short): the likelihood over one more stretch, computed
                // with the voxels' as one more interval (as a call of its own it was 5% of a
                // trace on icl-livingroom-5 at 0.02 m), then taken off.
                let stretch = seg.beyond_stretch(ray, &kf.noise, r);
                if let Some((z0, z1)) = stretch {
                    buf.room(n + 1);
                    (buf.z0[n], buf.z1[n]) = (z0, z1);
                }
                let intervals = n + usize::from(stretch.is_some());
                let skipped = likelihood.over_each(&buf.z0[..intervals], &buf.z1[..intervals], &mut buf.nu);
                buf.beyond = match stretch {
                    Some(_) => buf.nu.density.pop().unwrap_or(0.0),
                    None => 1.0,
                };
                // Voxels before the first one with any likelihood (the free stretch: at 0.02 m a
                // quarter of a ray's voxels on coffin-world, 46% on icl-livingroom-5, counted in
                // session 37) get the message 0 whatever anyone's
                // belief: a surface there would make the reading impossible. Nor does their
                // belief reach the other voxels' messages (the prefix of
                // `ray_log_messages` stays 0 through them). So they need no cavity and no
                // place in the ray's factor; their message is 0 (clamped), unless the ray has
                // no likelihood anywhere, beyond included, and says nothing (1/2).
                // (The first `skipped` are 0: the likelihood skipped them.)
                let nu = &buf.nu.density;
                let skipped = skipped.min(nu.len());
                buf.first = skipped + nu[skipped..].iter().position(|&nu| nu > 0.0).unwrap_or(nu.len() - skipped);
                buf.free = if buf.first < nu.len() || buf.beyond > 0.0 { logit(MSG_EPS) } else { 0.0 };
                // (A voxel's length in voxel edges, weighted: its z-depths' difference.)
                buf.per_z = weight * (1.0 / r) / cz;
                // (Over whole vectors, [`VECTOR_LANES`]: the padding's values are never read.)
                let padded = buf.first + (n - buf.first).next_multiple_of(VECTOR_LANES);
                buf.room(padded);
                for x in &mut buf.cavity[buf.first..padded] {
                    *x = exp(x.clamp(-MAX_LOG_ODDS, MAX_LOG_ODDS));
                }
                buf.ready = true;
            }

            /// The rest of the messages of the `ready` ray in buffer `w` and, with `both`, of
            /// the other's too (the one walked after it): the ray factor's messages, each
            /// added to the tile's voxel, weighted by its length, ray `w`'s first.
            $(#[$attr])*
            #[inline(never)]
            fn $msgs(&self, voxels: &mut [VoxelAcc], bufs: &mut [RayScratch; 2], w: usize, both: bool) {
                let bound = -logit(MSG_EPS);
                let [a, b] = bufs;
                let (this, next) = if w == 0 { (a, b) } else { (b, a) };
                if both {
                    ray_log_messages_pair(this.factor(), next.factor(), bound);
                } else {
                    let f = this.factor();
                    ray_log_messages(f.odds, f.nu, f.nu_beyond, bound, f.out);
                }
                for buf in [this, next].into_iter().take(1 + usize::from(both)) {
                    // Crossing `j`'s message `m` added to its voxel, weighted by its length.
                    let mut add = |j: usize, m: f64| {
                        let voxel = &mut voxels[buf.slots[j] as usize];
                        let length = buf.per_z * (buf.z1[j] - buf.z0[j]);
                        voxel.length += length;
                        voxel.sum += length * m;
                    };
                    for j in 0..buf.first {
                        add(j, buf.free);
                    }
                    for (j, &m) in (buf.first..).zip(&buf.out) {
                        add(j, m);
                    }
                    buf.ready = false;
                }
            }
        }
    };
}

tile_trace!(
    /// [`MrfEngine::trace_tile`] for any processor.
    trace_tile_baseline,
    ray_prepare_baseline,
    ray_messages_baseline,
    []
);

tile_trace!(
    /// [`MrfEngine::trace_tile`] compiled for AVX2 and FMA: the likelihood's, the cavities' and
    /// the messages' loops over a ray's voxels in four lanes instead of two. Bit for bit the
    /// same values (Rust never fuses a multiply and an add unasked, so FMA changes nothing);
    /// 0.93x the time of an MRF build (BENCHMARKS.md "MRF engine", session 25).
    trace_tile_avx2,
    ray_prepare_avx2,
    ray_messages_avx2,
    [#[cfg(target_arch = "x86_64")] #[target_feature(enable = "avx2,fma")]]
);

#[cfg(test)]
mod tests {
    use super::super::MrfParams;
    use super::super::tests::test_frames;
    use super::*;

    /// Walks that start at a tile's `z_near` reach the voxels of walks from the camera, with
    /// the same messages (but for the brick walk's rounding): before any trace, after one, and
    /// after a new keyframe allocated bricks in front of what the tiles had met.
    #[test]
    fn walks_from_the_near_bound_miss_nothing() {
        let frames = test_frames(3);
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        for frame in &frames {
            e.add_keyframe(frame.clone()).unwrap();
        }
        let compare = |e: &MrfEngine, what: &str| {
            let kf = &e.keyframes[1];
            let rays = FrameRays::new(&kf.frame);
            let (mut scratch, mut skipped, mut entries) = (Scratch::default(), 0, 0);
            for t in 0..kf.tiles.len() {
                let near = e.trace_tile(kf, &rays, t, &mut scratch);
                // The same tile walked from the camera.
                let mut from_camera = Keyframe {
                    id: kf.id,
                    frame: kf.frame.clone(),
                    noise: kf.noise.clone(),
                    bricks: Vec::new(),
                    tiles: kf.tiles.clone(),
                    tiles_x: kf.tiles_x,
                    checked_at: 0,
                };
                from_camera.tiles[t].z_near = 0.0;
                let full = e.trace_tile(&from_camera, &rays, t, &mut scratch);
                let keys = |tr: &Traced| tr.tile.iter().map(|(k, _)| k).collect::<Vec<_>>();
                assert_eq!(keys(&near), keys(&full), "{what}: tile {t}");
                for ((_, a), (_, b)) in near.tile.iter().zip(full.tile.iter()) {
                    assert!((a.message() - b.message()).abs() <= 1e-5 * a.message().abs().max(1.0), "{what}: tile {t}");
                }
                skipped += (kf.tiles[t].z_near > 0.0) as usize;
                entries += near.tile.entries.len();
            }
            assert!(
                skipped > 10 && entries > 1000,
                "{what}: {skipped} tiles start their walks late, {entries} entries"
            );
        };
        // Before any trace, from the bricks' corners alone.
        compare(&e, "before a trace");
        e.run(1);
        compare(&e, "after a sweep");
        // A keyframe whose surfaces lie halfway to keyframe 1's allocates bricks in front of
        // everything its tiles had met: their bounds come down, and their walks still find
        // every voxel.
        let before: Vec<f32> = e.keyframes[1].tiles.iter().map(|t| t.z_near).collect();
        let mut nearer = frames[1].clone();
        for v in 0..nearer.depth.height() {
            for u in 0..nearer.depth.width() {
                if let Some(z) = nearer.depth.get(u, v) {
                    nearer.depth.set(u, v, 0.5 * z);
                }
            }
        }
        e.add_keyframe(nearer).unwrap();
        let lowered = e.keyframes[1].tiles.iter().zip(&before).filter(|(t, b)| t.z_near < **b).count();
        assert!(lowered > 10, "{lowered} tiles' bounds came down");
        compare(&e, "after a nearer keyframe");
    }

    /// A ray with more crossings than its buffers had room for is walked again, and the tile's
    /// trace is the same, bit for bit.
    #[test]
    fn a_walk_out_of_room_is_walked_again_alike() {
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        for frame in test_frames(3) {
            e.add_keyframe(frame).unwrap();
        }
        e.run(1);
        let kf = &e.keyframes[1];
        let rays = FrameRays::new(&kf.frame);
        let (mut roomy, mut tight) = (Scratch::default(), Scratch { max_room: 0, ..Scratch::default() });
        let mut entries = 0;
        for t in 0..kf.tiles.len() {
            let (a, b) = (e.trace_tile(kf, &rays, t, &mut roomy), e.trace_tile(kf, &rays, t, &mut tight));
            let show = |tr: &Traced| format!("{:?} {:?} {:?} {}", tr.tile, tr.changes, tr.gone, tr.rays);
            assert_eq!(show(&a), show(&b), "tile {t}");
            entries += a.tile.entries.len();
        }
        // (With no room at first, every ray longer than 8 crossings was walked twice.)
        assert!(entries > 1000 && tight.rays.iter().any(|r| r.slots.len() > 8), "{entries} entries");
    }

    /// The AVX2 copy of the tile trace gives the baseline copy's tiles bit for bit. (Every
    /// other test runs the copy this machine picks; this one runs both.)
    #[test]
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))] // (no second copy to count)
    fn both_copies_of_a_tile_trace_agree() {
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        for frame in test_frames(3) {
            e.add_keyframe(frame).unwrap();
        }
        e.run(1); // beliefs away from the prior, so the cavities and messages vary
        let kf = &e.keyframes[1];
        let rays = FrameRays::new(&kf.frame);
        let mut scratch = (Scratch::default(), Scratch::default());
        let (mut entries, mut compared) = (0, 0);
        for t in 0..kf.tiles.len() {
            let base = e.trace_tile_baseline(kf, &rays, t, &mut scratch.0);
            entries += base.tile.entries.len();
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                // SAFETY: the processor has AVX2 and FMA, checked just above.
                let fast = unsafe { e.trace_tile_avx2(kf, &rays, t, &mut scratch.1) };
                let show = |tr: &Traced| format!("{:?} {:?} {:?} {}", tr.tile, tr.changes, tr.gone, tr.rays);
                assert_eq!(show(&base), show(&fast), "tile {t}");
                compared += 1;
            }
        }
        assert!(entries > 1000, "the scene's tiles reach {entries} voxels");
        if compared == 0 {
            eprintln!("skipped: this processor has no AVX2, only the baseline copy ran");
        }
    }
}
