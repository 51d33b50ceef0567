//! Tests on the real datasets in `../shared/data/` (skipped with a message when absent,
//! as in a user's clone).

use std::path::PathBuf;

use mrfmap::inference::{Engine, LogOddsEngine, LogOddsParams, Marking};
use mrfmap::source::Dataset;

fn shared(name: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data").join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found (only present next to the project's own checkout)", p.display());
        None
    }
}

#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn icl_livingroom_loads_with_negative_fy() {
    let Some(root) = shared("icl-livingroom-5") else {
        return;
    };
    let ds = Dataset::open(&root).unwrap();
    assert_eq!(ds.len(), 5);
    assert!(ds.camera().fy < 0.0);
    assert!(ds.noise().is_none());
    let f = ds.frame(0).unwrap();
    assert_eq!((f.depth.width(), f.depth.height()), (640, 480));
    assert!(f.depth.valid_count() > 200_000);
    assert!(ds.truth_depth(0).unwrap().is_none());
}

#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn coffin_world_loads_with_patch_noise_and_truth() {
    let Some(root) = shared("coffin-world") else {
        return;
    };
    let ds = Dataset::open(&root).unwrap();
    assert_eq!(ds.len(), 12);
    let noise = ds.noise().expect("coffin-world has noise.toml");
    assert_eq!(noise.patches.as_ref().map(|p| (p.rows, p.cols, p.size)), Some((24, 32, 20)));
    let truth = ds.truth_depth(3).unwrap().expect("gt_depth present");
    let noisy = ds.frame(3).unwrap().depth;
    // The noisy image is the truth plus the model's noise: normalised residuals
    // (noisy - truth - bias) / std have mean ~0 and spread ~1 (checks that we read the
    // per-patch polynomials and their pixel layout the way the data was generated).
    let (mut n, mut sum, mut sum2) = (0usize, 0.0, 0.0);
    for v in 0..480 {
        for u in 0..640 {
            if let (Some(t), Some(m)) = (truth.get(u, v), noisy.get(u, v)) {
                let (bias, std) = noise.bias_std(u, v, t as f64);
                let r = (m as f64 - t as f64 - bias) / std;
                n += 1;
                sum += r;
                sum2 += r * r;
            }
        }
    }
    let mean = sum / n as f64;
    let sd = (sum2 / n as f64 - mean * mean).sqrt();
    eprintln!("coffin-world view 3: {n} pixels, normalised residual mean {mean:.3}, std {sd:.3}");
    assert!(n > 100_000 && mean.abs() < 0.1 && (sd - 1.0).abs() < 0.15, "n {n}, mean {mean}, std {sd}");
}

/// OctoMap 1.9.7 on these five frames, no max range: 15,444 occupied voxels at 0.05 m and
/// 104,758 at 0.02 m. Our log-odds engine must agree within 3%, and finding the crossed voxels
/// by projection must give the same map as walking every ray.
#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn logodds_matches_octomap_occupied_counts() {
    let Some(root) = shared("icl-livingroom-5") else {
        return;
    };
    let ds = Dataset::open(&root).unwrap();
    let frames: Vec<_> = (0..ds.len()).map(|i| ds.frame(i).unwrap()).collect();
    for (resolution, octomap) in [(0.05, 15_444.0), (0.02, 104_758.0)] {
        let build = |marking| {
            let params = LogOddsParams { marking, ..Default::default() };
            let mut e = LogOddsEngine::new(resolution, Default::default(), params).unwrap();
            for f in &frames {
                e.integrate(f).unwrap();
            }
            e
        };
        let (walk, project) = (build(Marking::Walk), build(Marking::Project));
        let occupied = project.map().occupied_count() as f64;
        let rel = (occupied - octomap) / octomap;
        eprintln!("resolution {resolution}: {occupied} occupied, OctoMap {octomap}, {:+.2}%", rel * 100.0);
        assert!(rel.abs() < 0.03, "resolution {resolution}: {occupied} vs OctoMap {octomap} ({:+.2}%)", rel * 100.0);
        let (a, b) = (walk.log_odds(), project.log_odds());
        let differ = a.iter().filter(|(k, l)| b.get(*k) != Some(*l)).count()
            + b.iter().filter(|(k, _)| a.get(*k).is_none()).count();
        eprintln!("resolution {resolution}: {differ} of {} voxels differ between walking and projecting", a.len());
        assert!(differ * 100_000 <= a.len(), "{differ} of {} voxels differ", a.len());
    }
}

