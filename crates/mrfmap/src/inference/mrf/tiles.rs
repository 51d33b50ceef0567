//! Keyframes and their tiles: the per-voxel bookkeeping ([`Entry`], 10 bytes) of each
//! 16x16-pixel tile, which tiles a brick may reach, and the bricks keyframes allocate and free
//! (see the module docs of [`super`] for a tile's life).

use std::ops::ControlFlow;
use std::sync::Arc;

use rayon::prelude::*;
use rustc_hash::FxHashSet;

use super::{Allocation, KeyframeId, MrfEngine};
use crate::frames::{Frame, NoiseModel};
use crate::inference::Engine;
use crate::inference::logit;
use crate::map::{BRICK_EDGE, BrickKey, VoxelKey};
use crate::rays::{FrameRays, for_each_crossing, pose_parts};

/// Pixels per side of a tile, the unit of bookkeeping and re-tracing (see the module docs).
pub const TILE: u32 = 16;

/// One voxel that a tile's rays reach (10 bytes; its brick is the tile's run's). The tiles
/// are most of the engine's memory (22 million entries for coffin-world at 0.01 m), so the
/// fields are 16 bits wide: the message is an `f32` kept as two halves, so that the entry
/// needs no 4-byte alignment (12 bytes otherwise).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Entry {
    /// The tile's message to the voxel (log-odds), the bits of an `f32`: its rays' messages,
    /// each weighted by its length over the voxel edge, summed and damped. Kept exactly:
    /// removal subtracts it.
    message: [u16; 2],
    /// Summed length of the tile's rays in the voxel, in 1/[`LENGTH_STEPS`] voxel edges (a
    /// tile's 256 rays reach at most 443 edges; saturates at 512). It only apportions the
    /// message among the rays for their cavities.
    length: u16,
    /// The voxel's `S` that the tile's rays saw when it last traced, in 1/[`SEEN_STEPS`]
    /// log-odds, saturating at +-32 (where marginals differ from 0 or 1 by 1e-14): the
    /// rounding moves a marginal by at most 1.2e-4, a tenth of the default tolerance.
    seen: i16,
    /// Bits 0-8: the voxel's slot in its brick. Bits 9-15: `9 level + 3 calm + sign`, where
    /// `level` (0-8) is the extra damping (the share of a change that goes in is halved this
    /// many times), `calm` (0-2) counts the traces in a row whose change did not reverse, and
    /// `sign` is the last change's: 0 none, 1 positive, 2 negative.
    packed: u16,
}

// The tiles' memory is 10 bytes per entry, and the damping state fits its 7 bits.
const _: () = assert!(std::mem::size_of::<Entry>() == 10);

const _: () = assert!(9 * MAX_DAMPING_LEVEL as u16 + 3 * (CALM_TRACES as u16 - 1) + 2 < 1 << 7);

/// Steps per voxel edge of [`Entry::length`].
const LENGTH_STEPS: f64 = 128.0;

/// Steps per unit of log-odds of [`Entry::seen`].
const SEEN_STEPS: f32 = 1024.0;

impl Entry {
    /// The entry of the voxel in `slot`, with no damping and no change yet.
    pub(super) fn new(slot: usize) -> Entry {
        Entry { packed: slot as u16, ..Entry::default() }
    }

    /// The message (log-odds).
    pub(super) fn message(&self) -> f32 {
        f32::from_bits(self.message[0] as u32 | (self.message[1] as u32) << 16)
    }

    pub(super) fn set_message(&mut self, m: f32) {
        let bits = m.to_bits();
        self.message = [bits as u16, (bits >> 16) as u16];
    }

    /// The voxel's slot in its brick.
    pub(super) fn slot(&self) -> usize {
        (self.packed & 0x1ff) as usize
    }

    /// The summed length in voxel edges.
    pub(super) fn edges(&self) -> f32 {
        self.length as f32 / LENGTH_STEPS as f32
    }

