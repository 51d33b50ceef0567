//! The online schedule: belief propagation as anytime work under a budget.
//!
//! A robot cannot wait for loopy belief propagation to converge after each keyframe (at
//! 0.02 m it never quite does: surfaces drift between neighbouring voxels for hundreds of
//! sweeps, RESULTS.md), and the MRFMap paper never claims it does (its Fig. 10 runs a fixed
//! three passes per image). So online inference spends a budget, wall-clock milliseconds
//! and/or traced tiles, on the work that matters most, and keeps the rest for later:
//!
//! 1. **Own tiles first.** Tiles never traced (a new keyframe's, or a re-posed one's) are
//!    traced in full, whatever the budget: until they are, the map does not hold the frame.
//! 2. **Then the backlog, largest move first.** Every change to the sums is logged by brick
//!    ([`MrfEngine::apply_run`]); a *check* projects the bricks logged since a keyframe's last
//!    check into its image ([`MrfEngine::mark_suspects`]) and measures, for each tile they
//!    may reach, the largest marginal move of its voxels since it traced ([`largest_move`]).
//!    That move, at least the share a damped update held back and 1 for a stale tile, is the
//!    tile's priority. Tiles above the tolerance form the backlog; the largest are traced in
//!    batches (a batch's tiles grouped by keyframe, each group traced on all cores against the
//!    same sums, as [`MrfEngine::run_until`] does), the backlog checked again, and so on until
//!    the budget is spent or nothing is left above the tolerance ("settled").
//! 3. **Nothing is lost.** A priority only grows until the tile traces (a trace resets it),
//!    and every change is checked by every keyframe before the log drops it, so a change that
//!    is not traced waits in the backlog; [`MrfEngine::refine`] works it off when there is
//!    idle time, and the next keyframe's budget continues where this one stopped.
//!
//! The batch size follows the budget: with milliseconds, as many tiles as the remaining time
//! holds at the measured cost per tile; with tiles only, at most [`MAX_BATCH`], so that a
//! tile budget gives the same map on any machine and any number of threads.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use super::schedule::largest_move;
use super::tiles::Tile;
use super::{DEFAULT_TOLERANCE, KeyframeId, MrfEngine};
#[cfg(doc)]
use super::{Engine, MrfParams};
use crate::error::{Error, Result};
use crate::frames::Frame;

/// How much work one call of the online schedule may do (see the module docs). Both limits
/// may be set (the first reached stops it); neither means "until settled".
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Budget {
    /// Wall-clock milliseconds from the call's start (for [`MrfEngine::add_keyframe_within`],
    /// from the frame's arrival: its allocation and own tiles count).
    pub ms: Option<f64>,
    /// Tiles traced, a new keyframe's own tiles included.
    pub tiles: Option<usize>,
}

impl Budget {
    /// No limit: trace until nothing moves by more than the tolerance.
    pub const UNLIMITED: Budget = Budget { ms: None, tiles: None };

    /// At most `ms` milliseconds of wall time.
    pub fn ms(ms: f64) -> Budget {
        Budget { ms: Some(ms), tiles: None }
    }

    /// At most `tiles` traced tiles.
    pub fn tiles(tiles: usize) -> Budget {
        Budget { ms: None, tiles: Some(tiles) }
    }

    fn check(&self) -> Result<()> {
        match self.ms {
            Some(ms) if !(ms >= 0.0 && ms.is_finite()) => {
                Err(Error::Invalid(format!("MRF budget: milliseconds must be 0 or more, got {ms}")))
            }
            _ => Ok(()),
        }
    }
}

/// What one call of the online schedule did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StepReport {
    /// Tiles of new or re-posed keyframes, traced first (included in `tiles`).
    pub own_tiles: usize,
    /// Tiles traced in all.
    pub tiles: usize,
    /// Rays traced in all.
    pub rays: usize,
    /// Tiles waiting in the backlog afterwards, as the last check found them.
    pub backlog: usize,
    /// Nothing was left above the tolerance: the map is as converged as
    /// [`MrfEngine::run_until`] would leave it.
    pub settled: bool,
    /// Wall time of the call (for an add, from the frame's arrival).
    pub elapsed: Duration,
}

