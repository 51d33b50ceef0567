//! How much memory a build will take, estimated before it starts (checked against
//! [`crate::limits::max_memory`]).
//!
//! A map holds the 8x8x8 bricks its rays cross, and CRM a pdf per voxel they cross. Both
//! counts come from walking a sample of the rays brick by brick ([`frames_extent`],
//! [`scan_extent`]): up to 512 readings evenly spread over the sequence (every pose, each
//! with the depth of the decoded sample frame nearest it), and as many of their rays as about
//! 8 million brick steps allow. Bricks are counted as the walked rays cross them (the gaps
//! between one reading's walked rays are crossed by the next reading's); voxels are made up
//! for the pixels and readings not walked, at most 512 per brick (64 in a planar laser's
//! one-voxel-thick map). The forward-model engines (CRM, MRF) walk each ray to 3 std past its
//! bias-corrected reading, as they trace it.
//!
//! Bytes per brick and per voxel were measured (BENCHMARKS.md, "Memory estimates"): a
//! log-odds build peaks at 8 KiB per dense brick (the engine's f32 grid and the finished
//! map's copy, 8 bytes per voxel), 3 KiB when the map is saved from the engine without that
//! copy ([`MapOutput::Saved`]; bricks hold only their z-layers that hold voxels, so a planar
//! map's take an eighth); CRM holds 4 (particles + 1) + 5 bytes per voxel, a slot
//! table and the map's copy per brick (1 + 4 KiB dense) and, while a frame is applied, 4 KiB
//! per brick it
//! crosses; the MRF (band allocation) allocates
//! two bricks per brick holding depth points, 5 KiB each for the marginals (and the values the
//! change log compares with), and per keyframe 16 bytes per voxel its rays cross in those
//! bricks (its tiles' entries, found by a second walk once the band is known) and its depth
//! image. Integrating one reading takes about 40 bytes per pixel besides, and the program
//! itself [`BASE_MEMORY`]. The estimate is meant to be within 2x of the measured peak (the
//! test `memory_estimate` checks each engine at 0.05, 0.02 and 0.01 m against the heap a
//! build takes): enough to refuse a build that cannot fit, not to size a machine to the
//! megabyte.

use std::borrow::Cow;
use std::ops::ControlFlow;

use rustc_hash::{FxHashMap, FxHashSet};

use super::{EngineConfig, EngineKind};
use crate::error::Result;
use crate::frames::{Frame, NoiseModel, Pose, RangeScan, default_noise_model};
use crate::limits;
use crate::map::{BRICK_EDGE, BrickKey, VoxelKey};
use crate::rays::{FrameRays, PixelRay, ScanRays, Walk, pixel_direction, pose_parts};

/// Where a build's map goes, which decides whether the finished map is ever held beside the
/// engine's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapOutput {
    /// Made in memory ([`super::Engine::map`], [`crate::pipeline::build`], Python's builds).
    InMemory,
    /// Written from the engine to a file ([`super::Engine::save_map`], `mrfmap build`): a
    /// log-odds map is converted a brick at a time, never whole.
    Saved,
}

/// Estimated peak memory in bytes of building `config`'s map from the readings of `extent`
/// into `output` (see the module's documentation for what is counted).
pub fn estimate_memory(config: &EngineConfig, extent: &Extent, output: MapOutput) -> f64 {
    let scratch = SCRATCH_PER_PIXEL * extent.pixels;
    BASE_MEMORY
        + scratch
        + match config.kind {
            EngineKind::LogOdds => match output {
                MapOutput::InMemory => LOGODDS_BRICK * extent.bricks + LOGODDS_LAYER * extent.layers,
                MapOutput::Saved => LOGODDS_SAVED_BRICK * extent.bricks + LOGODDS_SAVED_LAYER * extent.layers,
            },
            EngineKind::Crm => {
                let per_voxel = 4.0 * (config.crm.particles as f64 + 1.0) + CRM_VOXEL;
                CRM_BRICK * extent.bricks
                    + MAP_LAYER * extent.layers
                    + per_voxel * extent.voxels
                    + CRM_FRAME_BRICK * extent.bricks_per_reading
            }
            EngineKind::Mrf => {
                let bricks = match config.mrf.allocation {
                    super::Allocation::Band => BAND * extent.surface_bricks,
                    super::Allocation::Full => extent.bricks,
                };
                let keyframe = MRF_ENTRY * extent.entries_per_reading + MRF_FRAME_PER_PIXEL * extent.pixels;
                MRF_BRICK * bricks + extent.readings * keyframe
            }
        }
}

