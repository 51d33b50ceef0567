//! Ground-truth map metrics (docs/ALGORITHMS.md 6.2, CRM sec. 8) for maps of analytic scenes.
//!
//! Per allocated voxel: the true occupancy (the fraction of a 4x4x4 lattice of points in
//! the voxel that lie inside the scene's solids, so partly covered voxels are partly
//! occupied), the map's mean `m` and standard deviation `sigma` (the engine's variance
//! where it has one, else `sqrt(m (1 - m))`), and the error `e = truth - m`. Reported:
//! mean absolute error, ROC AUC of `m` as a classifier of `truth >= 0.5`, the inconsistency
//! `I_c = sum max(0, |e| - gamma sigma)` for gamma 0.5 and 2 (as sums, and per voxel), and
//! the Pearson correlation of `sigma` with `|e|`; and, for a planner that thresholds at 1/2,
//! the precision and recall of the occupied voxels (`m > 0.5`) against `truth >= 0.5`.
//!
//! Scenes with no analytic model but noise-free depth (rendered datasets) get a reference from
//! that depth alone, [`surface_truth`].

use crate::frames::Frame;
use crate::map::{Grid, Map, MapVoxel, VoxelKey};
use crate::rays::{Projector, RayLimits};
use crate::source::{GridWorld, Scene};

/// Lattice points per axis used for a voxel's true occupancy.
const SAMPLES: usize = 4;

/// The metrics of one map against its scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthMetrics {
    /// Allocated voxels compared.
    pub voxels: usize,
    /// Mean absolute error of the occupancy.
    pub mae: f64,
    /// ROC AUC of the occupancy against `truth >= 0.5` (`NaN` when one class is missing).
    pub auc: f64,
    /// `I_c` with gamma 0.5, summed over voxels.
    pub ic_half: f64,
    /// `I_c` with gamma 2, summed over voxels.
    pub ic_two: f64,
    /// Pearson correlation of sigma with |error| (`NaN` when either is constant).
    pub pearson_sigma_error: f64,
    /// Share of the voxels with mean above 1/2 whose truth is at least 1/2 (`NaN` if none).
    pub precision: f64,
    /// Share of the voxels with truth at least 1/2 whose mean is above 1/2 (`NaN` if none).
    /// Over the compared voxels only: a voxel the map leaves out is not counted.
    pub recall: f64,
}

/// Per-voxel quantities behind [`TruthMetrics`] (also what the slice pictures show).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelTruth {
    /// True occupied fraction.
    pub truth: f64,
    /// Map mean.
    pub mean: f64,
    /// Map standard deviation.
    pub sigma: f64,
}

impl VoxelTruth {
    /// `truth - mean`.
    pub fn error(&self) -> f64 {
        self.truth - self.mean
    }

    /// `max(0, |e| - gamma sigma)`.
    pub fn inconsistency(&self, gamma: f64) -> f64 {
        (self.error().abs() - gamma * self.sigma).max(0.0)
    }
}

/// Occupied fraction of voxel `key` (size `r`) in `scene`.
pub fn true_occupancy(scene: &Scene, key: VoxelKey, r: f64) -> f64 {
    let lo = key.0.map(|i| i as f64 * r);
    let step = r / SAMPLES as f64;
    let mut inside = 0;
    for i in 0..SAMPLES * SAMPLES * SAMPLES {
        let idx = [i % SAMPLES, (i / SAMPLES) % SAMPLES, i / (SAMPLES * SAMPLES)];
        let p = [0, 1, 2].map(|a| lo[a] + (idx[a] as f64 + 0.5) * step);
        inside += scene.contains(p) as usize;
    }
    inside as f64 / (SAMPLES * SAMPLES * SAMPLES) as f64
}

