//! Micro-benchmarks (divan): voxel traversal, one frame through each engine, one MRF
//! iteration over N keyframes, scoring one held-out view, and batched planner queries. The frames are the demo room
//! (`crates/mrfmap-cli/assets/demo_room.toml`, 640x480, D435-like noise) rendered in setup.
//!
//! Run: `cargo bench -p mrfmap --bench engines` (release). Results: BENCHMARKS.md.

use std::ops::ControlFlow;

use divan::{Bencher, black_box, counter::ItemsCount};
use mrfmap::frames::Frame;
use mrfmap::inference::{CrmEngine, CrmParams, Engine, LogOddsEngine, LogOddsParams, Marking, MrfEngine, MrfParams};
use mrfmap::map::{Map, MapVoxel, VoxelKey};
use mrfmap::outputs::{AccuracyParams, QueryOptions, Scorer, VoxelSource, query_points, query_segments};
use mrfmap::random::Rng;
use mrfmap::rays::for_each_crossing;
use mrfmap::source::Scene;

fn main() {
    divan::main();
}

fn room() -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../mrfmap-cli/assets/demo_room.toml");
    Scene::load(&path).expect("demo scene")
}

/// The first `n` views of the demo room, noisy.
fn frames(n: usize) -> Vec<Frame> {
    let scene = room();
    scene.views.iter().take(n).enumerate().map(|(i, pose)| scene.frame(i, pose, Some(1))).collect()
}

/// Voxels visited per second: 1000 random 5 m rays at 0.01 m (about 870 voxels each).
#[divan::bench(sample_count = 20)]
fn traversal(bencher: Bencher) {
    let mut rng = Rng::new(1);
    let rays: Vec<([f64; 3], [f64; 3])> = (0..1000)
        .map(|_| {
            let o = [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)];
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            (o, d.map(|x| x / n))
        })
        .collect();
    let mut total = 0u64;
    for (o, d) in &rays {
        for_each_crossing(*o, *d, 0.0, 5.0, 0.01, |_| {
            total += 1;
            ControlFlow::Continue(())
        });
    }
    bencher.counter(ItemsCount::new(total)).bench(|| {
        let mut n = 0u64;
        for (o, d) in &rays {
            for_each_crossing(*o, *d, 0.0, 5.0, 0.01, |c| {
                n += c.key.0[0] as u64 & 1;
                ControlFlow::Continue(())
            });
        }
        black_box(n)
    });
}

/// One 640x480 frame into a log-odds map holding one earlier frame (OctoMap semantics),
/// 0.02 m, finding the crossed voxels by walking every ray or by projection.
#[divan::bench(args = ["walk", "project"], sample_count = 10)]
fn logodds_frame(bencher: Bencher, marking: &str) {
    let fs = frames(2);
    let marking = <Marking as mrfmap::Choice>::parse(marking).unwrap();
    bencher
        .with_inputs(|| {
            let params = LogOddsParams { marking, ..Default::default() };
            let mut e = LogOddsEngine::new(0.02, Default::default(), params).unwrap();
            e.integrate(&fs[0]).unwrap();
            e
        })
        .bench_local_refs(|e| e.integrate(&fs[1]).unwrap());
}

/// One 640x480 frame into a CRM map holding one earlier frame, 0.02 m, by particle count.
#[divan::bench(args = [15, 101], sample_count = 5)]
fn crm_frame(bencher: Bencher, particles: usize) {
    let fs = frames(2);
    bencher
        .with_inputs(|| {
            let mut e = CrmEngine::new(0.02, Default::default(), CrmParams { particles }).unwrap();
            e.integrate(&fs[0]).unwrap();
            e
        })
        .bench_local_refs(|e| e.integrate(&fs[1]).unwrap());
}

/// One MRF iteration (every keyframe re-traced once) over N keyframes, 0.05 m.
#[divan::bench(args = [1, 4, 12], sample_count = 5)]
fn mrf_iteration(bencher: Bencher, keyframes: usize) {
    let fs = frames(keyframes);
    let mut e = MrfEngine::new(0.05, Default::default(), MrfParams::default()).unwrap();
    for f in &fs {
        e.add_keyframe(f.clone()).unwrap();
    }
    e.run(2);
    bencher.counter(ItemsCount::new(keyframes)).bench_local(|| e.run_all(1));
}

/// Scoring one 640x480 held-out view against a log-odds map of the other views, 0.02 m.
#[divan::bench(sample_count = 10)]
fn accuracy_view(bencher: Bencher) {
    let fs = frames(12);
    let mut e = LogOddsEngine::new(0.02, Default::default(), LogOddsParams::default()).unwrap();
    for f in &fs[1..] {
        e.integrate(f).unwrap();
    }
    let map = e.map();
    let params = AccuracyParams::for_map(&map);
    let scorer = Scorer::new(&map, params);
    let held = &fs[0];
    bencher.bench(|| black_box(scorer.score_view(&held.camera, &held.pose, &held.depth)));
}

/// A segment's two end points.
type Segment = ([f64; 3], [f64; 3]);

/// A log-odds map of 12 demo-room views at 0.05 m, and `n` random queries inside its bounds:
/// points, and 1 m segments in random directions.
fn query_setup(n: usize) -> (Map, Vec<[f64; 3]>, Vec<Segment>) {
    let mut e = LogOddsEngine::new(0.05, Default::default(), LogOddsParams::default()).unwrap();
    for f in &frames(12) {
        e.integrate(f).unwrap();
    }
    let map = e.map();
    let (lo, hi) = map.bounds().unwrap();
    let mut rng = Rng::new(5);
    let points: Vec<[f64; 3]> = (0..n).map(|_| [0, 1, 2].map(|a| rng.range(lo[a], hi[a]))).collect();
    let segments = points
        .iter()
        .map(|a| {
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            (*a, [0, 1, 2].map(|i| a[i] + d[i] / len))
        })
        .collect();
    (map, points, segments)
}

/// A map read voxel by voxel through its hash map, without the brick cache of
/// `Map`'s lookup: the baseline for the segment queries.
struct Uncached<'a>(&'a Map);

impl VoxelSource for Uncached<'_> {
    fn resolution(&self) -> f64 {
        self.0.resolution()
    }
    fn has_variance(&self) -> bool {
        self.0.has_variance
    }
    fn voxel(&self, key: VoxelKey) -> Option<MapVoxel> {
        self.0.voxels.get(key).copied()
    }
}

/// Batched point queries (occupancy, sigma, known), all threads.
#[divan::bench(sample_count = 10)]
fn query_points_batch(bencher: Bencher) {
    let (map, points, _) = query_setup(1_000_000);
    let opts = QueryOptions::default();
    bencher.counter(ItemsCount::new(points.len())).bench(|| black_box(query_points(&map, &points, &opts)));
}

/// Batched 1 m segment queries at 0.05 m (free probability, its bound, first hit), all
/// threads; `uncached` looks every voxel up in the hash map (the baseline).
#[divan::bench(args = ["brick-cached", "uncached"], sample_count = 10)]
fn query_segments_batch(bencher: Bencher, lookup: &str) {
    let (map, _, segments) = query_setup(200_000);
    let opts = QueryOptions::default();
    bencher.counter(ItemsCount::new(segments.len())).bench(|| {
        if lookup == "uncached" {
            black_box(query_segments(&Uncached(&map), &segments, &opts))
        } else {
            black_box(query_segments(&map, &segments, &opts))
        }
    });
}