/// Brick steps the probe walk of [`frames_extent`] and [`scan_extent`] may take in all: about
/// a tenth of a second, and at most this many bricks (24 bytes each) held while counting.
const STEP_BUDGET: f64 = 8e6;

/// Brick steps after which a walk stops and the estimate falls back on the box's volume: the
/// budget with room for a mean ray length that was misjudged.
const CUT_STEPS: f64 = 4.0 * STEP_BUDGET;

/// Distinct bricks after which a walk stops likewise: the budget's steps, each a new brick.
/// (The steps' cut alone let a walk at a resolution far below the scene's scale, where every
/// step is a new brick, hold four times as many: 1 µm voxels on a room took 1.6 GB and
/// 25-34 s to refuse the build.)
const CUT_BRICKS: usize = STEP_BUDGET as usize;

/// Readings walked at most; more are subsampled evenly along the sequence.
const MAX_PROBES: usize = 512;

/// Rays walked per reading at least (the budget is met by walking fewer readings below this).
const MIN_RAYS: f64 = 64.0;

/// Where the sensors were, and what their rays will allocate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Extent {
    /// Lower corner of the box the rays reach (cut to the map's bounds).
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
    /// Bricks the rays cross (estimated: see [`frames_extent`]).
    pub bricks: f64,
    /// Voxels the rays cross (estimated likewise; at most 512 per brick).
    pub voxels: f64,
    /// Layers of 64 voxels (a brick's z-layers) that hold voxels: 8 per brick, or fewer where
    /// the box is thinner than a brick (one in a planar laser's map).
    pub layers: f64,
    /// Bricks one reading's rays cross, on average.
    pub bricks_per_reading: f64,
    /// Bricks holding ray end points. What the MRF allocates: bricks around depth points
    /// only.
    pub surface_bricks: f64,
    /// Voxels per reading its rays cross in the bricks holding their end points, once per
    /// pixel column (what an MRF keyframe's tiles hold).
    pub entries_per_reading: f64,
    /// Readings the engine keeps: the MRF's keyframes, or all.
    pub readings: f64,
    /// Pixels (or beams) of the largest reading.
    pub pixels: f64,
}

impl Extent {
    /// Largest side of the box (metres).
    pub fn size(&self) -> f64 {
        (0..3).map(|a| self.max[a] - self.min[a]).fold(0.0, f64::max)
    }
}

/// Counts the bricks and voxels a sample of rays crosses.
///
/// Rays are walked brick by brick, and the bricks they cross are counted. Rays not walked
/// are not made up for in bricks: the walked ones are dense at the brick scale, and across
/// readings the gaps of one are the rays of another (crediting each walked ray with the bricks
/// around it counted those twice: 1.9x a laser log's bricks). Voxels are made up for: a ray
/// walked `sampled` radians from the next (per image axis; `dims` axes: 2 for a camera, 1 for
/// a planar scan) crosses at range `d`, per axis, `min(max(1, sampled d / r), sampled /
/// native)` lines of voxels (every voxel of its tube where the sensor's own rays, `native`
/// radians apart, are denser than voxels; one line per ray where they are sparser), times the
/// `readings` it stands for along the sequence; a brick holds at most its voxels.
struct Probe<'a> {
    config: &'a EngineConfig,
    edge: f64,
    /// Per brick crossed: voxels the rays crossed in it, and the last reading that crossed it.
    bricks: FxHashMap<BrickKey, (f32, usize)>,
    /// Sum over readings of the bricks each crossed.
    crossed: f64,
    /// Brick steps walked (and planned for the ray being walked).
    steps: f64,
    /// Set when the steps or the bricks outgrew the budget: the walk stopped.
    cut: bool,
    /// Distinct bricks held at most ([`CUT_BRICKS`]).
    max_bricks: usize,
    /// Bricks holding an end point.
    surface: FxHashSet<BrickKey>,
    /// Set for a second walk: the bricks the MRF allocates, whose voxels the rays cross are
    /// counted in `entries` instead of all else.
    band: Option<FxHashSet<BrickKey>>,
    /// Sum over readings of the voxels their rays cross in the band (each voxel once per pixel
    /// column: the MRF's tile entries).
    entries: f64,
    readings: usize,
    min: [f64; 3],
    max: [f64; 3],
}

