//! The change log and the batch schedules: every change to a sum goes through
//! [`MrfEngine::apply_run`], which logs its brick; checks project the logged bricks into each
//! keyframe's tiles; [`MrfEngine::run`] sweeps every tile, [`MrfEngine::run_until`] only the
//! dirty ones (see the module docs of [`super`]).

use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::MrfEngine;
use super::tiles::Tile;
use crate::inference::sigmoid;
use crate::map::{Brick, BrickKey, Grid, VoxelKey};

/// What a schedule ([`MrfEngine::run`], [`MrfEngine::run_until`]) did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RunReport {
    /// Sweeps over the keyframes.
    pub sweeps: usize,
    /// Keyframe updates (a keyframe with at least one tile traced) in all.
    pub keyframe_updates: usize,
    /// Tiles traced in all.
    pub tiles: usize,
    /// Rays traced in all.
    pub rays: usize,
    /// Whether the last sweep had nothing left to trace (always false for [`MrfEngine::run`]).
    pub converged: bool,
}

impl RunReport {
    pub(super) fn add(&mut self, other: RunReport) {
        self.keyframe_updates += other.keyframe_updates;
        self.tiles += other.tiles;
        self.rays += other.rays;
    }

    /// The debug line of sweep `sweep`: what was traced since the report was `start`.
    fn log_sweep(&self, sweep: usize, start: &RunReport) {
        tracing::debug!("sweep {sweep}: {} tiles, {} rays traced", self.tiles - start.tiles, self.rays - start.rays);
    }
}

/// The largest marginal move, since `tile` traced, of a voxel its rays reach, or 1 when one
/// left the map. Only bricks that some update changed since the trace are read: those in
/// `recent` (every brick logged since the tile's keyframe was last checked; the tile traced
/// after that check or in the update just before it), else those stamped since. Moves up to
/// `floor` are not measured (0 is returned when there are only such), and it stops early
/// once the move exceeds `enough`.
pub(super) fn largest_move(
    sums: &Grid<f32>,
    stamps: &FxHashMap<BrickKey, u64>,
    tile: &Tile,
    recent: Option<&FxHashSet<BrickKey>>,
    floor: f64,
    enough: f64,
) -> f64 {
    let mut largest = 0.0f64;
    for (n, &(bk, _)) in tile.runs.iter().enumerate() {
        let changed = match recent {
            Some(r) => r.contains(&bk),
            None => stamps.get(&bk).is_some_and(|&e| e >= tile.traced_at),
        };
        if !changed {
            continue;
        }
        let Some(brick) = sums.brick(bk).and_then(Brick::dense) else { return 1.0 };
        for e in tile.run(n) {
            let s = brick[e.slot()];
            // |d sigmoid| <= |dS| / 4: the exponentials only for changes that may matter.
            let seen = e.seen();
            if (s - seen).abs() as f64 > 4.0 * largest.max(floor) {
                largest = largest.max((sigmoid(s as f64) - sigmoid(seen as f64)).abs());
                if largest > enough {
                    return largest;
                }
            }
        }
    }
    largest
}

impl MrfEngine {
    /// Belief propagation until nothing moves (change-driven). Each sweep visits the
    /// keyframes in turn and re-traces only their tiles for which, since the tile last traced,
    /// some voxel its rays reach moved by more than `tolerance` in marginal (by any tile,
    /// the tile's own last update included), whose last update damping held back by more than
    /// `tolerance` (a voxel whose marginal sits at 0 or 1 hardly moves while a damped message
    /// crawls towards the other side), or which are stale (new, moved, or near a brick that
    /// came or went). Stops when a sweep traces nothing, or after `max_sweeps` sweeps.
    /// Changes below the tolerance are not followed, so the result is within a small multiple
    /// of it of a fixed point, not at it.
    pub fn run_until(&mut self, tolerance: f64, max_sweeps: usize) -> RunReport {
        self.run_until_with_progress(tolerance, max_sweeps, &mut |_, _| {})
    }

    /// [`MrfEngine::run_until`], calling `progress(sweep, max_sweeps)` after each sweep.
    pub fn run_until_with_progress(
        &mut self,
        tolerance: f64,
        max_sweeps: usize,
        progress: &mut dyn FnMut(usize, usize),
    ) -> RunReport {
        let mut report = RunReport::default();
        self.use_tolerance(tolerance);
        for sweep in 0..max_sweeps {
            let start = report;
            for i in 0..self.keyframes.len() {
                let dirty = self.dirty_tiles(i, tolerance);
                report.add(self.update_tiles(i, &dirty));
            }
            // Changes every keyframe has checked are not needed any more.
            self.trim_log();
            report.sweeps += 1;
            report.log_sweep(sweep + 1, &start);
            progress(sweep + 1, max_sweeps);
            if report.tiles == start.tiles {
                report.converged = true;
                break;
            }
        }
        self.changed.clear();
        report
    }