/// A reference occupancy grid from noise-free depth alone, with no inverse sensor model: a
/// voxel is occupied (1) where a depth point of some frame falls in it, free (0) where some
/// frame's ray crosses it and no depth point of any frame falls in it; voxels no ray reaches
/// are left out. Rays are OctoMap's segments within `limits` (as the log-odds engine casts
/// them). Unlike a log-odds map of the same frames, a surface stays occupied however many
/// rays graze it, and the reference does not favour log-odds for being log-odds: what the
/// CRM paper's ICL-NUIM ground truth, from the scene's surface model, stands for where the
/// frames see.
///
/// ```
/// use mrfmap::frames::{Camera, DepthImage, Frame, look_at};
/// use mrfmap::outputs::surface_truth;
/// use mrfmap::rays::RayLimits;
/// use nalgebra::Vector3;
/// let camera = Camera::new(50.0, 50.0, 15.5, 15.5, 32, 32, 1000.0).unwrap();
/// let mut depth = DepthImage::new(32, 32);
/// for v in 0..32 { for u in 0..32 { depth.set(u, v, 1.0); } }
/// let pose = look_at(Vector3::new(0.01, 0.01, 0.01), Vector3::new(1.0, 0.01, 0.01)).unwrap();
/// let frame = Frame { index: 0, timestamp: 0.0, depth, pose, camera, noise: None };
/// let truth = surface_truth([Ok(frame.clone())], 0.05, &RayLimits::default()).unwrap();
/// // The wall 1 m ahead is at x = 1.01, voxel column 20: occupied there, free in front.
/// let at = |t: &mrfmap::map::Grid<mrfmap::map::MapVoxel>, x: i32| t.get(mrfmap::map::VoxelKey([x, 0, 0])).map(|v| v.occupancy);
/// assert_eq!((at(&truth, 20), at(&truth, 10), at(&truth, 21)), (Some(1.0), Some(0.0), None));
/// // A second frame sees through where the first saw the wall, to 2 m: the wall's voxel
/// // stays occupied (a log-odds map of the two would call it free or undecided).
/// let mut far = frame.clone();
/// for v in 0..32 { for u in 0..32 { far.depth.set(u, v, 2.0); } }
/// let truth = surface_truth([Ok(frame), Ok(far)], 0.05, &RayLimits::default()).unwrap();
/// assert_eq!((at(&truth, 20), at(&truth, 30), at(&truth, 40)), (Some(1.0), Some(0.0), Some(1.0)));
/// ```
pub fn surface_truth(
    frames: impl IntoIterator<Item = crate::Result<Frame>>,
    resolution: f64,
    limits: &RayLimits,
) -> crate::Result<Grid<MapVoxel>> {
    let (free, occupied) = (MapVoxel { occupancy: 0.0, variance: 0.0 }, MapVoxel { occupancy: 1.0, variance: 0.0 });
    let mut truth = Grid::new(resolution)?;
    let mut projector = Projector::default();
    for frame in frames {
        let seen = projector.crossed_voxels(&frame?, limits, resolution, None, None);
        // Crossed voxels enter free (an occupied one stays so); then this frame's surfaces.
        for (brick, mask) in &seen.crossed {
            truth.brick_or_insert(*brick).update_slots(mask, free, |_| {});
        }
        for (brick, hit) in &seen.ends {
            truth.brick_or_insert(*brick).update_slots(hit, occupied, |v| *v = occupied);
        }
    }
    Ok(truth)
}

/// Mean and standard deviation the metrics use for a map voxel.
pub fn mean_sigma(map: &Map, v: &MapVoxel) -> (f64, f64) {
    v.mean_sigma(map.has_variance)
}

/// Per-voxel truth, mean and sigma for every allocated voxel of `map` (in parallel).
pub fn voxel_truths(map: &Map, scene: &Scene) -> Vec<(VoxelKey, VoxelTruth)> {
    use rayon::prelude::*;
    let r = map.resolution();
    let voxels: Vec<(VoxelKey, &MapVoxel)> = map.voxels.iter().collect();
    voxels
        .into_par_iter()
        .map(|(k, v)| {
            let (mean, sigma) = mean_sigma(map, v);
            (k, VoxelTruth { truth: true_occupancy(scene, k, r), mean, sigma })
        })
        .collect()
}

/// Truth, mean and sigma of every cell of a planar world (row-major from the bottom row), for
/// a map built in its voxel layer. Cells the map does not have take `prior` (mean, sigma):
/// in a 2D study unobserved cells count, at what the engine would say about them.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::map::{Map, MapVoxel};
/// use mrfmap::source::GridWorld;
/// let mut world = GridWorld::new(0.1, 2, 1).unwrap();
/// world.fill(1, 0, 2, 1);
/// let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
/// map.voxels.insert(world.key(1, 0), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// let cells = mrfmap::outputs::grid_world_truths(&world, &map, (0.5, 0.5));
/// assert_eq!((cells[0].truth, cells[0].mean), (0.0, 0.5));
/// assert_eq!(cells[1].truth, 1.0);
/// ```
pub fn grid_world_truths(world: &GridWorld, map: &Map, prior: (f64, f64)) -> Vec<VoxelTruth> {
    let mut out = Vec::with_capacity(world.width * world.height);
    for y in 0..world.height {
        for x in 0..world.width {
            let truth = if world.is_occupied(x as i64, y as i64) { 1.0 } else { 0.0 };
            let (mean, sigma) = map.voxels.get(world.key(x, y)).map_or(prior, |v| mean_sigma(map, v));
            out.push(VoxelTruth { truth, mean, sigma });
        }
    }
    out
}