impl<'a> Probe<'a> {
    fn new(config: &'a EngineConfig) -> Self {
        Probe {
            config,
            edge: BRICK_EDGE as f64 * config.resolution,
            bricks: FxHashMap::default(),
            crossed: 0.0,
            steps: 0.0,
            cut: false,
            max_bricks: CUT_BRICKS,
            surface: FxHashSet::default(),
            band: None,
            entries: 0.0,
            readings: 0,
            min: [f64::INFINITY; 3],
            max: [f64::NEG_INFINITY; 3],
        }
    }

    fn include(&mut self, p: [f64; 3]) {
        if p.iter().all(|v| v.is_finite()) {
            self.min = [0, 1, 2].map(|a| self.min[a].min(p[a]));
            self.max = [0, 1, 2].map(|a| self.max[a].max(p[a]));
        }
    }

    /// Walks one ray of a reading with `noise` (see [`Probe`] for `sampled`, `native`, `dims`
    /// and `readings`).
    fn ray(&mut self, ray: &PixelRay, noise: &NoiseModel, sampled: f64, native: f64, dims: i32, readings: f64) {
        // The forward-model engines stop 3 std past the bias-corrected reading (short of it,
        // where the bias is larger: 0.9 m at 5 m for a D435).
        let seg = match self.config.kind {
            EngineKind::LogOdds => self.config.limits.segment(ray, 0.0),
            EngineKind::Crm | EngineKind::Mrf => self.config.limits.forward_model_segment(ray, noise),
        };
        let Some(seg) = seg else { return };
        let at = |s: f64| [0, 1, 2].map(|a| ray.origin[a] + s * ray.dir[a]);
        self.include(at(seg.start));
        self.include(at(seg.end));
        let r = self.config.resolution;
        let lines = sampled / native;
        // A walk the budget cannot pay for (a resolution far below the scene's scale) stops
        // here; the estimate then falls back on the box's volume.
        self.steps += 1.8 * (seg.end - seg.start) / self.edge + 1.0;
        if self.cut || self.steps > CUT_STEPS {
            self.cut = true;
            return;
        }
        let Some(walk) = Walk::new(ray.origin, ray.dir, self.edge) else { return };
        if let Some(band) = &self.band {
            // The second walk: the voxels this ray crosses in the MRF's band (once per pixel
            // column: where pixels are smaller than voxels, neighbours share columns).
            let pixels = lines.powi(dims);
            let mut entries = 0.0;
            walk.crossings(seg.start, seg.end, |c| {
                if band.contains(&BrickKey(c.key.0)) {
                    let own = (native * 0.5 * (c.s_in + c.s_out) / r).min(1.0).powi(dims);
                    entries += pixels * own * c.length() / r;
                }
                ControlFlow::Continue(())
            });
            self.entries += entries;
            return;
        }
        let reading = self.readings + 1;
        walk.crossings(seg.start, seg.end, |c| {
            let across = (sampled * 0.5 * (c.s_in + c.s_out) / r).max(1.0).min(lines).powi(dims);
            if self.bricks.len() >= self.max_bricks {
                self.cut = true;
                return ControlFlow::Break(());
            }
            let cell = self.bricks.entry(BrickKey(c.key.0)).or_default();
            cell.0 += (c.length() / r * across * readings) as f32;
            if cell.1 != reading {
                cell.1 = reading;
                self.crossed += 1.0;
            }
            ControlFlow::Continue(())
        });
        // The depth point itself (not the segment's end, 3 std past it and maybe cut by the
        // bounds: a floor at the box's bottom face).
        let point = at(ray.range);
        let limits = &self.config.limits;
        if limits.surface_range(ray).is_some() && limits.bounds.is_none_or(|b| b.contains(point)) {
            self.surface.insert(BrickKey(VoxelKey::from_point(point, self.edge).0));
        }
    }