    /// Runs `iterations` sweeps of belief propagation, re-tracing every tile of each keyframe
    /// in a sweep. After keyframes were added, moved or removed, only the keyframes that share
    /// a brick with them or have stale tiles are swept: the others' voxels did not change,
    /// so their messages would come out the same. (Effects two or more overlaps away are left
    /// to later runs.) With no such edits pending it sweeps every keyframe, so repeated calls
    /// keep converging.
    pub fn run(&mut self, iterations: usize) -> RunReport {
        self.run_with_progress(iterations, &mut |_, _| {})
    }

    /// [`MrfEngine::run`], calling `progress(done, total)` after each keyframe update.
    pub fn run_with_progress(&mut self, iterations: usize, progress: &mut dyn FnMut(usize, usize)) -> RunReport {
        let active: Vec<usize> = if self.changed.is_empty() {
            (0..self.keyframes.len()).collect()
        } else {
            let changed = &self.changed;
            (0..self.keyframes.len())
                .filter(|&i| {
                    let kf = &self.keyframes[i];
                    kf.bricks.iter().any(|b| changed.contains(b)) || kf.tiles.iter().any(|t| t.stale)
                })
                .collect()
        };
        let total = iterations * active.len();
        let mut report = RunReport { sweeps: iterations, ..Default::default() };
        for round in 0..iterations {
            let start = report;
            for (n, &i) in active.iter().enumerate() {
                let all: Vec<usize> = (0..self.keyframes[i].tiles.len()).collect();
                report.add(self.update_tiles(i, &all));
                progress(round * active.len() + n + 1, total);
            }
            report.log_sweep(round + 1, &start);
        }
        self.changed.clear();
        self.last_run = active.len();
        report
    }

    /// Runs `iterations` sweeps over every keyframe, whatever changed.
    pub fn run_all(&mut self, iterations: usize) -> RunReport {
        self.changed.clear();
        self.run(iterations)
    }

    /// Keyframes the last [`MrfEngine::run`] updated in each iteration.
    pub fn last_run_keyframes(&self) -> usize {
        self.last_run
    }

    /// Adds `(voxel, change)` pairs, in runs by brick, to the sums (changes to voxels no longer
    /// allocated are dropped). A brick is stamped and logged when a marginal in it moved by
    /// more than `log_threshold` since it was last logged. A voxel that no log entry names
    /// has moved by at most two thresholds since the last check of any tile that reaches it,
    /// which found it within the tolerance: so changes that go unseen stay below 1.5
    /// tolerances.
    pub(super) fn apply(&mut self, deltas: &[(VoxelKey, f32)]) {
        for run in deltas.chunk_by(|a, b| a.0.brick() == b.0.brick()) {
            self.apply_run(run[0].0.brick(), run.iter().map(|(k, d)| (k.slot(), *d)));
        }
    }

    /// [`MrfEngine::apply`] of `(slot, change)` pairs of brick `bk`.
    pub(super) fn apply_run(&mut self, bk: BrickKey, run: impl Iterator<Item = (usize, f32)>) {
        let theta = self.log_threshold;
        // (The MRF's bricks are dense: every voxel is allocated when its brick is.)
        let sums = self.sums.brick_mut(bk).and_then(Brick::dense_mut);
        let (Some(sums), Some(logged)) = (sums, self.logged.brick_mut(bk).and_then(Brick::dense_mut)) else { return };
        let mut moved = false;
        for (slot, d) in run {
            let (s, l) = (&mut sums[slot], &mut logged[slot]);
            *s += d;
            // |d sigmoid| <= |dS| / 4: the exponentials only for changes that may matter.
            if (*s - *l).abs() as f64 > 4.0 * theta && (sigmoid(*s as f64) - sigmoid(*l as f64)).abs() > theta {
                *l = *s;
                moved = true;
            }
        }
        if moved {
            self.stamp(bk);
        }
    }

    /// Records that a sum in brick `b` changed in the current epoch. The log is bounded: past
    /// a few entries per brick it is dropped, and keyframes check all their tiles once.
    fn stamp(&mut self, b: BrickKey) {
        self.stamps.insert(b, self.epoch);
        if self.log.len() > 4 * self.brick_refs.len() + 4096 {
            self.log.clear();
            self.log_floor = self.epoch;
        }
        self.log.push((self.epoch, b));
    }