/// All metrics of `map` against `scene`, over the map's allocated voxels.
pub fn truth_metrics(map: &Map, scene: &Scene) -> TruthMetrics {
    let vt: Vec<VoxelTruth> = voxel_truths(map, scene).into_iter().map(|(_, t)| t).collect();
    metrics_of(&vt)
}

/// The metrics of any set of voxels (for example every cell of a 2D world, observed or not).
///
/// ```
/// use mrfmap::outputs::{VoxelTruth, metrics_of};
/// let v = |truth, mean, sigma| VoxelTruth { truth, mean, sigma };
/// let m = metrics_of(&[v(1.0, 0.9, 0.1), v(0.0, 0.2, 0.3), v(0.0, 0.5, 0.5)]);
/// assert!((m.mae - (0.1 + 0.2 + 0.5) / 3.0).abs() < 1e-12);
/// assert_eq!(m.auc, 1.0);
/// assert_eq!((m.precision, m.recall), (1.0, 1.0)); // 0.5 is not above 1/2
/// ```
pub fn metrics_of(vt: &[VoxelTruth]) -> TruthMetrics {
    let n = vt.len();
    let mae = vt.iter().map(|t| t.error().abs()).sum::<f64>() / n.max(1) as f64;
    let scores: Vec<f64> = vt.iter().map(|t| t.mean).collect();
    let labels: Vec<bool> = vt.iter().map(|t| t.truth >= 0.5).collect();
    let sigmas: Vec<f64> = vt.iter().map(|t| t.sigma).collect();
    let errors: Vec<f64> = vt.iter().map(|t| t.error().abs()).collect();
    let count = |f: &dyn Fn(&VoxelTruth) -> bool| vt.iter().filter(|t| f(t)).count() as f64;
    let hits = count(&|t| t.mean > 0.5 && t.truth >= 0.5);
    TruthMetrics {
        voxels: n,
        mae: if n == 0 { f64::NAN } else { mae },
        auc: roc_auc(&scores, &labels),
        ic_half: vt.iter().map(|t| t.inconsistency(0.5)).sum(),
        ic_two: vt.iter().map(|t| t.inconsistency(2.0)).sum(),
        pearson_sigma_error: pearson(&sigmas, &errors),
        precision: hits / count(&|t| t.mean > 0.5),
        recall: hits / count(&|t| t.truth >= 0.5),
    }
}

/// Area under the ROC curve of `scores` for binary `labels`, by the Mann-Whitney statistic
/// with tied scores given their average rank (a tie counts half). `NaN` if a class is empty.
///
/// ```
/// let auc = mrfmap::outputs::roc_auc(&[0.1, 0.4, 0.35, 0.8], &[false, false, true, true]);
/// assert!((auc - 0.75).abs() < 1e-12);
/// ```
pub fn roc_auc(scores: &[f64], labels: &[bool]) -> f64 {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    let (mut rank_sum_pos, mut n_pos) = (0.0, 0usize);
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && scores[order[j + 1]] == scores[order[i]] {
            j += 1;
        }
        let avg_rank = (i + j) as f64 / 2.0 + 1.0; // ranks are 1-based
        for &k in &order[i..=j] {
            if labels[k] {
                rank_sum_pos += avg_rank;
                n_pos += 1;
            }
        }
        i = j + 1;
    }
    let n_neg = scores.len() - n_pos;
    if n_pos == 0 || n_neg == 0 {
        return f64::NAN;
    }
    (rank_sum_pos - (n_pos * (n_pos + 1)) as f64 / 2.0) / (n_pos * n_neg) as f64
}