    /// Ends a reading's rays.
    fn next_reading(&mut self) {
        if self.band.is_none() {
            self.readings += 1;
        }
    }

    /// The extent of `count` readings of `pixels` each: `None` when no ray was walked.
    fn finish(self, count: usize, pixels: f64) -> Option<Extent> {
        if !self.min[0].is_finite() {
            return None;
        }
        let (min, max) = (self.min, self.max);
        let r = self.config.resolution;
        // Voxels per brick the box allows: 512, or fewer where it is thinner than a brick (a
        // planar laser's map is one voxel thick: 64 per brick).
        let across = |a: usize| (((max[a] - min[a]) / r).floor() + 1.0).min(BRICK_EDGE as f64);
        let per_brick: f64 = (0..3).map(across).product();
        let readings = self.readings.max(1) as f64;
        let by_volume: f64 = (0..3).map(|a| ((max[a] - min[a]) / self.edge).ceil() + 1.0).product();
        if self.cut {
            // Everything in the box, and as many tile entries per pixel as a brick is deep.
            return Some(Extent {
                min,
                max,
                bricks: by_volume,
                voxels: by_volume * per_brick,
                layers: by_volume * across(2),
                bricks_per_reading: by_volume,
                surface_bricks: by_volume,
                entries_per_reading: pixels * BRICK_EDGE as f64,
                readings: count as f64,
                pixels,
            });
        }
        let voxels = self.bricks.values().map(|&(v, _)| (v as f64).min(per_brick)).sum();
        Some(Extent {
            min,
            max,
            bricks: self.bricks.len() as f64,
            voxels,
            layers: self.bricks.len() as f64 * across(2),
            bricks_per_reading: self.crossed / readings,
            surface_bricks: self.surface.len() as f64,
            entries_per_reading: self.entries / readings,
            readings: count as f64,
            pixels,
        })
    }
}

/// Readings to walk of `count`, and per reading a sampling stride for rays of about
/// `mean_length` metres, so that the walk stays within [`STEP_BUDGET`].
///
/// A camera's rays (`focal` length in pixels) need not be walked closer than a quarter brick
/// apart at the mean range: a brick there spans `focal * edge / mean_length` pixels, so such
/// rays meet the bricks a denser walk would, and the walk's voxel counts are per ray (made up
/// for the pixels between). Half a brick apart was tried and found too few of the MRF's
/// surface bricks (its estimates fell to 0.66x the peak). Without this bound a few-frame build
/// walked a third of its pixels, and the estimate was 44% of the whole build's instructions
/// (icl-livingroom-5 at 0.05 m; BENCHMARKS.md, "Memory estimates").
fn plan(count: usize, rays: f64, mean_length: f64, edge: f64, focal: Option<f64>) -> (usize, f64) {
    let steps = 1.8 * mean_length / edge + 1.0;
    let probes = count.min(MAX_PROBES).min((STEP_BUDGET / (MIN_RAYS * steps)).max(1.0) as usize).max(1);
    let spacing = focal.map_or(1.0, |f| (0.25 * f * edge / mean_length.max(edge)).max(1.0));
    let per = (STEP_BUDGET / (probes as f64 * steps))
        .min(rays / (spacing * spacing))
        .clamp(MIN_RAYS.min(rays.max(1.0)), rays.max(1.0));
    (probes, rays / per)
}