/// OctoMap 1.9.7 with `maxrange` 6 m on coffin-world (depths up to 6.5 m) at 0.05 m: 138,210
/// occupied voxels (`bench/octomap_driver DATASET 0.05 1 - 6`). A ray cut at the max range
/// marks its voxels free up to, not including, the cut point's voxel; when that voxel was
/// marked as well, 334 fewer voxels (0.24%) stayed occupied.
#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn logodds_cuts_at_the_max_range_as_octomap_does() {
    let Some(root) = shared("coffin-world") else {
        return;
    };
    let ds = Dataset::open(&root).unwrap();
    let limits = mrfmap::rays::RayLimits { max_range: Some(6.0), bounds: None };
    let mut e = LogOddsEngine::new(0.05, limits, LogOddsParams::default()).unwrap();
    for i in 0..ds.len() {
        e.integrate(&ds.frame(i).unwrap()).unwrap();
    }
    let occupied = e.map().occupied_count() as i64;
    eprintln!("coffin-world 0.05 m, max range 6 m: {occupied} occupied, OctoMap 138210");
    assert!((occupied - 138_210).abs() <= 14, "{occupied} occupied, OctoMap 138210");
}

#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn intel_lab_log_reads_and_maps_the_lab() {
    use mrfmap::inference::CrmEngine;
    use mrfmap::source::{CarmenLog, CarmenOptions, Misses};
    let Some(root) = shared("intel-lab") else {
        return;
    };
    let log = CarmenLog::open(&root.join("intel-corrected.log.gz"), CarmenOptions::default()).unwrap();
    assert_eq!(log.readings.len(), 910);
    assert!(log.readings.iter().all(|r| r.message == "FLASER" && r.ranges.len() == 180));
    let mut crm = CrmEngine::new(0.1, Default::default(), Default::default()).unwrap();
    let mut lo = LogOddsEngine::new(0.1, Default::default(), LogOddsParams::default()).unwrap();
    for (i, r) in log.readings.iter().enumerate() {
        let scan = r.to_scan(i, 0.05, 1, Misses::Ignore, None).unwrap();
        crm.integrate_scan(&scan).unwrap();
        lo.integrate_scan(&scan).unwrap();
    }
    // The lab is about 30 m x 30 m; without misses nothing reaches much beyond it.
    for map in [crm.map(), lo.map()] {
        let (min, max) = map.bounds().unwrap();
        assert!((max[0] - min[0]) < 60.0 && (max[1] - min[1]) < 60.0, "{min:?} {max:?}");
        assert_eq!((min[2], max[2]), (0.0, 0.1), "one layer");
        // Walls are a small share of the known cells, as in any floor plan.
        let share = map.occupied_count() as f64 / map.voxels.len() as f64;
        assert!(share > 0.02 && share < 0.2, "{} occupied share {share}", map.engine);
    }
}

/// `add-noise --model kinect` against the published noisy depth of Augmented ICL-NUIM
/// livingroom1 (frames 0-4, `noisy_sample/`): the simulated noise has the published frames'
/// statistics within 30% (issue #33's check) for ten sensor seeds. MAD, 95th percentile of |e|,
/// lost pixels and depth levels hold per frame and seed. The median (about 2 mm) is set mostly by
/// the sensor's fixed distortion field, one draw of which the published frames are: per seed it
/// spans 1.7-2.8 mm, so it is checked on the ten seeds' average. The model's parameters were read
/// off these same frames (docs/ALGORITHMS.md 3.1): this is an in-sample check.
#[test]
#[cfg_attr(not(shared_data), ignore = "needs ../shared/data, absent in a plain clone")]
fn kinect_noise_has_the_published_icl_statistics() {
    use mrfmap::source::{StructuredLight, noise_statistics, quantise_depth, read_depth_png};
    let Some(root) = shared("icl-livingroom1") else {
        return;
    };
    let ds = Dataset::open(&root).unwrap();
    let camera = *ds.camera();
    let sensor = StructuredLight::kinect();
    let within = |what: &str, sim: f64, publ: f64| {
        assert!((sim - publ).abs() <= 0.3 * publ.abs(), "{what}: simulated {sim} vs published {publ}");
    };
    let (mut published_median, mut simulated_median, mut n) = (0.0, 0.0, 0.0);
    for i in 0..5 {
        let clean = ds.frame(i).unwrap().depth;
        let published =
            read_depth_png(&root.join(format!("noisy_sample/{i:06}.png")), camera.depth_scale, None).unwrap();
        let p = noise_statistics(&published, &clean, camera.depth_scale).unwrap();
        for seed in 0..10 {
            // Through the 16-bit millimetre encoding, as a written dataset stores it.
            let simulated = quantise_depth(&sensor.apply(&clean, &camera, seed, i as u64), camera.depth_scale);
            let s = noise_statistics(&simulated, &clean, camera.depth_scale).unwrap();
            let at = format!("frame {i} seed {seed}");
            within(&format!("{at} MAD"), s.mad, p.mad);
            within(&format!("{at} p95 |e|"), s.p95_abs, p.p95_abs);
            within(&format!("{at} lost share"), s.lost, p.lost);
            within(&format!("{at} levels"), s.levels as f64, p.levels as f64);
            published_median += p.median;
            simulated_median += s.median;
            n += 1.0;
        }
    }
    within("median over seeds and frames", simulated_median / n, published_median / n);
}
