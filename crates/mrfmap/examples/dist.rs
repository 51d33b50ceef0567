use mrfmap::inference::{Engine, MrfEngine, MrfParams};
use mrfmap::rays::RayLimits;
use mrfmap::source::Dataset;
use std::collections::HashMap;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let ds = Dataset::open(std::path::Path::new(&a[1])).unwrap();
    let res: f64 = a[2].parse().unwrap();
    let sweeps: usize = a[3].parse().unwrap();
    let tol: f64 = a[4].parse().unwrap();
    let bounds = if a.len() > 5 { Some(mrfmap::rays::Aabb::parse(&a[5]).unwrap()) } else { None };
    let mut e = MrfEngine::new(res, RayLimits { max_range: None, bounds }, MrfParams::default()).unwrap();
    for i in 0..ds.len() {
        e.integrate(&ds.frame(i).unwrap()).unwrap();
    }
    let mut snaps: Vec<(usize, usize, HashMap<_, f64>)> = Vec::new();
    let mut tiles = 0;
    for s in 0..sweeps {
        let r = e.run_until(tol, 1);
        tiles += r.tiles;
        if [1, 2, 3, 4, 5, 6, 8, 10, 15, 20, 30, 40].contains(&(s + 1)) {
            snaps.push((s + 1, tiles, e.marginals().collect()));
        }
    }
    let mut fin: HashMap<_, f64> = e.marginals().collect();
    let refp = std::env::var("REF").unwrap_or_default();
    if std::env::var("SAVE").is_ok() {
        let mut out = String::new();
        for (k, m) in &fin {
            out += &format!("{} {} {} {}\n", k.0[0], k.0[1], k.0[2], m);
        }
        std::fs::write(&refp, out).unwrap();
    } else if !refp.is_empty() {
        fin.clear();
        for l in std::fs::read_to_string(&refp).unwrap().lines() {
            let v: Vec<&str> = l.split(' ').collect();
            fin.insert(
                mrfmap::map::VoxelKey([v[0].parse().unwrap(), v[1].parse().unwrap(), v[2].parse().unwrap()]),
                v[3].parse().unwrap(),
            );
        }
    }
    let lp = (0.1f64 / 0.9).ln();
    for (s, t, m) in &snaps {
        let (mut n, mut w02, mut w05, mut flip, mut maxd) = (0usize, 0usize, 0usize, 0usize, 0f64);
        for (k, f) in &fin {
            let f = *f;
            // only voxels with evidence (as the map would keep)
            let lf = (f / (1.0 - f)).ln();
            if (lf - lp).abs() < 1.0986 {
                continue;
            }
            let g = m.get(k).copied().unwrap_or(0.1);
            n += 1;
            let d = (g - f).abs();
            maxd = maxd.max(d);
            if d <= 0.02 {
                w02 += 1;
            }
            if d <= 0.05 {
                w05 += 1;
            }
            if (g > 0.5) != (f > 0.5) {
                flip += 1;
            }
        }
        println!(
            "sweep {s} tiles {t}: known {n} within0.02 {:.4} within0.05 {:.4} flips {flip} max {maxd:.3}",
            w02 as f64 / n as f64,
            w05 as f64 / n as f64
        );
    }
    println!("final sweeps {sweeps} tiles {tiles}");
}
