//! How much memory a build will take, estimated before it starts (checked against
//! [`crate::limits::max_memory`]).
//!
//! A map holds the 8x8x8 bricks its rays cross. Their number is bounded twice: by the volume
//! the rays span (the box around the sensor positions and ray end points, cut to the map's
//! bounds) over a brick's volume, and by the total ray length over a brick's
//! edge (twice: a ray crosses a brick at a slant). The smaller bound wins; indoor scenes are
//! volume-bound, long trajectories ray-bound. Bytes per brick were measured on coffin-world
//! and the demo room (BENCHMARKS.md) and include each engine's scratch memory: log-odds
//! 6 KiB, CRM 1 KiB + 4 (particles + 1) bytes per voxel it allocates (512, or fewer in a
//! map thinner than a brick, such as a planar laser's). The MRF (band allocation)
//! allocates around depth points only, three bricks per brick holding end points: 5 KiB
//! each for the marginals (and the values the change log compares with), and per keyframe
//! 2.5 KiB each for its tiles' messages (10 bytes per voxel a tile's rays reach and 16 per
//! run of them in one brick; measured on the demo room with 12-byte entries: 2.7 MiB per
//! keyframe for 299 end-point bricks at 0.05 m). Accurate to a factor of about 2: enough to
//! refuse a build that cannot fit, not to size a machine.

use super::{EngineConfig, EngineKind};
use crate::error::Result;
use crate::frames::{Frame, RangeScan};
use crate::limits;
use crate::map::BRICK_EDGE;

/// Pixels (per side) between the sampled pixels of [`frames_extent`].
const SAMPLE_STRIDE: u32 = 8;

/// Where the sensors were and how far they saw.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Extent {
    /// Lower corner of the reachable box.
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
    /// Summed length of every ray that will be traced (metres).
    pub ray_length: f64,
    /// Bricks holding ray end points: over all readings sampled, and per sampled reading
    /// (0 when unknown). What the MRF allocates: bricks around depth points only.
    pub surface_bricks: (f64, f64),
}