/// Where depth frames at `poses` look and what their rays will allocate, from every frame's
/// pose and the depth of a few decoded `sampled` frames (evenly spread over the sequence):
/// up to 512 of the poses (for the MRF, of its keyframes), each with the depth of the sampled
/// frame nearest it in the sequence, are walked brick by brick through as many of their
/// pixels as the step budget allows. Bricks are counted as crossed; voxels are made up for
/// the pixels and frames not walked (the module's documentation says how). `None` without
/// poses or depth.
///
/// ```
/// use mrfmap::frames::{Camera, DepthImage, Frame, Pose};
/// use mrfmap::inference::{EngineConfig, EngineKind, frames_extent};
/// let camera = Camera::new(100.0, 100.0, 49.5, 39.5, 100, 80, 1000.0).unwrap();
/// // A wall 2 m ahead of a camera looking along +z.
/// let frame = Frame {
///     index: 0,
///     timestamp: 0.0,
///     depth: DepthImage::from_vec(100, 80, vec![2.0; 8000]).unwrap(),
///     pose: Pose::identity(),
///     camera,
///     noise: None,
/// };
/// let config = EngineConfig::new(EngineKind::LogOdds, 0.05);
/// let one = frames_extent([Pose::identity()], std::slice::from_ref(&frame), &config).unwrap();
/// // The frustum is a pyramid 2 m deep on a 2 x 1.6 m base: it fills a third of the 5 x 4 x 5
/// // bricks of 0.4 m around it and crosses a good part of the others.
/// assert!(one.bricks > 33.0 && one.bricks < 100.0, "{}", one.bricks);
/// // The same frame from ten poses 2 m apart sideways: ten times the bricks, about.
/// let poses = (0..10).map(|i| Pose::translation(2.0 * i as f64, 0.0, 0.0));
/// let ten = frames_extent(poses, std::slice::from_ref(&frame), &config).unwrap();
/// assert!(ten.bricks > 8.0 * one.bricks && ten.bricks <= 10.0 * one.bricks, "{}", ten.bricks);
/// // No poses, or no sampled depth: nothing to estimate.
/// assert!(frames_extent([], std::slice::from_ref(&frame), &config).is_none());
/// assert!(frames_extent([Pose::identity()], &[], &config).is_none());
/// ```
pub fn frames_extent(
    poses: impl IntoIterator<Item = Pose>,
    sampled: &[Frame],
    config: &EngineConfig,
) -> Option<Extent> {
    let Ok(extent) = frames_extent_loaded::<std::convert::Infallible>(
        poses,
        sampled.len(),
        |k| Ok(Cow::Borrowed(&sampled[k])),
        config,
    );
    extent
}