    pub(super) fn set_edges(&mut self, edges: f64) {
        self.length = (edges * LENGTH_STEPS).round().min(u16::MAX as f64) as u16;
    }

    /// The `S` the tile saw.
    pub(super) fn seen(&self) -> f32 {
        self.seen as f32 / SEEN_STEPS
    }

    pub(super) fn set_seen(&mut self, s: f32) {
        self.seen = (s * SEEN_STEPS).round().clamp(-(i16::MAX as f32), i16::MAX as f32) as i16;
    }

    /// `9 level + 3 calm + sign` (see [`Entry::packed`]).
    pub(super) fn damping(&self) -> u8 {
        (self.packed >> 9) as u8
    }

    /// Extra damping level.
    pub(super) fn level(&self) -> u8 {
        self.damping() / 9
    }

    /// Traces in a row without a reversal.
    pub(super) fn calm(&self) -> u8 {
        self.damping() / 3 % 3
    }

    /// The sign of the message's last change (0 for none).
    pub(super) fn step_sign(&self) -> f64 {
        match self.damping() % 3 {
            1 => 1.0,
            2 => -1.0,
            _ => 0.0,
        }
    }

    /// Records the damping level (at most [`MAX_DAMPING_LEVEL`]), the calm count (below
    /// [`CALM_TRACES`]) and the sign of the last change, `step`.
    pub(super) fn set_damping(&mut self, level: u8, calm: u8, step: f64) {
        let sign = if step > 0.0 {
            1
        } else if step < 0.0 {
            2
        } else {
            0
        };
        let code = 9 * level.min(MAX_DAMPING_LEVEL) as u16 + 3 * calm.min(CALM_TRACES - 1) as u16 + sign;
        self.packed = (self.packed & 0x1ff) | code << 9;
    }
}

/// Cap on an entry's extra damping level (its changes go in at 2^-8 of the plain share).
pub(super) const MAX_DAMPING_LEVEL: u8 = 8;

/// Traces in a row without a reversal after which an entry's extra damping level drops by one.
pub(super) const CALM_TRACES: u8 = 3;

#[derive(Clone, Debug, Default)]
pub(super) struct Tile {
    /// Sorted by brick, then slot, so that consecutive entries share a brick lookup.
    pub(super) entries: Vec<Entry>,
    /// Each brick of the entries with the index of its first entry.
    pub(super) runs: Vec<(BrickKey, u32)>,
    /// The `MrfEngine::epoch` of its last trace.
    pub(super) traced_at: u64,
    /// Must be re-traced: new, moved, or a brick its rays may cross came or went.
    pub(super) stale: bool,
    /// A brick its rays may cross changed since the keyframe's last check.
    pub(super) suspect: bool,
    /// The largest camera z its rays reach (m); new bricks beyond it cannot affect it.
    pub(super) z_max: f32,
    /// A camera z (m) before which none of its rays meets an allocated brick: where its last
    /// trace's rays first met one, lowered since to the nearest corner of each brick
    /// allocated that may reach it; before its first trace, the nearest corner of the bricks
    /// allocated then that may reach it ([`Keyframe::bound_tiles`]). A trace starts its rays'
    /// walks a voxel before it (so that rounding cannot start a walk inside the first brick):
    /// at 0.02 m a ray crossed about 39 bricks, most of them empty space in front of the band
    /// of allocated bricks around the surfaces.
    pub(super) z_near: f32,
    /// How far (in marginal) its last update fell short of what its rays computed, where
    /// damping held a message back: the largest move the rest of the step would make.
    pub(super) held_back: f32,
    /// The online schedule's backlog priority ([`MrfEngine::refine`]): the largest marginal
    /// move of a voxel its rays reach since it traced, as far as the checks so far found
    /// (0 until a check finds one; a trace resets it).
    pub(super) priority: f32,
}

impl Tile {
    /// The entries of run `n` (brick `runs[n].0`).
    pub(super) fn run(&self, n: usize) -> &[Entry] {
        let end = self.runs.get(n + 1).map_or(self.entries.len(), |r| r.1 as usize);
        &self.entries[self.runs[n].1 as usize..end]
    }