/// Most tiles traced between two checks of the backlog.
pub const MAX_BATCH: usize = 512;

/// A stale tile's priority: a brick it may reach came or went, so its messages may be missing
/// wholly somewhere, as large a move as a marginal can make.
const STALE_PRIORITY: f32 = 1.0;

/// Cost per tile assumed before one was measured (ms of wall time; about what a tile costs
/// at 0.02 m on two cores).
const FIRST_MS_PER_TILE: f64 = 0.5;

impl Tile {
    /// The tile's place in the backlog (see the module docs).
    fn backlog_priority(&self) -> f32 {
        if self.stale { STALE_PRIORITY } else { self.priority.max(self.held_back) }
    }
}

impl MrfEngine {
    /// Adds a keyframe and runs the online schedule within `budget`, timed from the frame's
    /// arrival: its own tiles are traced, then the backlog's largest moves (module docs). The
    /// map is readable and holds the frame when it returns.
    pub fn add_keyframe_within(&mut self, frame: Frame, budget: Budget) -> Result<(KeyframeId, StepReport)> {
        let start = Instant::now();
        budget.check()?;
        let id = self.add_keyframe(frame)?;
        Ok((id, self.refine_from(start, budget)))
    }

    /// Spends `budget` on the online schedule: tiles never traced (new or re-posed
    /// keyframes) first, then the backlog's largest moves. Call it after
    /// [`MrfEngine::remove_keyframe`] or [`MrfEngine::set_pose`], and whenever there is idle
    /// time; with [`Budget::UNLIMITED`] it runs until settled.
    pub fn refine(&mut self, budget: Budget) -> Result<StepReport> {
        budget.check()?;
        Ok(self.refine_from(Instant::now(), budget))
    }

    /// Tiles waiting in the backlog, as the last check of the online schedule found them
    /// (stale tiles and never-traced ones included); changes since then are counted by the
    /// next call.
    pub fn backlog(&self) -> usize {
        let tol = self.tolerance() as f32;
        self.keyframes.iter().flat_map(|k| &k.tiles).filter(|t| t.backlog_priority() > tol).count()
    }

    /// The tolerance below which a move is not followed.
    fn tolerance(&self) -> f64 {
        self.params.tolerance.unwrap_or(DEFAULT_TOLERANCE)
    }

