//! Map operations and planner queries on maps built from a simulated scene: merge against
//! the map of all frames, crop / clear / diff / project against enumeration, and queries on
//! live engines against queries on their finished maps.

use mrfmap::frames::Frame;
use mrfmap::inference::{EngineConfig, EngineKind, LogOddsParams, merge, new_engine};
use mrfmap::map::Aabb;
use mrfmap::map::{Map, MapVoxel, VoxelState};
use mrfmap::outputs::{LiveEngine, QueryOptions, query_box, query_point, query_segment};
use mrfmap::random::Rng;

mod common;

fn frames() -> Vec<Frame> {
    common::box_on_floor_frames(3)
}

fn config(kind: EngineKind) -> EngineConfig {
    let mut c = EngineConfig::new(kind, 0.05);
    // Wide clamps: the log-odds sum is then exact for any split of the frames.
    c.logodds = LogOddsParams { clamp_min: 1e-6, clamp_max: 1.0 - 1e-6, ..LogOddsParams::default() };
    c
}

fn build(kind: EngineKind, frames: &[Frame]) -> Map {
    let mut e = new_engine(&config(kind)).unwrap();
    for f in frames {
        e.integrate(f).unwrap();
    }
    e.finish().unwrap();
    e.map()
}

#[test]
fn merging_log_odds_halves_gives_the_map_of_all_frames() {
    let f = frames();
    let all = build(EngineKind::LogOdds, &f);
    let merged = merge(&build(EngineKind::LogOdds, &f[..2]), &build(EngineKind::LogOdds, &f[2..])).unwrap();
    assert_eq!(merged.voxels.len(), all.voxels.len());
    for (k, v) in all.voxels.iter() {
        let m = merged.voxels.get(k).expect("same voxels");
        // f32 probabilities round-trip through log-odds: agree to float precision.
        assert!((m.occupancy - v.occupancy).abs() < 2e-5, "{k:?}: {} vs {}", m.occupancy, v.occupancy);
    }
    assert_eq!(merged.occupied_count(), all.occupied_count());
    // Different resolutions or engines are refused.
    let crm = build(EngineKind::Crm, &f[..1]);
    assert!(merge(&all, &crm).unwrap_err().to_string().contains("one engine and resolution"));
}

#[test]
fn merging_crm_and_mrf_keeps_what_each_half_saw() {
    let f = frames();
    for kind in [EngineKind::Crm, EngineKind::Mrf] {
        let (a, b) = (build(kind, &f[..2]), build(kind, &f[2..]));
        let merged = merge(&a, &b).unwrap();
        for (k, v) in merged.voxels.iter() {
            match (a.voxels.get(k), b.voxels.get(k)) {
                (Some(x), None) | (None, Some(x)) => assert_eq!(v, x),
                (Some(x), Some(y)) => {
                    // Agreeing evidence gets stronger: the merged belief is at least as far
                    // from the prior as the weaker of the two when both lean the same way.
                    let prior: f32 = merged.params.get("prior").map_or(0.5, |p| p.parse().unwrap());
                    let lean = |p: f32| p - prior;
                    if lean(x.occupancy) * lean(y.occupancy) > 0.0 {
                        let weaker = lean(x.occupancy).abs().min(lean(y.occupancy).abs());
                        assert!(lean(v.occupancy).abs() >= weaker - 1e-4, "{kind} {k:?}: {x:?} + {y:?} = {v:?}");
                    }
                    if kind == EngineKind::Crm {
                        // Beta parameters by moments; with every parameter at least 1 the
                        // product's are at least each factor's: more data, more concentration.
                        let beta = |v: &MapVoxel| {
                            let (m, var) = (v.occupancy as f64, v.variance as f64);
                            let n = m * (1.0 - m) / var - 1.0;
                            (m * n, (1.0 - m) * n)
                        };
                        let ((a1, b1), (a2, b2), (a, b)) = (beta(x), beta(y), beta(v));
                        if a1.min(b1).min(a2).min(b2) >= 1.0 {
                            assert!(a >= a1.max(a2) * 0.999 && b >= b1.max(b2) * 0.999, "{x:?} + {y:?} = {v:?}");
                        }
                    }
                }
                (None, None) => panic!("merged voxel {k:?} from nowhere"),
            }
        }
    }
}