impl Extent {
    /// The box around `points` (sensor positions and ray end points, or a sample of them),
    /// cut to the config's bounds, with the total ray length. `None` without points.
    pub fn new(points: impl IntoIterator<Item = [f64; 3]>, ray_length: f64, config: &EngineConfig) -> Option<Self> {
        let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in points.into_iter().filter(|p| p.iter().all(|v| v.is_finite())) {
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        if !min[0].is_finite() {
            return None;
        }
        if let Some(b) = config.limits.bounds {
            for a in 0..3 {
                min[a] = min[a].max(b.min[a]);
                max[a] = max[a].min(b.max[a]).max(min[a]);
            }
        }
        Some(Extent { min, max, ray_length, surface_bricks: (0.0, 0.0) })
    }

    /// Records the bricks (at `resolution`) holding the end points of each sampled reading.
    pub fn with_surface(mut self, readings: &[Vec<[f64; 3]>], resolution: f64) -> Self {
        let key = |p: &[f64; 3]| crate::map::VoxelKey::from_point(*p, resolution).brick();
        let all: rustc_hash::FxHashSet<_> = readings.iter().flatten().map(key).collect();
        let per: f64 =
            readings.iter().map(|r| r.iter().map(key).collect::<rustc_hash::FxHashSet<_>>().len() as f64).sum::<f64>()
                / readings.len().max(1) as f64;
        self.surface_bricks = (all.len() as f64, per);
        self
    }

    /// Largest side of the box (metres).
    pub fn size(&self) -> f64 {
        (0..3).map(|a| self.max[a] - self.min[a]).fold(0.0, f64::max)
    }

    /// Bricks of edge `8 resolution` the rays can touch.
    pub fn bricks(&self, resolution: f64) -> f64 {
        let edge = BRICK_EDGE as f64 * resolution;
        let by_volume: f64 = (0..3).map(|a| ((self.max[a] - self.min[a]) / edge).ceil() + 1.0).product();
        let by_rays = 2.0 * self.ray_length / edge;
        by_volume.min(by_rays.max(1.0))
    }

    /// Voxels per brick the readings can reach: 512, or fewer where the box is thinner than
    /// a brick (a planar laser's map is one voxel thick: 64 per brick).
    pub fn voxels_per_brick(&self, resolution: f64) -> f64 {
        (0..3).map(|a| (((self.max[a] - self.min[a]) / resolution).floor() + 1.0).min(BRICK_EDGE as f64)).product()
    }
}

/// Estimated peak memory in bytes of building `config`'s map from `readings` frames or scans.
///
/// ```
/// use mrfmap::inference::{EngineConfig, EngineKind, Extent, estimate_memory};
/// let config = EngineConfig::new(EngineKind::LogOdds, 0.02);
/// let room = Extent::new([[-3.0, -3.0, 0.0], [3.0, 3.0, 3.0]], 1e7, &config).unwrap();
/// let bytes = estimate_memory(&config, &room, 10);
/// assert!(bytes > 1e7 && bytes < 1e9, "{bytes}");
/// let tiny = EngineConfig::new(EngineKind::LogOdds, 1e-9);
/// assert!(estimate_memory(&tiny, &room, 10) > 1e15);
/// // CRM keeps a pdf per voxel it allocates: a planar laser's one-voxel-thick map needs an
/// // eighth of a room's pdfs per brick.
/// let crm = EngineConfig::new(EngineKind::Crm, 0.05);
/// let floor = Extent::new([[-3.0, -3.0, 0.0], [3.0, 3.0, 0.0]], 1e7, &crm).unwrap();
/// let thick = Extent::new([[-3.0, -3.0, 0.0], [3.0, 3.0, 3.0]], 1e7, &crm).unwrap();
/// assert_eq!(floor.voxels_per_brick(0.05), 64.0);
/// assert!(estimate_memory(&crm, &floor, 10) < estimate_memory(&crm, &thick, 10) / 8.0);
/// ```
pub fn estimate_memory(config: &EngineConfig, extent: &Extent, readings: usize) -> f64 {
    let per_brick = match config.kind {
        EngineKind::LogOdds => 6144.0,
        EngineKind::Crm => {
            1024.0 + extent.voxels_per_brick(config.resolution) * 4.0 * (config.crm.particles as f64 + 1.0)
        }
        EngineKind::Mrf => {
            // Band allocation: bricks around depth points (and their neighbours), for the
            // marginals and for each keyframe's tiles.
            let (all, per) = extent.surface_bricks;
            if per > 0.0 && config.mrf.allocation == super::Allocation::Band {
                return BAND * (5120.0 * all + 2560.0 * readings as f64 * per);
            }
            6144.0 * (1.0 + readings as f64)
        }
    };
    extent.bricks(config.resolution) * per_brick
}

/// Where `count` posed depth frames look: every one of their `positions`, and the end points of
/// every `SAMPLE_STRIDE`-th pixel of the `sampled` frames, whose ray length is scaled up to all.
pub fn frames_extent(
    positions: impl Iterator<Item = [f64; 3]>,
    sampled: &[Frame],
    count: usize,
    config: &EngineConfig,
) -> Option<Extent> {
    let max_range = config.limits.max_range.unwrap_or(f64::INFINITY);
    let mut points: Vec<[f64; 3]> = positions.collect();
    let mut length = 0.0;
    let mut surfaces = Vec::new();
    for frame in sampled {
        let cam = &frame.camera;
        let mut surface = Vec::new();
        for v in (0..cam.height).step_by(SAMPLE_STRIDE as usize) {
            for u in (0..cam.width).step_by(SAMPLE_STRIDE as usize) {
                if let Some(z) = frame.depth.get(u, v) {
                    let ray = cam.pixel_ray(u as f64, v as f64);
                    let range = (ray.norm() * z as f64).min(max_range);
                    length += range;
                    let end: [f64; 3] = (frame.pose * nalgebra::Point3::from(ray.normalize() * range)).coords.into();
                    points.push(end);
                    surface.push(end);
                }
            }
        }
        surfaces.push(surface);
    }
    let scale = (SAMPLE_STRIDE * SAMPLE_STRIDE) as f64 * count as f64 / sampled.len().max(1) as f64;
    Extent::new(points, length * scale, config).map(|e| e.with_surface(&surfaces, config.resolution))
}

/// Where laser scans look: every beam's end point (misses at the maximum range).
pub fn scan_extent(scans: &[RangeScan], config: &EngineConfig) -> Option<Extent> {
    let mut points = Vec::new();
    let mut length = 0.0;
    for s in scans {
        points.push(s.pose.translation.vector.into());
        for b in &s.beams {
            let r = b.range.unwrap_or(s.max_range).min(config.limits.max_range.unwrap_or(f64::INFINITY));
            length += r;
            let d = nalgebra::Vector3::from(b.dir) * r;
            points.push((s.pose * nalgebra::Point3::from(d)).coords.into());
        }
    }
    Extent::new(points, length, config)
}

/// Refuses a build of `readings` frames or scans spanning `extent` whose memory estimate is
/// over [`limits::max_memory`] (the error names the estimate, the limit and `advice`), and
/// warns when a voxel is larger than everything the sensors saw. No extent (nothing seen):
/// nothing to refuse.
pub fn check_build(config: &EngineConfig, extent: Option<Extent>, readings: usize, advice: &str) -> Result<()> {
    let Some(extent) = extent else { return Ok(()) };
    let what = format!("a {} map at {} m", config.kind, config.resolution);
    let estimate = estimate_memory(config, &extent, readings);
    // Big builds say so before they start (a fine resolution can take minutes and gigabytes).
    if estimate > (1u64 << 30) as f64 {
        tracing::info!(
            "{what}: expect about {} of memory (limit {})",
            limits::human(estimate),
            limits::human(limits::max_memory() as f64)
        );
    } else {
        tracing::debug!("{what}: memory estimate {}", limits::human(estimate));
    }
    limits::check_memory(&what, estimate, advice)?;
    if config.resolution > extent.size() {
        tracing::warn!(
            "a {} m voxel is larger than everything the sensors saw ({:.2} m across): the map will be a few voxels",
            config.resolution,
            extent.size()
        );
    }
    Ok(())
}

/// Bricks the MRF's band allocates per brick holding end points (the brick and its neighbours
/// along the rays; measured 209 MiB for an estimate of about 330 on coffin-world at 0.01 m).
const BAND: f64 = 3.0;