    fn refine_from(&mut self, start: Instant, budget: Budget) -> StepReport {
        let tol = self.tolerance();
        self.use_tolerance(tol);
        let mut report = StepReport::default();
        let arrived_ms = start.elapsed().as_secs_f64() * 1e3;
        // 1. Tiles never traced, whatever the budget.
        for i in 0..self.keyframes.len() {
            let own: Vec<usize> =
                (0..self.keyframes[i].tiles.len()).filter(|&t| self.keyframes[i].tiles[t].traced_at == 0).collect();
            if !own.is_empty() {
                let t = Instant::now();
                let r = self.update_tiles(i, &own);
                self.learn_tile_cost(t.elapsed(), r.tiles);
                (report.own_tiles, report.tiles, report.rays) =
                    (report.own_tiles + r.tiles, report.tiles + r.tiles, report.rays + r.rays);
            }
        }
        // 2. The backlog, largest move first, in batches the budget holds. A check costs
        // time too: a batch leaves room for the one after it, and none starts without room
        // for a check and a tile.
        let own_ms = start.elapsed().as_secs_f64() * 1e3 - arrived_ms;
        let (mut check_ms, mut checks_ms, mut batches) = (0.0, 0.0, 0);
        // The budget's milliseconds left once a check of `check_ms` more is paid for.
        let left_ms = |check_ms: f64| budget.ms.map(|ms| ms - start.elapsed().as_secs_f64() * 1e3 - check_ms);
        loop {
            let tile_ms = self.tile_ms.unwrap_or(FIRST_MS_PER_TILE);
            if left_ms(check_ms).is_some_and(|left| left < tile_ms) || budget.tiles.is_some_and(|n| report.tiles >= n) {
                break;
            }
            let t = Instant::now();
            let mut candidates = self.check_backlog(tol);
            check_ms = t.elapsed().as_secs_f64() * 1e3;
            checks_ms += check_ms;
            if candidates.is_empty() {
                report.settled = true;
                break;
            }
            let mut batch = MAX_BATCH;
            if let Some(n) = budget.tiles {
                batch = batch.min(n - report.tiles);
            }
            if let Some(left) = left_ms(check_ms) {
                batch = batch.min((left / tile_ms).max(0.0) as usize);
            }
            if batch == 0 {
                break;
            }
            // The `batch` largest, ties to the older keyframe and the earlier tile (the same
            // choice on every machine), traced in keyframe and tile order.
            let order =
                |a: &(f32, u32, u32), b: &(f32, u32, u32)| b.0.total_cmp(&a.0).then((a.1, a.2).cmp(&(b.1, b.2)));
            if candidates.len() > batch {
                candidates.select_nth_unstable_by(batch - 1, order);
                candidates.truncate(batch);
            }
            candidates.sort_unstable_by_key(|&(_, k, t)| (k, t));
            let t = Instant::now();
            let mut traced = 0;
            for group in candidates.chunk_by(|a, b| a.1 == b.1) {
                let tiles: Vec<usize> = group.iter().map(|&(_, _, t)| t as usize).collect();
                let r = self.update_tiles(group[0].1 as usize, &tiles);
                (traced, report.rays) = (traced + r.tiles, report.rays + r.rays);
            }
            self.learn_tile_cost(t.elapsed(), traced);
            report.tiles += traced;
            batches += 1;
        }
        self.changed.clear();
        report.backlog = self.backlog();
        report.elapsed = start.elapsed();
        tracing::debug!(
            "online: {arrived_ms:.0} ms before tracing (allocation), {} own tiles in {own_ms:.0} ms, \
             {batches} batches of the backlog ({} tiles), checks {checks_ms:.0} ms; backlog {}",
            report.own_tiles,
            report.tiles - report.own_tiles,
            report.backlog
        );
        report
    }

    /// [`Engine::finish`] with [`MrfParams::work`] `w`: the online schedule with a budget of
    /// `w` times the keyframes' tiles, in chunks so that `progress(tiles traced, budget)` moves.
    pub(super) fn finish_by_work(&mut self, w: f64, progress: &mut dyn FnMut(usize, usize)) -> Result<()> {
        let total = (w * self.keyframes.iter().map(|k| k.tiles.len()).sum::<usize>() as f64).ceil() as usize;
        let (mut spent, mut last) = (0, StepReport::default());
        while spent < total && !last.settled {
            last = self.refine_from(Instant::now(), Budget::tiles((total - spent).min(8 * MAX_BATCH)));
            spent += last.tiles;
            progress(spent.min(total), total);
        }
        tracing::info!(
            "MRF: {spent} tiles traced over {} keyframes ({w} sweeps' worth at most), {} left in the backlog{} \
             ({} MiB of tile messages)",
            self.keyframes.len(),
            last.backlog,
            if last.settled { ", settled" } else { "" },
            self.tile_bytes() >> 20
        );
        Ok(())
    }

