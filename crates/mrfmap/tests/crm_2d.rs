//! The CRM paper's qualitative claims on our 2D world (sec. 8): with the same noisy scans,
//! CRM's sigma predicts its error better than log-odds with the paper's best ramp ISM does,
//! and CRM ranks cells better (AUC). `mrfmap experiment crm-2d` reports the full table.

use mrfmap::inference::{CrmEngine, CrmParams, Engine, LogOddsEngine, LogOddsParams, SensorModel};
use mrfmap::map::Map;
use mrfmap::outputs::{TruthMetrics, grid_world_truths, metrics_of};
use mrfmap::random::Rng;
use mrfmap::source::GridWorld;

fn metrics(world: &GridWorld, map: &Map, prior_sigma: f64) -> TruthMetrics {
    metrics_of(&grid_world_truths(world, map, (0.5, prior_sigma)))
}

#[test]
fn crm_sigma_tracks_its_error_better_than_logodds() {
    let (world, waypoints) = GridWorld::crm_paper();
    for (seed, cells_of_noise) in [(1u64, 0.25), (2, 1.0), (3, 3.0)] {
        let mut rng = Rng::new(seed);
        let scans: Vec<_> = waypoints
            .iter()
            .enumerate()
            .map(|(i, p)| world.scan(i, *p, 60, 1.0, cells_of_noise * world.cell, &mut rng).unwrap())
            .collect();
        let mut crm = CrmEngine::new(world.cell, Default::default(), CrmParams::default()).unwrap();
        let params = LogOddsParams {
            model: SensorModel::CRM_PAPER,
            clamp_min: 1e-3,
            clamp_max: 1.0 - 1e-3,
            ..Default::default()
        };
        let mut lo = LogOddsEngine::new(world.cell, Default::default(), params).unwrap();
        for s in &scans {
            crm.integrate_scan(s).unwrap();
            lo.integrate_scan(s).unwrap();
        }
        let c = metrics(&world, &crm.map(), (102.0f64 / (12.0 * 100.0)).sqrt());
        let l = metrics(&world, &lo.map(), 0.5);
        println!("noise {cells_of_noise} cells: CRM {c:?}\n  log-odds {l:?}");
        assert!(c.pearson_sigma_error > l.pearson_sigma_error + 0.03, "PCC {c:?} vs {l:?}");
        assert!(c.auc > l.auc, "AUC {c:?} vs {l:?}");
        assert!(c.mae < l.mae, "MAE {c:?} vs {l:?}");
    }
}

/// The CRM issue's conflict test, literally: a one-cell pole seen by two range scans. When
/// the second scan's pose is off by one cell (misregistered), the pole's cell gets evidence
/// for and against and keeps a higher variance than when both scans agree.
#[test]
fn misaligned_scans_of_a_thin_pole_keep_variance_high() {
    let mut world = GridWorld::new(0.05, 40, 40).unwrap();
    world.fill(20, 20, 21, 21); // the pole: cell (20, 20)
    let pole = world.key(20, 20);
    let run = |shift: f64| {
        let mut crm = CrmEngine::new(world.cell, Default::default(), CrmParams::default()).unwrap();
        let mut rng = Rng::new(9);
        for round in 0..10 {
            for (i, p) in [[0.5, 1.025], [1.525, 0.5]].iter().enumerate() {
                let mut scan = world.scan(2 * round + i, *p, 720, 2.0, 0.01, &mut rng).unwrap();
                if i == 1 {
                    // The second sensor believes it is `shift` metres from where it is.
                    scan.pose.translation.vector.y += shift;
                }
                crm.integrate_scan(&scan).unwrap();
            }
        }
        crm.mean_variance(pole).unwrap()
    };
    let (consistent, misaligned) = (run(0.0), run(0.05));
    println!("pole mean/variance: consistent {consistent:?}, misaligned {misaligned:?}");
    assert!(consistent.0 > 0.8 && consistent.1 < 0.02, "{consistent:?}");
    assert!(misaligned.1 > 3.0 * consistent.1, "{consistent:?} vs {misaligned:?}");
}