    /// Every entry with its voxel.
    pub(super) fn iter(&self) -> impl Iterator<Item = (VoxelKey, &Entry)> + '_ {
        (0..self.runs.len()).flat_map(move |n| self.run(n).iter().map(move |e| (self.runs[n].0.voxel(e.slot()), e)))
    }

    /// Appends the entry of voxel `key` (entries come sorted by brick and slot).
    pub(super) fn push(&mut self, key: VoxelKey, entry: Entry) {
        if self.runs.last().is_none_or(|&(b, _)| b != key.brick()) {
            self.runs.push((key.brick(), self.entries.len() as u32));
        }
        self.entries.push(entry);
    }

    /// Drops the entries in bricks `freed`; true if there were any.
    fn drop_bricks(&mut self, freed: &FxHashSet<BrickKey>) -> bool {
        if !self.runs.iter().any(|(b, _)| freed.contains(b)) {
            return false;
        }
        let mut kept =
            Tile { stale: true, traced_at: self.traced_at, z_max: self.z_max, z_near: self.z_near, ..Tile::default() };
        kept.entries.reserve_exact(self.entries.len());
        for (k, e) in self.iter().filter(|(k, _)| !freed.contains(&k.brick())) {
            kept.push(k, *e);
        }
        kept.entries.shrink_to_fit();
        kept.runs.shrink_to_fit();
        *self = kept;
        true
    }
}

/// The largest `f32` at most `z` (a bound must not round up past what it bounds).
pub(super) fn f32_at_most(z: f64) -> f32 {
    let f = z as f32;
    if f as f64 > z { f.next_down() } else { f }
}

pub(super) struct Keyframe {
    pub(super) id: KeyframeId,
    pub(super) frame: Frame,
    pub(super) noise: Arc<NoiseModel>,
    /// Bricks this keyframe allocated (counted in `MrfEngine::brick_refs`).
    pub(super) bricks: Vec<BrickKey>,
    /// Row-major, `tiles_x` per row.
    pub(super) tiles: Vec<Tile>,
    pub(super) tiles_x: u32,
    /// The `MrfEngine::epoch` when `run_until` last checked its tiles.
    pub(super) checked_at: u64,
}

impl Keyframe {
    /// The pixel columns and rows of tile `t`.
    pub(super) fn tile_pixels(&self, t: usize) -> (std::ops::Range<u32>, std::ops::Range<u32>) {
        let (tx, ty) = (t as u32 % self.tiles_x, t as u32 / self.tiles_x);
        let (w, h) = (self.frame.depth.width(), self.frame.depth.height());
        (tx * TILE..((tx + 1) * TILE).min(w), ty * TILE..((ty + 1) * TILE).min(h))
    }

    /// The world-to-camera rotation and the camera's origin.
    pub(super) fn to_camera(&self) -> (nalgebra::Matrix3<f64>, [f64; 3]) {
        let (rotation, origin) = pose_parts(&self.frame.pose);
        (rotation.transpose(), origin)
    }