    /// Checks every keyframe's tiles against the changes logged since its last check and
    /// returns the backlog: `(priority, keyframe, tile)` of every tile above `tol`.
    fn check_backlog(&mut self, tol: f64) -> Vec<(f32, u32, u32)> {
        for i in 0..self.keyframes.len() {
            let recent = self.mark_suspects(i);
            let MrfEngine { keyframes, sums, stamps, .. } = self;
            keyframes[i].tiles.par_iter_mut().filter(|t| t.suspect).for_each(|tile| {
                let moved = largest_move(sums, stamps, tile, recent.as_ref(), tol, 1.0);
                tile.priority = tile.priority.max(moved as f32);
                tile.suspect = false;
            });
        }
        self.trim_log();
        let tol = tol as f32;
        let mut backlog = Vec::new();
        for (k, kf) in self.keyframes.iter().enumerate() {
            for (t, tile) in kf.tiles.iter().enumerate() {
                let p = tile.backlog_priority();
                if p > tol {
                    backlog.push((p, k as u32, t as u32));
                }
            }
        }
        backlog
    }

    /// Folds a measured trace (`tiles` in `took`) into the cost per tile that sizes batches.
    fn learn_tile_cost(&mut self, took: Duration, tiles: usize) {
        if tiles >= 8 {
            let ms = took.as_secs_f64() * 1e3 / tiles as f64;
            self.tile_ms = Some(self.tile_ms.map_or(ms, |old| 0.5 * old + 0.5 * ms));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{moves_against_every_brick, test_frames};
    use super::*;
    use crate::inference::MrfParams;

    /// After each call under a small tile budget, a tile outside the backlog has no voxel
    /// that moved by more than the 1.5 tolerances the change log guarantees, checking every
    /// brick (not only those the log projects onto it); and once the budget is lifted, the
    /// backlog empties and every tile is within that bound. Through adds, a removal and a
    /// re-pose.
    #[test]
    fn the_backlog_never_loses_a_change() {
        let frames = test_frames(5);
        let tol = 1e-3;
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        let check = |e: &mut MrfEngine, what: &str| {
            // What the next call's check would find, then every brick counted as changed.
            let backlog = e.check_backlog(tol).len();
            assert_eq!(backlog, e.backlog(), "{what}");
            let mut waiting = 0;
            for (k, t, moved) in moves_against_every_brick(e) {
                if e.keyframes[k].tiles[t].backlog_priority() as f64 > tol {
                    waiting += 1;
                } else {
                    assert!(moved <= 1.5 * tol, "{what}: keyframe {k} tile {t} moved {moved} outside the backlog");
                }
            }
            waiting
        };
        let budget = Budget::tiles(30);
        let mut waited = 0;
        for (n, f) in frames[..4].iter().enumerate() {
            let (_, r) = e.add_keyframe_within(f.clone(), budget).unwrap();
            assert!(r.tiles <= r.own_tiles.max(30), "{r:?}");
            waited += check(&mut e, &format!("add {n}"));
        }
        assert!(waited > 0, "the budget should leave work in the backlog");
        let id = e.keyframe_ids()[1];
        e.remove_keyframe(id).unwrap();
        e.refine(budget).unwrap();
        check(&mut e, "remove");
        let last = *e.keyframe_ids().last().unwrap();
        let moved = crate::frames::Pose::new([0.0, 0.2, 0.0].into(), [0.0, 0.0, 0.1].into()) * frames[3].pose;
        e.set_pose(last, moved).unwrap();
        let r = e.refine(budget).unwrap();
        assert!(r.own_tiles > 0, "the re-posed keyframe traces first: {r:?}");
        check(&mut e, "re-pose");
        let r = e.refine(Budget::UNLIMITED).unwrap();
        assert!(r.settled && r.backlog == 0, "{r:?}");
        assert_eq!(check(&mut e, "settled"), 0);
    }

    #[test]
    fn bad_budgets_are_refused() {
        let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
        for ms in [-1.0, f64::NAN, f64::INFINITY] {
            let err = e.refine(Budget::ms(ms)).unwrap_err();
            assert!(err.to_string().contains("budget"), "{err}");
        }
        assert_eq!(e.refine(Budget::ms(0.0)).unwrap().backlog, 0);
        assert!(e.refine(Budget::UNLIMITED).unwrap().settled);
    }
}