/// Pearson correlation coefficient; `NaN` when either input is constant or empty.
///
/// ```
/// let r = mrfmap::outputs::pearson(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.5]);
/// assert!(r > 0.99 && r <= 1.0);
/// ```
pub fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().min(y.len()) as f64;
    let mx = x.iter().sum::<f64>() / n;
    let my = y.iter().sum::<f64>() / n;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx) * (a - mx);
        syy += (b - my) * (b - my);
    }
    if sxx == 0.0 || syy == 0.0 { f64::NAN } else { sxy / (sxx * syy).sqrt() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::EngineKind;
    use crate::random::Rng;

    /// AUC by its definition: P(score_pos > score_neg) + 0.5 P(equal), over all pairs.
    fn auc_pairs(scores: &[f64], labels: &[bool]) -> f64 {
        let (mut sum, mut n) = (0.0, 0);
        for i in 0..scores.len() {
            for j in 0..scores.len() {
                if labels[i] && !labels[j] {
                    n += 1;
                    sum += if scores[i] > scores[j] {
                        1.0
                    } else if scores[i] == scores[j] {
                        0.5
                    } else {
                        0.0
                    };
                }
            }
        }
        sum / n as f64
    }

    #[test]
    fn precision_and_recall_of_the_occupied_voxels() {
        let v = |truth, mean| VoxelTruth { truth, mean, sigma: 0.1 };
        // Occupied (> 0.5): a true hit, a false one and a 0.75-solid voxel; 0.5 itself is not
        // occupied, and a 0.25-solid voxel is free in truth.
        let m = metrics_of(&[v(1.0, 0.9), v(0.0, 0.6), v(0.75, 0.7), v(1.0, 0.5), v(0.25, 0.8), v(0.0, 0.1)]);
        assert_eq!(m.precision, 2.0 / 4.0);
        assert_eq!(m.recall, 2.0 / 3.0);
        let none = metrics_of(&[v(0.0, 0.2)]);
        assert!(none.precision.is_nan() && none.recall.is_nan());
    }

    #[test]
    fn auc_matches_pairwise_definition_with_ties() {
        let mut rng = Rng::new(4);
        for _ in 0..50 {
            let n = 2 + (rng.next_u64() % 40) as usize;
            // Scores on a coarse grid so that ties are common.
            let scores: Vec<f64> = (0..n).map(|_| (rng.next_u64() % 5) as f64 / 4.0).collect();
            let labels: Vec<bool> = (0..n).map(|_| rng.uniform() < 0.5).collect();
            let expected = auc_pairs(&scores, &labels);
            let got = roc_auc(&scores, &labels);
            if expected.is_nan() {
                assert!(got.is_nan());
            } else {
                assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
            }
        }
        assert!(roc_auc(&[0.1, 0.2], &[true, true]).is_nan());
    }

    #[test]
    fn pearson_against_direct_formula() {
        let x = [1.0, 2.0, 4.0, 7.0];
        let y = [0.5, 0.1, 0.9, 0.3];
        // Direct: cov / (sd_x sd_y) with population moments.
        let mx = 3.5;
        let my = 0.45;
        let cov: f64 = x.iter().zip(&y).map(|(a, b)| (a - mx) * (b - my)).sum::<f64>() / 4.0;
        let sx = (x.iter().map(|a| (a - mx).powi(2)).sum::<f64>() / 4.0).sqrt();
        let sy = (y.iter().map(|b| (b - my).powi(2)).sum::<f64>() / 4.0).sqrt();
        assert!((pearson(&x, &y) - cov / (sx * sy)).abs() < 1e-12);
        assert!(pearson(&[1.0, 1.0], &[0.0, 2.0]).is_nan());
    }

    #[test]
    fn metrics_of_a_perfect_and_a_wrong_map() {
        let text = "[camera]\nfx = 10.0\nfy = 10.0\ncx = 1.5\ncy = 1.5\nwidth = 4\nheight = 4\ndepth_scale = 1000.0\n\
                    [[box]]\nmin = [0.0, 0.0, 0.0]\nmax = [0.2, 0.2, 0.2]\n[[view]]\neye = [1.0, 0.1, 0.1]\ntarget = [0.0, 0.1, 0.1]\n";
        let scene = Scene::from_toml(text, std::path::Path::new("t.toml")).unwrap();
        let mut perfect = Map::new(EngineKind::Mrf, 0.1).unwrap();
        let mut wrong = Map::new(EngineKind::Mrf, 0.1).unwrap();
        for x in -1..3 {
            let key = VoxelKey([x, 0, 0]);
            let truth = true_occupancy(&scene, key, 0.1);
            assert_eq!(truth, if (0..2).contains(&x) { 1.0 } else { 0.0 });
            perfect.voxels.insert(key, MapVoxel { occupancy: truth as f32, variance: 0.0 });
            wrong.voxels.insert(key, MapVoxel { occupancy: 0.5, variance: 0.0 });
        }
        let m = truth_metrics(&perfect, &scene);
        assert_eq!((m.voxels, m.mae, m.auc, m.ic_half), (4, 0.0, 1.0, 0.0));
        let w = truth_metrics(&wrong, &scene);
        assert_eq!((w.mae, w.auc), (0.5, 0.5));
        // sigma = 0.5 for m = 0.5: |e| - 0.5 sigma = 0.25 per voxel; gamma 2 forgives it.
        assert!((w.ic_half - 1.0).abs() < 1e-12 && w.ic_two == 0.0);
    }
}