    /// Calls `visit` on every tile whose rays may cross brick `b` (of edge `edge` m), with
    /// the camera z of the brick's nearest corner: the brick's projection (the box around its
    /// projected corners, a pixel wider) overlaps the tile, and its nearest point is no
    /// farther than the tile's rays reach. A ray that crosses the brick passes through its
    /// projection, at a depth at least the brick's smallest, so no such tile is missed.
    ///
    /// A brick that reaches behind the camera plane projects without bound, but not
    /// everywhere: its points in front of the camera lie in the box around its corners in
    /// camera axes, with `z` up to the largest corner's, so along an axis where that box lies
    /// wholly on one side of the optical axis the projection is bounded on that side's inner
    /// edge (`x / z >= x_min / z_max` for `x_min > 0`). The floor under a camera looking ahead
    /// projects below the image instead of onto all of it.
    pub(super) fn for_tiles_reaching(
        &mut self,
        to_camera: &(nalgebra::Matrix3<f64>, [f64; 3]),
        b: BrickKey,
        edge: f64,
        mut visit: impl FnMut(&mut Tile, f64),
    ) {
        let (rotation, origin) = to_camera;
        let camera = &self.frame.camera;
        let (w, h) = (camera.width as f64, camera.height as f64);
        let (mut z_min, mut z_max) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        // The box around the corners in camera x and y.
        let (mut axis_lo, mut axis_hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        let mut behind = false;
        for c in 0..8 {
            let p = nalgebra::Vector3::from_fn(|a, _| (b.0[a] as f64 + (c >> a & 1) as f64) * edge - origin[a]);
            let q = rotation * p;
            z_min = z_min.min(q.z);
            z_max = z_max.max(q.z);
            for a in 0..2 {
                axis_lo[a] = axis_lo[a].min(q[a]);
                axis_hi[a] = axis_hi[a].max(q[a]);
            }
            match camera.project(&q) {
                Some((u, v)) if q.z > 1e-9 => {
                    lo = [lo[0].min(u - 1.0), lo[1].min(v - 1.0)];
                    hi = [hi[0].max(u + 1.0), hi[1].max(v + 1.0)];
                }
                _ => behind = true,
            }
        }
        if z_max <= 0.0 {
            // Wholly behind the camera: rays only go forward. (Before this check, every tile
            // of a keyframe facing away from a new brick was marked stale: an add re-traced
            // whole keyframes that could not see it.)
            return;
        }
        if behind {
            // A corner at or behind the camera plane: per image axis, the range of `x / z`
            // over the box's points in front of the camera, then of the pixel coordinate.
            for (a, (f, c)) in [(camera.fx, camera.cx), (camera.fy, camera.cy)].into_iter().enumerate() {
                let (t_lo, t_hi) = match (axis_lo[a] > 0.0, axis_hi[a] < 0.0) {
                    (true, _) => (axis_lo[a] / z_max, f64::INFINITY),
                    (_, true) => (f64::NEG_INFINITY, axis_hi[a] / z_max),
                    _ => (f64::NEG_INFINITY, f64::INFINITY),
                };
                // (An infinite end times a focal length keeps its sign's meaning.)
                let (p, q) = (f * t_lo + c, f * t_hi + c);
                (lo[a], hi[a]) = (p.min(q) - 1.0, p.max(q) + 1.0);
            }
        }
        if hi[0] < 0.0 || hi[1] < 0.0 || lo[0] >= w || lo[1] >= h {
            return;
        }
        let cols = (lo[0].max(0.0) as u32 / TILE)..=((hi[0].min(w - 1.0)) as u32 / TILE);
        let rows = (lo[1].max(0.0) as u32 / TILE)..=((hi[1].min(h - 1.0)) as u32 / TILE);
        for ty in rows {
            for tx in cols.clone() {
                let tile = &mut self.tiles[(ty * self.tiles_x + tx) as usize];
                if z_min <= tile.z_max as f64 {
                    visit(tile, z_min);
                }
            }
        }
    }

    /// Forgets every message and marks every tile for tracing, with no near bound yet
    /// (nothing known of what its rays may reach).
    pub(super) fn reset_tiles(&mut self) {
        let (w, h) = (self.frame.depth.width(), self.frame.depth.height());
        self.tiles_x = w.div_ceil(TILE);
        let n = (self.tiles_x * h.div_ceil(TILE)) as usize;
        self.tiles = vec![Tile { stale: true, z_max: f32::INFINITY, z_near: f32::INFINITY, ..Tile::default() }; n];
    }

    /// Gives tiles just reset ([`Keyframe::reset_tiles`]) their near bound: the nearest
    /// corner of the bricks `allocated` (of edge `edge` m) that may reach each. Before it a
    /// first trace walked its rays from the camera, through empty space no keyframe had
    /// mapped.
    pub(super) fn bound_tiles<'a>(&mut self, allocated: impl Iterator<Item = &'a BrickKey>, edge: f64) {
        let to_camera = self.to_camera();
        for b in allocated {
            self.for_tiles_reaching(&to_camera, *b, edge, |tile, z_min| {
                tile.z_near = tile.z_near.min(f32_at_most(z_min));
            });
        }
    }
}