    /// The tiles of keyframe `i` that [`MrfEngine::run_until`] re-traces: stale ones, those
    /// whose last update damping held back by more than `tolerance`, and those a voxel of
    /// which moved by more than `tolerance` (marginal) since the tile saw it, or left the map.
    fn dirty_tiles(&mut self, i: usize, tolerance: f64) -> Vec<usize> {
        let recent = self.mark_suspects(i);
        let (kf, sums, stamps) = (&self.keyframes[i], &self.sums, &self.stamps);
        let dirty = (0..kf.tiles.len())
            .into_par_iter()
            .filter(|&t| {
                let tile = &kf.tiles[t];
                tile.stale
                    || tile.held_back as f64 > tolerance
                    || (tile.suspect
                        && largest_move(sums, stamps, tile, recent.as_ref(), tolerance, tolerance) > tolerance)
            })
            .collect();
        self.keyframes[i].tiles.iter_mut().for_each(|t| t.suspect = false);
        dirty
    }

    /// Logs changes finely enough for `tolerance`: if they were logged more coarsely, every
    /// tile is checked once.
    pub(super) fn use_tolerance(&mut self, tolerance: f64) {
        if tolerance / 4.0 < self.log_threshold {
            self.log_threshold = tolerance / 4.0;
            self.log.clear();
            self.log_floor = self.epoch + 1;
        }
    }

    /// Marks `suspect` the tiles of keyframe `i` that a brick logged since the keyframe's last
    /// check may reach, and records the check. Returns those bricks, or `None` when the log
    /// was dropped since (then every tile is suspect and the brick stamps tell what changed).
    pub(super) fn mark_suspects(&mut self, i: usize) -> Option<FxHashSet<BrickKey>> {
        let edge = self.brick_edge();
        let since = self.keyframes[i].checked_at;
        let kf = &mut self.keyframes[i];
        kf.checked_at = self.epoch;
        if since < self.log_floor {
            kf.tiles.iter_mut().for_each(|t| t.suspect = true);
            return None;
        }
        // The bricks logged since the keyframe's last check: a small table, where the stamps
        // of every brick are a large one.
        let start = self.log.partition_point(|&(e, _)| e <= since);
        let bricks: FxHashSet<BrickKey> = self.log[start..].iter().map(|x| x.1).collect();
        let to_camera = kf.to_camera();
        for &b in &bricks {
            kf.for_tiles_reaching(&to_camera, b, edge, |t, _| t.suspect = true);
        }
        Some(bricks)
    }

    /// Drops the log entries that every keyframe has checked.
    pub(super) fn trim_log(&mut self) {
        let checked = self.keyframes.iter().map(|k| k.checked_at).min().unwrap_or(self.epoch);
        let seen = self.log.partition_point(|&(e, _)| e <= checked);
        self.log.drain(..seen);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::Pose;
    use crate::inference::MrfParams;
    use crate::inference::mrf::tests::{moves_against_every_brick, test_frames};

    /// After change-driven inference has converged, checking every tile of every keyframe
    /// against every brick (not only those the change log projects onto it) finds no voxel
    /// moved by more than the 1.5 tolerances that `apply` guarantees: the log and the
    /// projection missed nothing, through adds, removals and re-poses.
    #[test]
    fn change_log_misses_no_dirty_tile() {
        let frames = test_frames(5);
        let tol = 1e-3;
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        let check = |e: &mut MrfEngine, what: &str| {
            let r = e.run_until(tol, 500);
            assert!(r.converged, "{what}: {r:?}");
            for (k, t, moved) in moves_against_every_brick(e) {
                assert!(moved <= 1.5 * tol, "{what}: keyframe {k} tile {t} left dirty ({moved})");
            }
        };
        for f in &frames[..4] {
            e.add_keyframe(f.clone()).unwrap();
        }
        check(&mut e, "build");
        let id = e.add_keyframe(frames[4].clone()).unwrap();
        check(&mut e, "add");
        e.remove_keyframe(e.keyframe_ids()[0]).unwrap();
        check(&mut e, "remove");
        let moved = Pose::new([0.0, 0.2, 0.0].into(), [0.0, 0.0, 0.1].into()) * frames[4].pose;
        e.set_pose(id, moved).unwrap();
        check(&mut e, "re-pose");
    }
}