/// [`frames_extent`] with `count` sampled frames that `load(k)` gives (`k` in `0..count`, in
/// the sequence's order) when they are needed, so that no more than one is held at a time:
/// for frames read from files, decoded again rather than kept (eight 640 x 480 frames were
/// the largest part of a small build's peak memory).
pub fn frames_extent_loaded<'f, E>(
    poses: impl IntoIterator<Item = Pose>,
    count: usize,
    mut load: impl FnMut(usize) -> std::result::Result<Cow<'f, Frame>, E>,
    config: &EngineConfig,
) -> std::result::Result<Option<Extent>, E> {
    let mut poses: Vec<Pose> = poses.into_iter().collect();
    // The MRF keeps its keyframes only.
    if config.kind == EngineKind::Mrf {
        poses = config.mrf.keyframes.keep(&poses).into_iter().map(|i| poses[i]).collect();
    }
    if poses.is_empty() || count == 0 {
        return Ok(None);
    }
    // The mean ray length, from every 8th pixel of the samples.
    let (mut length, mut n) = (0.0, 0.0f64);
    let (mut pixels, mut f) = (0.0, 0.0);
    for k in 0..count {
        let frame = load(k)?;
        if k == 0 {
            (pixels, f) = (
                frame.depth.width() as f64 * frame.depth.height() as f64,
                0.5 * (frame.camera.fx.abs() + frame.camera.fy.abs()),
            );
        }
        let rays = FrameRays::new(&frame);
        for v in (0..frame.depth.height()).step_by(8) {
            for ray in rays.row(v).step_by(8) {
                if let Some(seg) = config.limits.segment(&ray, 0.0) {
                    length += seg.end - seg.start;
                }
                n += 1.0;
            }
        }
    }
    let default_noise = default_noise_model();
    let mut probe = Probe::new(config);
    for pose in &poses {
        probe.include(pose.translation.vector.into());
    }
    let (probes, stride) = plan(poses.len(), pixels, length / n.max(1.0), probe.edge, Some(f));
    let step = stride.sqrt().ceil().max(1.0) as u32;
    let (sampled_angle, native) = (step as f64 / f, 1.0 / f);
    let readings = poses.len() as f64 / probes as f64;
    let mut walk = |probe: &mut Probe| {
        // Probes go through the sequence in order, so each sample is loaded once per walk.
        let mut current: Option<(usize, Cow<'f, Frame>)> = None;
        for j in 0..probes {
            let i = j * poses.len() / probes;
            let k = (i * count / poses.len()).min(count - 1);
            let frame = match current {
                Some((at, ref frame)) if at == k => frame,
                _ => &current.insert((k, load(k)?)).1,
            };
            let (rotation, origin) = pose_parts(&poses[i]);
            let noise = frame.noise.as_deref().unwrap_or(&default_noise);
            for v in (0..frame.depth.height()).step_by(step as usize) {
                for u in (0..frame.depth.width()).step_by(step as usize) {
                    let Some(z) = frame.depth.get(u, v) else { continue };
                    let (dir, norm) = pixel_direction(&frame.camera, &rotation, u, v);
                    let range = z as f64 * norm;
                    let ray = PixelRay { u, v, origin, dir, range, cz: 1.0 / norm, returned: true };
                    probe.ray(&ray, noise, sampled_angle, native, 2, readings);
                }
            }
            probe.next_reading();
        }
        Ok(())
    };
    walk(&mut probe)?;
    // The MRF's tiles hold the voxels their rays cross in the allocated bricks, which are
    // known only now: the band around end points, or every brick crossed.
    if config.kind == EngineKind::Mrf {
        probe.band = Some(match config.mrf.allocation {
            super::Allocation::Band => probe.surface.clone(),
            super::Allocation::Full => probe.bricks.keys().copied().collect(),
        });
        walk(&mut probe)?;
        probe.band = None;
    }
    Ok(probe.finish(poses.len(), pixels))
}

/// Where laser scans look and what their beams will allocate (misses up to the sensor's
/// range), walked as [`frames_extent`] walks frames: beams are a fan, so each walked beam
/// stands for its neighbours in one direction only. `None` without scans.
///
/// ```
/// let config = mrfmap::inference::EngineConfig::new(mrfmap::inference::EngineKind::LogOdds, 0.05);
/// assert!(mrfmap::inference::scan_extent(&[], &config).is_none());
/// ```
pub fn scan_extent(scans: &[RangeScan], config: &EngineConfig) -> Option<Extent> {
    if scans.is_empty() {
        return None;
    }
    let default_noise = default_noise_model();
    let mut probe = Probe::new(config);
    let beams: usize = scans.iter().map(|s| s.beams.len()).sum();
    let length: f64 = scans
        .iter()
        .flat_map(|s| {
            s.beams.iter().map(|b| b.range.unwrap_or(s.max_range).min(config.limits.max_range.unwrap_or(f64::INFINITY)))
        })
        .sum();
    let per_scan = beams as f64 / scans.len().max(1) as f64;
    let (probes, stride) = plan(scans.len(), per_scan, length / beams.max(1) as f64, probe.edge, None);
    let every = stride.ceil().max(1.0) as usize;
    let readings = scans.len() as f64 / probes as f64;
    for j in 0..probes {
        let scan = &scans[j * scans.len() / probes];
        probe.include(scan.pose.translation.vector.into());
        // The fan's spacing: its spread over its gaps.
        let native = match (scan.beams.first(), scan.beams.last()) {
            (Some(a), Some(b)) if scan.beams.len() > 1 => {
                let cos = (0..3).map(|k| a.dir[k] * b.dir[k]).sum::<f64>().clamp(-1.0, 1.0);
                (cos.acos() / (scan.beams.len() - 1) as f64).max(1e-6)
            }
            _ => std::f64::consts::PI,
        };
        let rays = ScanRays::new(scan);
        let noise = scan.noise.as_deref().unwrap_or(&default_noise);
        for ray in (0..rays.rows()).flat_map(|v| rays.row(v).collect::<Vec<_>>()).step_by(every) {
            probe.ray(&ray, noise, native * every as f64, native, 1, readings);
        }
        probe.next_reading();
    }
    probe.finish(scans.len(), scans.iter().map(|s| s.beams.len()).max().unwrap_or(0) as f64)
}

/// Estimates above this are announced before a build starts ([`check_build`]).
pub const ANNOUNCED_MEMORY: f64 = (1u64 << 30) as f64;

/// An upper bound on the extent of a log-odds build of `pixels`-pixel frames from cameras at
/// `poses` with a max range and no bounds, from the poses alone: every voxel such a build
/// marks holds a point of a segment that ends within the max range of its camera
/// ([`crate::rays::RayLimits::hit_miss_segment`]), so its bricks lie in the box around the
/// cameras widened by the max range. Every count is taken as that box's (a brick's eight
/// layers, its 512 voxels), so [`estimate_memory`] of it is at least that of any estimate of
/// the same frames. `None` for the other engines (they keep what depends on the readings
/// themselves), without a max range, with bounds, or without poses.
pub fn poses_bound(poses: impl IntoIterator<Item = Pose>, pixels: f64, config: &EngineConfig) -> Option<Extent> {
    let (EngineKind::LogOdds, Some(reach), None) = (config.kind, config.limits.max_range, &config.limits.bounds) else {
        return None;
    };
    let (mut min, mut max, mut readings) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3], 0.0);
    for pose in poses {
        let t = pose.translation.vector;
        for a in 0..3 {
            (min[a], max[a]) = (min[a].min(t[a] - reach), max[a].max(t[a] + reach));
        }
        readings += 1.0;
    }
    if readings == 0.0 || !min.iter().chain(&max).all(|v| v.is_finite()) {
        return None;
    }
    let r = config.resolution;
    let (lo, hi) = (VoxelKey::from_point(min, r).brick().0, VoxelKey::from_point(max, r).brick().0);
    let bricks: f64 = (0..3).map(|a| hi[a] as f64 - lo[a] as f64 + 1.0).product();
    let voxels = bricks * (BRICK_EDGE * BRICK_EDGE * BRICK_EDGE) as f64;
    Some(Extent {
        min,
        max,
        bricks,
        voxels,
        layers: bricks * BRICK_EDGE as f64,
        bricks_per_reading: bricks,
        surface_bricks: bricks,
        entries_per_reading: voxels,
        readings,
        pixels,
    })
}