#[test]
fn crop_clear_diff_and_project_agree_with_enumeration() {
    let f = frames();
    let map = build(EngineKind::LogOdds, &f);
    let region = Aabb::new([-0.5, -0.33, 0.1], [0.52, 0.4, 0.9]).unwrap();
    // Voxel i overlaps [min, max] when i r < max and (i + 1) r > min.
    let inside =
        |k: [i32; 3]| (0..3).all(|a| k[a] as f64 * 0.05 < region.max[a] && (k[a] + 1) as f64 * 0.05 > region.min[a]);
    let cropped = map.crop(&region);
    let expected: Vec<_> = map.voxels.iter().filter(|(k, _)| inside(k.0)).collect();
    assert!(!expected.is_empty());
    assert_eq!(cropped.voxels.len(), expected.len());
    for (k, v) in expected {
        assert_eq!(cropped.voxels.get(k), Some(v));
    }

    let mut cleared = map.clone();
    let n = cleared.clear(&region);
    assert_eq!(n, cropped.voxels.len());
    assert_eq!(cleared.voxels.len(), map.voxels.len() - n);
    let opts = QueryOptions::default();
    let a = query_box(&cleared, &region, &opts).unwrap();
    assert_eq!((a.occupied, a.free), (0, 0), "a cleared box is unknown");
    assert!(!query_point(&cleared, [0.0, 0.0, 0.5], &opts).known);

    // What changed from the cleared map back to the full one: exactly the cleared voxels,
    // from unknown to their state.
    let changes = cleared.diff(&map, 0.5).unwrap();
    assert_eq!(changes.len(), n);
    for c in &changes {
        assert!(inside(c.key.0) && c.before.is_none() && c.after.is_some());
        assert_ne!(VoxelState::of(c.after.as_ref(), 0.5), VoxelState::Unknown);
    }

    // Projection between two heights: each column's most occupied voxel.
    let grid = map.project(0.1, 0.6).unwrap();
    let r = map.resolution();
    let mut checked = 0;
    for j in 0..grid.height {
        for i in 0..grid.width {
            let x = grid.origin[0] + (i as f64 + 0.5) * r;
            let y = grid.origin[1] + (j as f64 + 0.5) * r;
            let column: Vec<f32> = (2..12) // voxels 2..=11 overlap z in (0.1, 0.6)
                .filter_map(|z| map.occupancy_at([x, y, (z as f64 + 0.5) * r]))
                .collect();
            let want = column.iter().copied().fold(None, |m: Option<f32>, p| Some(m.map_or(p, |m| m.max(p))));
            assert_eq!(grid.cell(i, j).map(|c| c.0), want, "column {i}, {j}");
            checked += want.is_some() as usize;
        }
    }
    assert!(checked > 100, "{checked} known columns");
}

#[test]
fn live_engines_answer_like_their_maps() {
    let f = frames();
    let opts = QueryOptions { unknown: 0.4, k: 1.0, ..Default::default() };
    let mut rng = Rng::new(1);
    let segs: Vec<_> =
        (0..500).map(|_| ([0; 3].map(|_| rng.range(-2.0, 2.0)), [0; 3].map(|_| rng.range(-2.0, 2.0)))).collect();
    for kind in EngineKind::ALL {
        let mut e = new_engine(&config(*kind)).unwrap();
        for fr in &f {
            e.integrate(fr).unwrap();
        }
        e.finish().unwrap();
        let map = e.map();
        let live = LiveEngine(e.as_ref());
        for (a, b) in &segs {
            assert_eq!(query_segment(&live, *a, *b, &opts), query_segment(&map, *a, *b, &opts), "{kind}");
            assert_eq!(query_point(&live, *a, &opts), query_point(&map, *a, &opts), "{kind}");
        }
        let region = Aabb::new([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]).unwrap();
        assert_eq!(query_box(&live, &region, &opts).unwrap(), query_box(&map, &region, &opts).unwrap());
    }
}

#[test]
fn pictures_and_grids_of_far_apart_voxels_are_refused_not_allocated() {
    use mrfmap::map::VoxelKey;
    let mut map = Map::new(EngineKind::LogOdds, 0.05).unwrap();
    for x in [0, 2_000_000] {
        map.voxels.insert(VoxelKey([x, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
        map.voxels.insert(VoxelKey([0, x, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
    }
    let e = mrfmap::outputs::slice_map(&map, 2, 0.01).unwrap_err().to_string();
    assert!(e.contains("crop the map"), "{e}");
    let e = map.project(0.0, 0.05).unwrap_err().to_string();
    assert!(e.contains("crop it first"), "{e}");
}