impl MrfEngine {
    /// A brick's edge (m).
    pub(super) fn brick_edge(&self) -> f64 {
        self.resolution() * BRICK_EDGE as f64
    }

    /// References `bricks`; returns those that were not allocated before (they start at the
    /// prior; a brick already allocated keeps its sums).
    pub(super) fn reference_bricks(&mut self, bricks: &[BrickKey]) -> Vec<BrickKey> {
        let prior = logit(self.params.prior) as f32;
        let mut new = Vec::new();
        for &b in bricks {
            let refs = self.brick_refs.entry(b).or_insert(0);
            *refs += 1;
            if *refs == 1 {
                for grid in [&mut self.sums, &mut self.logged] {
                    grid.brick_or_insert(b).update_slots(&[u64::MAX; 8], prior, |_| ());
                }
                new.push(b);
            }
        }
        new
    }

    /// Marks stale every tile whose rays may cross one of the new `bricks`: the brick's
    /// corners projected into the keyframe's image overlap the tile, and the brick's nearest
    /// corner is no farther than the tile's rays reach; the tile's near bound comes down to
    /// that corner if it lay beyond. Tiles never traced are stale already.
    pub(super) fn mark_tiles_reaching(&mut self, bricks: &[BrickKey]) {
        if bricks.is_empty() {
            return;
        }
        let edge = self.brick_edge();
        self.keyframes.par_iter_mut().for_each(|kf| {
            let to_camera = kf.to_camera();
            for b in bricks {
                kf.for_tiles_reaching(&to_camera, *b, edge, |tile, z_min| {
                    tile.stale = true;
                    tile.z_near = tile.z_near.min(f32_at_most(z_min));
                });
            }
        });
    }

    /// Drops a reference to each brick; bricks nobody references leave the map, and every
    /// tile's messages in them go too (as if they had never been allocated; those tiles are
    /// marked stale).
    pub(super) fn release_bricks(&mut self, bricks: &[BrickKey]) {
        let mut freed = FxHashSet::default();
        for b in bricks {
            if let Some(refs) = self.brick_refs.get_mut(b) {
                *refs -= 1;
                if *refs == 0 {
                    self.brick_refs.remove(b);
                    freed.insert(*b);
                }
            }
        }
        if freed.is_empty() {
            return;
        }
        let list: Vec<BrickKey> = freed.iter().copied().collect();
        self.sums.remove_bricks(&list);
        self.logged.remove_bricks(&list);
        self.stamps.retain(|b, _| !freed.contains(b));
        self.keyframes.par_iter_mut().flat_map(|k| &mut k.tiles).for_each(|tile| {
            tile.drop_bricks(&freed);
        });
    }

    /// The bricks keyframe `kf` allocates.
    pub(super) fn allocation_of(&self, kf: &Keyframe) -> Vec<BrickKey> {
        let r = self.resolution();
        let rays = FrameRays::new(&kf.frame);
        let full = self.params.allocation == Allocation::Full;
        let limits = self.limits;
        let mut bricks: Vec<BrickKey> = (0..rays.rows())
            .into_par_iter()
            .fold(FxHashSet::default, |mut out: FxHashSet<BrickKey>, v| {
                // Neighbouring pixels' depth points often share a voxel: its bricks once.
                let mut last = None;
                for ray in rays.row(v) {
                    let Some(seg) = limits.forward_model_segment(&ray, &kf.noise) else { continue };
                    if seg.hits_surface {
                        // Bricks of the voxels within one voxel of the depth point: one to
                        // eight (the same brick unless the voxel is on a brick's face).
                        let k = VoxelKey::from_point(FrameRays::endpoint(&ray), r);
                        if last != Some(k) {
                            last = Some(k);
                            let lo = VoxelKey(k.0.map(|i| i - 1)).brick().0;
                            let hi = VoxelKey(k.0.map(|i| i + 1)).brick().0;
                            for z in lo[2]..=hi[2] {
                                for y in lo[1]..=hi[1] {
                                    for x in lo[0]..=hi[0] {
                                        out.insert(BrickKey([x, y, z]));
                                    }
                                }
                            }
                        }
                    }
                    if full {
                        let edge = r * BRICK_EDGE as f64;
                        for_each_crossing(ray.origin, ray.dir, seg.start, seg.end, edge, |c| {
                            out.insert(BrickKey(c.key.0));
                            ControlFlow::Continue(())
                        });
                    }
                }
                out
            })
            .reduce(FxHashSet::default, |mut a, b| {
                a.extend(b);
                a
            })
            .into_iter()
            .collect();
        bricks.sort_unstable();
        bricks
    }

