//! What every engine promises, checked for all three on one small simulated scene: the map
//! does not depend on the number of threads; an empty frame and NaN depths are no readings;
//! frames that see nothing inside the bounds leave the map empty; a map survives its file,
//! and an engine saved straight to a file writes the file its map would.

use mrfmap::frames::{DepthImage, Frame};
use mrfmap::inference::{EngineConfig, EngineKind, new_engine};
use mrfmap::map::{Aabb, Map};

mod common;

/// The box on the floor from three sides.
fn frames() -> Vec<Frame> {
    common::box_on_floor_frames(7)[..3].to_vec()
}

fn build(config: &EngineConfig, frames: &[Frame]) -> Map {
    let mut engine = new_engine(config).unwrap();
    for f in frames {
        engine.integrate(f).unwrap();
    }
    engine.finish().unwrap();
    engine.map()
}

/// Every voxel with its occupancy and variance, bit for bit.
fn voxels(map: &Map) -> Vec<([i32; 3], u32, u32)> {
    let mut v: Vec<_> = map.voxels.iter().map(|(k, v)| (k.0, v.occupancy.to_bits(), v.variance.to_bits())).collect();
    v.sort_unstable();
    v
}

fn on_threads<T: Send>(n: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap().install(f)
}

#[test]
fn every_engine_keeps_the_engine_contract() {
    let fr = frames();
    for kind in EngineKind::ALL.iter().copied() {
        let config = EngineConfig::new(kind, 0.05);
        let map = on_threads(1, || build(&config, &fr));
        assert!(map.occupied_count() > 100, "{kind}: {} occupied", map.occupied_count());

        // The number of threads changes nothing.
        assert_eq!(voxels(&map), voxels(&on_threads(3, || build(&config, &fr))), "{kind}: 1 vs 3 threads");

        // An empty frame (no valid pixel) is no reading: the map of the others, unchanged.
        let mut blank = fr[1].clone();
        blank.depth = DepthImage::new(blank.depth.width(), blank.depth.height());
        let with_blank = on_threads(1, || build(&config, &[fr[0].clone(), blank.clone(), fr[2].clone()]));
        let without = on_threads(1, || build(&config, &[fr[0].clone(), fr[2].clone()]));
        assert_eq!(voxels(&with_blank), voxels(&without), "{kind}: an empty frame changed the map");
        assert!(on_threads(1, || build(&config, &[blank])).voxels.is_empty(), "{kind}: empty frame alone");

        // NaN and infinite depths are no readings, as zeros are.
        let (mut nan, mut zero) = (fr[0].clone(), fr[0].clone());
        for v in (0..nan.depth.height()).step_by(3) {
            for u in 0..nan.depth.width() {
                nan.depth.set(u, v, if u % 2 == 0 { f32::NAN } else { f32::INFINITY });
                zero.depth.set(u, v, 0.0);
            }
        }
        let (nan_map, zero_map) = on_threads(1, || (build(&config, &[nan]), build(&config, &[zero])));
        assert!(nan_map.occupied_count() > 10, "{kind}: the valid pixels still map");
        assert_eq!(voxels(&nan_map), voxels(&zero_map), "{kind}: NaN depth is not a missing reading");

        // Bounds the frames do not reach: nothing to map, and no error.
        let mut away = config;
        away.limits.bounds = Some(Aabb::new([50.0, 50.0, 50.0], [51.0, 51.0, 51.0]).unwrap());
        assert!(on_threads(1, || build(&away, &fr)).voxels.is_empty(), "{kind}: voxels outside the bounds");

        // The map file gives back every voxel, bit for bit, and what the map says of itself.
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("m.mrfmap");
        map.save(&path).unwrap();
        let back = Map::load(&path).unwrap();
        assert_eq!(voxels(&back), voxels(&map), "{kind}: map file round trip");
        assert_eq!((back.engine, back.has_variance, &back.params), (kind, map.has_variance, &map.params));

        // Saved straight from the engine (what `mrfmap build` does), the same bytes as the
        // engine's map with the same parameters added and saved, and the same counts.
        let mut engine = new_engine(&config).unwrap();
        fr.iter().for_each(|f| engine.integrate(f).unwrap());
        engine.finish().unwrap();
        let extra = std::collections::BTreeMap::from([("source".to_string(), "three views".to_string())]);
        let mut whole = engine.map();
        whole.params.extend(extra.clone());
        whole.save(&path).unwrap();
        let streamed = tmp.path().join("streamed.mrfmap");
        let saved = engine.save_map(&streamed, &extra).unwrap();
        assert_eq!(std::fs::read(&streamed).unwrap(), std::fs::read(&path).unwrap(), "{kind}: saved from the engine");
        assert_eq!((saved.voxels, saved.occupied), (whole.voxels.len(), whole.occupied_count()), "{kind}");
        assert!(saved.occupied > 10, "{kind}: {saved:?}");
    }
}