/// Refuses a build of `readings` frames or scans spanning `extent` into `output` whose memory
/// estimate is over [`limits::max_memory`] (the error names the estimate, the limit and
/// `advice`), and warns when a voxel is larger than everything the sensors saw. No extent
/// (nothing seen): nothing to refuse.
pub fn check_build(config: &EngineConfig, extent: Option<Extent>, output: MapOutput, advice: &str) -> Result<()> {
    let Some(extent) = extent else { return Ok(()) };
    let what = format!("a {} map at {} m", config.kind, config.resolution);
    let estimate = estimate_memory(config, &extent, output);
    tracing::debug!(
        "{what}: memory estimate {} ({:.0} bricks, {:.0} voxels, {:.0} bricks holding end points, {:.0} readings kept, {:.0} tile entries each)",
        limits::human(estimate),
        extent.bricks,
        extent.voxels,
        extent.surface_bricks,
        extent.readings,
        extent.entries_per_reading
    );
    // Big builds say so before they start (a fine resolution can take minutes and gigabytes).
    if estimate > ANNOUNCED_MEMORY {
        tracing::info!(
            "{what}: expect about {} of memory (limit {})",
            limits::human(estimate),
            limits::human(limits::max_memory() as f64)
        );
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

/// Bricks the MRF's band allocates per brick holding end points: that brick, and the
/// neighbours of points within a voxel of a face.
const BAND: f64 = 2.0;

/// Bytes of a build besides its engine (in every estimate): the program, its libraries and
/// threads, and the frame being decoded (the code and libraries are about 8 MiB resident; a
/// build of a few bricks from 640 x 480 frames peaks at 14 MiB).
pub const BASE_MEMORY: f64 = 12.0 * 1048576.0;

/// Bytes per brick of a log-odds map while it is built, besides its layers: the engine's grid
/// and the finished map's copy, each a mask, a layer table and a hash table entry.
const LOGODDS_BRICK: f64 = 512.0;
/// Bytes per layer of 64 voxels of a log-odds map: 4 bytes per voxel in the engine's grid, 8
/// in the finished map's copy, and room for the layers' vectors to grow. The engine's layers
/// are freed as the map's are made ([`crate::inference::Engine::into_map`]), so the heap
/// peaks below the sum (the `memory_estimate` test: 1.6-1.8x under this price), but the
/// allocator keeps most of what they held, so the resident size does not (0.9-1.0x on
/// coffin-world and intel-lab).
const LOGODDS_LAYER: f64 = 896.0;
/// [`LOGODDS_BRICK`] of a log-odds map saved from its engine ([`MapOutput::Saved`]): the
/// engine's grid alone.
const LOGODDS_SAVED_BRICK: f64 = 256.0;
/// [`LOGODDS_LAYER`] of a log-odds map saved from its engine: its 4 bytes per voxel and room
/// for the layers' vectors to grow, no finished map's copy.
const LOGODDS_SAVED_LAYER: f64 = 352.0;
/// Bytes per brick of a CRM map besides its voxels and the map's layers: the slot table
/// (1 KiB) and the finished map's brick.
const CRM_BRICK: f64 = 1280.0;
/// Bytes per layer of 64 voxels of the finished map's copy (8 bytes each, allocated or not).
const MAP_LAYER: f64 = 512.0;
/// Bytes per CRM voxel besides its pdf: its mean and pending passes.
const CRM_VOXEL: f64 = 5.0;
/// Bytes per brick a frame crosses of a CRM frame's update: its passes per slot (2 KiB),
/// gathered by two blocks of rows on average.
const CRM_FRAME_BRICK: f64 = 4096.0;
/// Bytes per MRF brick for the marginals (and the values the change log compares with).
const MRF_BRICK: f64 = 5120.0;
/// Bytes per entry of an MRF keyframe's tiles (a voxel one of its tiles' rays reach): 10,
/// and the runs that index them and the vectors' spare capacity (measured 287 MiB of tiles
/// for 12 keyframes of 1.49 M estimated entries on coffin-world at 0.02 m: 16.8).
const MRF_ENTRY: f64 = 16.0;
/// Bytes per pixel a keyframe keeps (its depth image).
const MRF_FRAME_PER_PIXEL: f64 = 4.0;
/// Bytes per pixel of the working memory of integrating one reading.
const SCRATCH_PER_PIXEL: f64 = 40.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_camera_walks_rays_a_quarter_brick_apart_at_most() {
        // 5 frames of 640 x 480, rays of 3 m, bricks of 0.4 m, focal 480 px: a brick at 3 m
        // spans 64 pixels, so rays 16 pixels apart (1,200 a frame) are enough.
        let (probes, stride) = plan(5, 307_200.0, 3.0, 0.4, Some(480.0));
        assert_eq!(probes, 5);
        assert!((stride - 256.0).abs() < 1e-9, "{stride}");
        // Without a camera the budget alone decides: far denser.
        let (_, budget_only) = plan(5, 307_200.0, 3.0, 0.4, None);
        assert!(budget_only < 3.0, "{budget_only}");
        // Never fewer than MIN_RAYS a reading, however coarse the bricks.
        let (_, coarse) = plan(5, 307_200.0, 3.0, 40.0, Some(480.0));
        assert!(307_200.0 / coarse >= MIN_RAYS - 1e-9, "{coarse}");
    }

    #[test]
    fn a_walk_stops_at_its_brick_limit_and_falls_back_on_the_volume() {
        let config = EngineConfig::new(EngineKind::LogOdds, 0.01);
        let mut probe = Probe::new(&config);
        let noise = default_noise_model();
        // 4 m rays along x, side by side: about 50 bricks of 8 cm each.
        let ray = |y: f64| PixelRay {
            u: 0,
            v: 0,
            origin: [0.01, y, 0.01],
            dir: [1.0, 0.0, 0.0],
            range: 4.0,
            cz: 1.0,
            returned: true,
        };
        probe.ray(&ray(0.05), &noise, 1e-3, 1e-3, 2, 1.0);
        let one = probe.bricks.len();
        assert!(!probe.cut && one > 40, "{one}");
        probe.max_bricks = one + 10;
        probe.ray(&ray(0.25), &noise, 1e-3, 1e-3, 2, 1.0);
        assert!(probe.cut && probe.bricks.len() == one + 10, "{}", probe.bricks.len());
        // Once cut, no ray is walked; the box the rays reach, whole, is the estimate.
        probe.ray(&ray(0.45), &noise, 1e-3, 1e-3, 2, 1.0);
        assert_eq!(probe.bricks.len(), one + 10);
        let extent = probe.finish(3, 1.0).unwrap();
        assert!(extent.bricks >= 3.0 * one as f64, "{}", extent.bricks);
    }
}