    /// Takes keyframe `i`'s messages out of the sums and forgets them (exactly: each tile
    /// knows its messages).
    pub(super) fn withdraw_messages(&mut self, i: usize) {
        self.epoch += 1;
        let tiles = std::mem::take(&mut self.keyframes[i].tiles);
        for tile in &tiles {
            let out: Vec<(VoxelKey, f32)> = tile.iter().map(|(k, e)| (k, -e.message())).collect();
            self.apply(&out);
        }
        self.keyframes[i].reset_tiles();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inference::MrfParams;
    use crate::inference::mrf::tests::test_scene;
    use crate::map::BRICK_VOXELS;

    /// Every field of a packed entry reads back what was written, whatever its neighbours
    /// hold: messages bit for bit (removal subtracts exactly what went in), every damping state.
    #[test]
    fn entries_keep_every_field() {
        let mut rng = crate::random::Rng::new(13);
        for n in 0..2000 {
            let slot = n % BRICK_VOXELS;
            let mut e = Entry::new(slot);
            assert_eq!((e.level(), e.calm(), e.step_sign()), (0, 0, 0.0));
            let m = (rng.range(-1.0, 1.0) * 10f64.powf(rng.range(-8.0, 4.0))) as f32;
            e.set_message(m);
            e.set_edges(rng.range(0.0, 500.0));
            e.set_seen(rng.range(-40.0, 40.0) as f32);
            let (edges, seen) = (e.edges(), e.seen());
            let level = (n % (MAX_DAMPING_LEVEL as usize + 1)) as u8;
            let calm = (n / 9 % CALM_TRACES as usize) as u8;
            let step = [1.5, -0.25, 0.0][n / 27 % 3];
            e.set_damping(level, calm, step);
            assert_eq!(e.message().to_bits(), m.to_bits());
            assert_eq!(e.slot(), slot);
            assert_eq!((e.level(), e.calm(), e.step_sign()), (level, calm, step.signum() * (step != 0.0) as u8 as f64));
            assert_eq!((e.edges(), e.seen()), (edges, seen));
        }
    }

    /// Rays only go forward: a brick wholly behind a camera reaches none of its tiles, one it
    /// looks at reaches some.
    #[test]
    fn bricks_behind_a_camera_reach_no_tile() {
        let scene = test_scene(1);
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        e.add_keyframe(scene.frame(0, &scene.views[0], Some(1))).unwrap();
        e.run(1);
        let edge = 0.05 * BRICK_EDGE as f64;
        let kf = &mut e.keyframes[0];
        let to_camera = kf.to_camera();
        let origin = to_camera.1;
        // The scene's centre, and a point as far behind the camera.
        let ahead = [0.0, 0.0, 0.3];
        let behind: Vec<f64> = (0..3).map(|a| 2.0 * origin[a] - ahead[a]).collect();
        let brick = |p: &[f64]| VoxelKey::from_point([p[0], p[1], p[2]], 0.05).brick();
        let mut reached = |p: &[f64]| {
            let mut n = 0;
            kf.for_tiles_reaching(&to_camera, brick(p), edge, |_, _| n += 1);
            n
        };
        assert!(reached(&ahead) > 0);
        assert_eq!(reached(&behind), 0);
    }

    /// Brute force: every pixel whose ray (through a random point of the pixel) crosses a
    /// brick lies in a tile the brick reaches, with at most the camera z where the ray enters
    /// it, for cameras at random poses and bricks all around them, the ones through the
    /// camera plane included; and some of those reach only part of the image.
    #[test]
    fn bricks_reach_every_tile_their_rays_cross() {
        let scene = test_scene(1);
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        e.add_keyframe(scene.frame(0, &scene.views[0], Some(1))).unwrap();
        let kf = &mut e.keyframes[0];
        kf.reset_tiles(); // (every tile reachable: nothing bounds its rays' reach yet)
        let camera = kf.frame.camera;
        let edge = 0.2;
        let mut rng = crate::random::Rng::new(5);
        let (mut through, mut partly, mut crossed) = (0, 0, 0);
        for _ in 0..12 {
            let q = nalgebra::Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            let rotation = *nalgebra::UnitQuaternion::from_quaternion(q).to_rotation_matrix().matrix();
            let origin = [(); 3].map(|_| rng.range(-1.0, 1.0));
            let to_camera = (rotation, origin);
            let centre = origin.map(|c| (c / edge).floor() as i32);
            for n in 0..7 * 7 * 7 {
                let d = [n % 7, n / 7 % 7, n / 49];
                let b = BrickKey([0, 1, 2].map(|a| centre[a] + d[a] - 3));
                // Each tile's `priority` holds the z the brick reached it with (infinite: not reached).
                kf.tiles.iter_mut().for_each(|t| t.priority = f32::INFINITY);
                kf.for_tiles_reaching(&to_camera, b, edge, |tile, z| tile.priority = z as f32);
                let corner =
                    |c: i32| nalgebra::Vector3::from_fn(|a, _| (b.0[a] + (c >> a & 1)) as f64 * edge - origin[a]);
                let z: Vec<f64> = (0..8).map(|c| (rotation * corner(c)).z).collect();
                if z.iter().any(|&z| z <= 0.0) && z.iter().any(|&z| z > 0.0) {
                    through += 1;
                    partly += kf.tiles.iter().any(|t| t.priority.is_infinite()) as usize;
                }
                for (u, v) in (0..camera.height).flat_map(|v| (0..camera.width).map(move |u| (u, v))) {
                    // The ray in camera axes (z 1 per unit of length), then in the world's.
                    let (x, y) = (u as f64 + rng.uniform(), v as f64 + rng.uniform());
                    let ray = nalgebra::Vector3::new((x - camera.cx) / camera.fx, (y - camera.cy) / camera.fy, 1.0);
                    let dir = rotation.transpose() * ray;
                    // Where it enters and leaves the brick (slabs), in camera z.
                    let (mut enter, mut leave) = (0.0f64, f64::INFINITY);
                    for a in 0..3 {
                        let (lo, hi) = (b.0[a] as f64 * edge - origin[a], (b.0[a] + 1) as f64 * edge - origin[a]);
                        let (t0, t1) = (lo / dir[a], hi / dir[a]); // (a zero step: both infinite, or NaN on a face)
                        (enter, leave) = (enter.max(t0.min(t1)), leave.min(t0.max(t1)));
                    }
                    if enter < leave {
                        crossed += 1;
                        let tile = &kf.tiles[(v / TILE * kf.tiles_x + u / TILE) as usize];
                        assert!(
                            tile.priority as f64 <= enter + 1e-9,
                            "brick {b:?}, pixel ({x:.2}, {y:.2}) enters at z {enter:.3}"
                        );
                    }
                }
            }
        }
        assert!(
            through > 100 && partly > 10 && crossed > 100_000,
            "{through} bricks through the camera plane, {partly} reach part of the image; {crossed} rays crossed"
        );
    }
}
