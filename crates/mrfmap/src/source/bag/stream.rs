//! One pass over a bag: its depth images ([`for_each_frame`], [`DepthStream`]) or range scans
//! ([`bag_scans`]) with their poses, read once in log order.
//!
//! Poses come from messages logged beside the images: the pose topic's samples or the
//! transform tree, which a stamp is interpolated in once samples on both sides of it have
//! arrived. So each image waits ([`Posing`]) until its pose is known (or known to be
//! missing), and then until [`JITTER`] more images have arrived, so that images logged a
//! little out of stamp order are mapped in stamp order. Memory holds the waiting images (at
//! most [`WINDOW`]: past that the oldest goes with what is known), the transforms of the last
//! [`KEEP_POSES`] seconds and the map, whatever the bag's size.

use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::path::Path;
use std::sync::Arc;

use super::{Bag, BagOptions, Encoding, insert_tf, msgs, sibling_camera_info, tf};
use crate::error::{Error, Result};
use crate::frames::{Beam, Camera, Frame, NoiseModel, Pose, RangeScan};

/// Images (or scans) that arrive after one before it is released: how far out of stamp order
/// the log may be and still be mapped in stamp order.
pub const JITTER: u64 = 16;

/// Messages waiting at most; past this the oldest is released with the pose known so far
/// (64 images of 640 x 480 millimetres: 39 MB).
pub const WINDOW: usize = 64;

/// Seconds of transforms kept behind the last released message's stamp.
pub const KEEP_POSES: f64 = 30.0;

/// Where poses come from, fed message by message as the bag is read.
enum Poses {
    /// Samples of the pose topic.
    Topic { topic: String, series: tf::Series },
    /// `/tf` and `/tf_static`, looked up in `fixed`.
    Tf { fixed: String, buffer: tf::TfBuffer },
}

impl Poses {
    fn new(options: &BagOptions) -> Result<Self> {
        Ok(match (&options.pose_topic, &options.fixed_frame) {
            (Some(topic), _) => Poses::Topic { topic: topic.clone(), series: tf::Series::default() },
            (None, Some(fixed)) => Poses::Tf { fixed: fixed.clone(), buffer: tf::TfBuffer::default() },
            (None, None) => {
                return Err(Error::Invalid("a bag needs --fixed-frame (poses from /tf) or --pose-topic".into()));
            }
        })
    }

    /// The topics the poses come from.
    fn topics(&self) -> Vec<String> {
        match self {
            Poses::Topic { topic, .. } => vec![topic.clone()],
            Poses::Tf { .. } => vec!["/tf".into(), "/tf_static".into()],
        }
    }

    /// Takes in one message of [`Poses::topics`].
    fn accept(&mut self, bag: &Bag, topic: &str, msgtype: &str, data: &[u8], encoding: Encoding) -> Result<()> {
        match self {
            Poses::Topic { series, .. } => {
                // Odometry and TransformStamped both put a child frame id before the pose.
                let odometry = msgtype.contains("Odometry") || msgtype.contains("TransformStamped");
                let (h, p) = msgs::pose(data, encoding, odometry)
                    .map_err(|m| Error::file(&bag.path, format!("{topic}: {m}")))?;
                series.push(h.stamp, &p);
            }
            Poses::Tf { buffer, .. } => insert_tf(buffer, bag, topic, data, encoding)?,
        }
        Ok(())
    }

    /// The pose of `frame` (a message's frame id) at `t`, as far as the samples so far tell.
    fn lookup(&self, frame: &str, t: f64, max_gap: f64) -> std::result::Result<Pose, String> {
        match self {
            Poses::Topic { series, .. } => series.at(t, max_gap),
            Poses::Tf { fixed, buffer } => buffer.lookup(fixed, frame, t, max_gap),
        }
    }

    /// The time up to which the poses are known (no sample can come before it any more).
    fn known_until(&self) -> Option<f64> {
        match self {
            Poses::Topic { series, .. } => series.latest(),
            Poses::Tf { buffer, .. } => buffer.known_until(),
        }
    }

    fn forget_before(&mut self, t: f64) {
        match self {
            Poses::Topic { series, .. } => series.forget_before(t),
            Poses::Tf { buffer, .. } => buffer.forget_before(t),
        }
    }

    /// The error for a bag that held no pose at all.
    fn none_error(&self, bag: &Bag) -> Option<Error> {
        let none = match self {
            Poses::Topic { topic, series } => {
                series.is_empty().then(|| format!("no messages on the pose topic {topic}"))
            }
            Poses::Tf { buffer, .. } => buffer
                .frames()
                .is_empty()
                .then(|| "no transforms on /tf or /tf_static: name a --pose-topic".to_string()),
        };
        none.map(|m| Error::file(&bag.path, m))
    }
}

/// A message waiting for its pose: its stamp, frame id, number on its topic (from 1) and
/// what it carries.
struct Waiting<T> {
    stamp: f64,
    frame_id: String,
    n: usize,
    item: T,
}

/// Waiting messages' order: stamp, then arrival.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Order(f64, u64);

impl Eq for Order {}

impl PartialOrd for Order {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Order {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0).then(self.1.cmp(&other.1))
    }
}

/// Messages waiting for their poses, released in stamp order once their turn has come (see
/// the module docs).
struct Posing<T> {
    poses: Poses,
    max_gap: f64,
    /// What a message is called in reports (`image`, `scan`).
    what: &'static str,
    waiting: BTreeMap<Order, Waiting<T>>,
    arrived: u64,
    /// Latest stamp released.
    released: f64,
    /// Messages released after one stamped later (more out of order than [`JITTER`]).
    late: usize,
    /// Messages without a pose, and why.
    skipped: Vec<String>,
}

impl<T> Posing<T> {
    fn new(options: &BagOptions, what: &'static str) -> Result<Self> {
        Ok(Posing {
            poses: Poses::new(options)?,
            max_gap: options.max_pose_gap,
            what,
            waiting: BTreeMap::new(),
            arrived: 0,
            released: f64::NEG_INFINITY,
            late: 0,
            skipped: Vec::new(),
        })
    }

    fn push(&mut self, stamp: f64, frame_id: String, n: usize, item: T) {
        self.waiting.insert(Order(stamp, self.arrived), Waiting { stamp, frame_id, n, item });
        self.arrived += 1;
    }

    /// Hands `emit` each waiting message whose turn has come, with its pose (those without
    /// one are skipped): all of them at the `end`, else while the earliest has its pose
    /// settled, `ready` holds (the camera is known) and [`JITTER`] messages arrived after it,
    /// or more than [`WINDOW`] wait.
    fn release(
        &mut self,
        end: bool,
        ready: bool,
        mut emit: impl FnMut(Waiting<T>, Pose) -> Result<ControlFlow<()>>,
    ) -> Result<ControlFlow<()>> {
        loop {
            let crowded = self.waiting.len() > WINDOW;
            let Some(entry) = self.waiting.first_entry() else { break };
            let (order, w) = (*entry.key(), entry.get());
            // (The pose is looked up only once the message could go: not on every message
            // that arrives while it waits for its followers.)
            let may_go = ready && self.arrived - order.1 > JITTER; // (JITTER arrived after it)
            if !(end || crowded || may_go) {
                break;
            }
            let pose = self.poses.lookup(&w.frame_id, w.stamp, self.max_gap);
            let settled = pose.is_ok() || self.poses.known_until().is_some_and(|known| known > w.stamp + self.max_gap);
            if !(end || crowded || settled) {
                break;
            }
            let w = entry.remove();
            if w.stamp < self.released {
                self.late += 1;
            }
            self.released = self.released.max(w.stamp);
            self.poses.forget_before(self.released - KEEP_POSES);
            match pose {
                Ok(pose) => {
                    if emit(w, pose)?.is_break() {
                        return Ok(ControlFlow::Break(()));
                    }
                }
                Err(why) => self.skipped.push(format!("{} {} at {:.3} s: {why}", self.what, w.n, w.stamp)),
            }
        }
        Ok(ControlFlow::Continue(()))
    }

    /// After the last message: the error for a bag without poses, and a warning for messages
    /// mapped out of stamp order.
    fn finish(&self, bag: &Bag, topic: &str) -> Result<()> {
        if let Some(e) = self.poses.none_error(bag) {
            return Err(e);
        }
        if self.late > 0 {
            tracing::warn!(
                "{}: {topic}: {} {}(s) logged more than {JITTER} after later-stamped ones were mapped out of stamp order",
                bag.path.display(),
                self.late,
                self.what
            );
        }
        Ok(())
    }
}

/// What a pass over a bag's depth images found besides the frames.
#[derive(Clone, Debug, Default)]
pub struct StreamReport {
    /// Posed frames handed on.
    pub frames: usize,
    /// Images without a pose, and why.
    pub skipped: Vec<String>,
}

/// A depth image as logged, decoded when its turn comes (memory holds its message, half the
/// decoded size for 16-bit depth).
struct Image {
    data: Vec<u8>,
    decode: msgs::DecodeImage,
    encoding: Encoding,
}

/// The decoder of an image topic's message type.
fn image_decoder(bag: &Bag, topic: &str, msgtype: &str) -> Result<msgs::DecodeImage> {
    match msgtype {
        "sensor_msgs/msg/Image" | "" => Ok(msgs::depth_image),
        "sensor_msgs/msg/CompressedImage" => Ok(msgs::compressed_depth),
        other => Err(Error::file(
            &bag.path,
            format!("{topic} carries {other}, not sensor_msgs/msg/Image or CompressedImage"),
        )),
    }
}

/// A posed depth image, not decoded yet: what the pass over the bag hands on, so that
/// decoding can run on another thread than reading ([`DepthStream`]).
struct PosedImage {
    index: usize,
    stamp: f64,
    pose: Pose,
    camera: Camera,
    /// Its number on the topic (from 1), for errors.
    n: usize,
    image: Image,
}

impl PosedImage {
    /// The frame: the image decoded (errors name `bag`'s file and `topic`).
    fn decode(self, bag: &Path, topic: &str, noise: Option<Arc<NoiseModel>>) -> Result<Frame> {
        let bad = |m: String| Error::file(bag, format!("{topic}: image {}: {m}", self.n));
        let (_, depth) = (self.image.decode)(&self.image.data, self.image.encoding).map_err(bad)?;
        let camera = self.camera;
        if (depth.width(), depth.height()) != (camera.width, camera.height) {
            return Err(bad(format!(
                "{}x{} but its camera info says {}x{}",
                depth.width(),
                depth.height(),
                camera.width,
                camera.height
            )));
        }
        Ok(Frame { index: self.index, timestamp: self.stamp, depth, pose: self.pose, camera, noise })
    }
}

/// Calls `visit` with each posed depth image of `options.depth_topic` (see
/// [`for_each_frame`]), undecoded.
fn for_each_posed_image(
    bag: &Bag,
    options: &BagOptions,
    mut visit: impl FnMut(PosedImage) -> Result<ControlFlow<()>>,
) -> Result<StreamReport> {
    let bad = |m: String| Error::file(&bag.path, m);
    let topic = options.depth_topic.as_str();
    let info_topic = options.camera_info_topic.clone().unwrap_or_else(|| sibling_camera_info(topic));
    let mut posing = Posing::new(options, "image")?;
    let mut topics = posing.poses.topics();
    topics.extend([info_topic.clone(), topic.to_string()]);
    let topics: Vec<&str> = topics.iter().map(String::as_str).collect();
    let (mut camera, mut images, mut frames, mut last_stamp) = (None::<Camera>, 0, 0, f64::NEG_INFINITY);
    // A released image, handed on.
    let mut emit = |camera: Option<Camera>, w: Waiting<Image>, pose: Pose| -> Result<ControlFlow<()>> {
        let Some(camera) = camera else {
            return Err(bad(format!(
                "no CameraInfo on {info_topic} before image {} (name it with --camera-info-topic)",
                w.n
            )));
        };
        frames += 1;
        visit(PosedImage { index: frames - 1, stamp: w.stamp, pose, camera, n: w.n, image: w.item })
    };
    let mut stopped = false;
    let read = bag.for_each(&topics, |t, msgtype, _, data, encoding| {
        if t == topic {
            images += 1;
            let decode = image_decoder(bag, t, msgtype)?;
            let h = msgs::image_header(data, encoding).map_err(|m| bad(format!("{t}: image {images}: {m}")))?;
            if h.stamp < last_stamp {
                tracing::warn!("{t}: image {images} is stamped before the one logged before it");
            }
            last_stamp = last_stamp.max(h.stamp);
            posing.push(h.stamp, h.frame_id, images, Image { data: data.to_vec(), decode, encoding });
        } else if t == info_topic {
            if camera.is_none() {
                let (_, w, h, k) = msgs::camera_info(data, encoding).map_err(|m| bad(format!("{t}: {m}")))?;
                camera = Some(Camera::new(k[0], k[4], k[2], k[5], w, h, 1000.0).map_err(|e| bad(format!("{t}: {e}")))?);
            }
        } else {
            posing.poses.accept(bag, t, msgtype, data, encoding)?;
        }
        let cam = camera;
        if posing.release(false, cam.is_some(), |w, pose| emit(cam, w, pose))?.is_break() {
            stopped = true;
            // (An error is the readers' only way to stop early; it is not one.)
            return Err(Error::Invalid("stopped".into()));
        }
        Ok(())
    });
    if !stopped {
        read?;
        if images == 0 {
            return Err(bad(format!("no messages on {topic}")));
        }
        if camera.is_none() {
            return Err(bad(format!("no CameraInfo on {info_topic} (name it with --camera-info-topic)")));
        }
        posing.finish(bag, topic)?;
        let cam = camera;
        // (A break here has nothing left to stop.)
        let _ = posing.release(true, true, |w, pose| emit(cam, w, pose))?;
    }
    Ok(StreamReport { frames, skipped: posing.skipped })
}

/// Calls `visit` with each posed depth frame of `options.depth_topic`, in one pass over the
/// bag: frame `i` is the `i`-th posed image in stamp order (up to [`JITTER`]), with the
/// intrinsics of the first `CameraInfo` on the camera-info topic. Stops early when `visit`
/// breaks. Memory holds a few images (see the module docs), whatever the bag's size.
pub fn for_each_frame(
    bag: &Bag,
    options: &BagOptions,
    noise: Option<NoiseModel>,
    mut visit: impl FnMut(Frame) -> Result<ControlFlow<()>>,
) -> Result<StreamReport> {
    let noise = noise.map(Arc::new);
    for_each_posed_image(bag, options, |image| visit(image.decode(&bag.path, &options.depth_topic, noise.clone())?))
}

/// The posed depth frames of a bag ([`for_each_frame`]) as an iterator, in three stages that
/// overlap: a thread reads the bag and poses the images, a second decodes them, and the
/// caller works on the last ones (a few wait between stages).
pub struct DepthStream {
    frames: std::sync::mpsc::IntoIter<Result<Frame>>,
    report: std::sync::mpsc::Receiver<Result<StreamReport>>,
    done: Option<StreamReport>,
}

impl DepthStream {
    /// Starts reading `bag`.
    pub fn new(bag: Bag, options: BagOptions, noise: Option<NoiseModel>) -> Self {
        let (send_image, receive_image) = std::sync::mpsc::sync_channel::<PosedImage>(4);
        let (send_frame, receive_frame) = std::sync::mpsc::sync_channel(2);
        let (send_report, report) = std::sync::mpsc::channel();
        let (path, topic) = (bag.path.clone(), options.depth_topic.clone());
        let errors = send_frame.clone();
        std::thread::spawn(move || {
            let result = for_each_posed_image(&bag, &options, |image| {
                // A closed channel: the caller has stopped reading.
                Ok(match send_image.send(image) {
                    Ok(()) => ControlFlow::Continue(()),
                    Err(_) => ControlFlow::Break(()),
                })
            });
            // (Images first: the decoder ends when the reader has, then the caller sees the error.)
            drop(send_image);
            match result {
                Ok(r) => {
                    let _ = send_report.send(Ok(r));
                }
                Err(e) => {
                    let _ = errors.send(Err(e));
                }
            }
        });
        let noise = noise.map(Arc::new);
        std::thread::spawn(move || {
            for image in receive_image {
                if send_frame.send(image.decode(&path, &topic, noise.clone())).is_err() {
                    return;
                }
            }
        });
        DepthStream { frames: receive_frame.into_iter(), report, done: None }
    }

    /// What the pass found, once the iterator has ended (`None` if it ended in an error).
    pub fn report(&mut self) -> Option<&StreamReport> {
        if self.done.is_none() {
            self.done = self.report.try_recv().ok().and_then(|r| r.ok());
        }
        self.done.as_ref()
    }
}

impl Iterator for DepthStream {
    type Item = Result<Frame>;

    fn next(&mut self) -> Option<Result<Frame>> {
        self.frames.next()
    }
}

/// Depth frames of `options.depth_topic` with poses, all in memory (refused before they
/// outgrow the memory limit; see [`DepthStream`] to stream them); also the images skipped and
/// why.
pub fn bag_frames(bag: &Bag, options: &BagOptions, noise: Option<NoiseModel>) -> Result<(Vec<Frame>, Vec<String>)> {
    let mut frames: Vec<Frame> = Vec::new();
    let report = for_each_frame(bag, options, noise, |frame| {
        // Decoded frames stay in memory (4 bytes a pixel): stop before they outgrow the limit.
        let held = (frames.len() + 1) as f64 * frame.camera.pixel_count() as f64 * 4.0;
        crate::limits::check_memory(
            &format!("decoding {} images of {}", frames.len() + 1, options.depth_topic),
            held,
            "map part of the bag (split it, or export-dataset and build with --frames)",
        )?;
        frames.push(frame);
        Ok(ControlFlow::Continue(()))
    })?;
    Ok((frames, report.skipped))
}

/// A range scan as decoded, before its pose: beams and max range.
type Beams = (Vec<Beam>, f64);

/// Range scans of the `sensor_msgs/LaserScan` or `sensor_msgs/PointCloud2` topic `topic`
/// (a cloud's points as beams from the sensor's origin), posed as `options` says (its depth
/// topic is not used), in one pass; also the scans skipped and why.
pub fn bag_scans(
    bag: &Bag,
    topic: &str,
    options: &BagOptions,
    noise: Option<NoiseModel>,
) -> Result<(Vec<RangeScan>, Vec<String>)> {
    let bad = |m: String| Error::file(&bag.path, m);
    let mut posing: Posing<Beams> = Posing::new(options, "scan")?;
    let mut topics = posing.poses.topics();
    topics.push(topic.to_string());
    let topics: Vec<&str> = topics.iter().map(String::as_str).collect();
    let noise = noise.map(Arc::new);
    let (mut scans, mut n, mut held) = (Vec::new(), 0, 0.0);
    let mut emit = |w: Waiting<Beams>, pose: Pose| -> Result<ControlFlow<()>> {
        let (beams, max_range) = w.item;
        // Scans are held until the build (a lidar's clouds are megabytes each): stop before
        // they outgrow the memory limit.
        held += (beams.len() * std::mem::size_of::<Beam>() + std::mem::size_of::<RangeScan>()) as f64;
        crate::limits::check_memory(
            &format!("holding {} scans of {topic}", scans.len() + 1),
            held,
            "map part of the recording (split the bag)",
        )
        .map_err(|e| bad(e.to_string()))?;
        let scan = RangeScan::new(scans.len(), pose, beams, max_range, noise.clone())
            .map_err(|e| bad(format!("{topic}: scan {}: {e}", w.n)))?;
        scans.push(scan);
        Ok(ControlFlow::Continue(()))
    };
    bag.for_each(&topics, |t, msgtype, _, data, encoding| {
        if t != topic {
            posing.poses.accept(bag, t, msgtype, data, encoding)?;
        } else {
            n += 1;
            let decoded = match msgtype {
                "sensor_msgs/msg/LaserScan" => msgs::laser_scan(data, encoding).map(|(h, beams, max_range)| {
                    let beams =
                        beams.into_iter().map(|(a, range)| Beam { dir: [a.cos(), a.sin(), 0.0], range }).collect();
                    (h, beams, max_range)
                }),
                // A cloud's points are beams from the sensor's origin, every one a return.
                "sensor_msgs/msg/PointCloud2" => msgs::point_cloud(data, encoding).map(|(h, points)| {
                    let beams: Vec<Beam> = points
                        .into_iter()
                        .filter_map(|p| {
                            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                            (r > 0.0).then(|| Beam { dir: p.map(|v| v / r), range: Some(r) })
                        })
                        .collect();
                    let max_range = beams.iter().filter_map(|b| b.range).fold(1e-3, f64::max) * 1.01;
                    (h, beams, max_range)
                }),
                other => {
                    return Err(bad(format!("{t} carries {other:?}, not sensor_msgs/msg/LaserScan or PointCloud2")));
                }
            };
            let (h, beams, max_range) = decoded.map_err(|m| bad(format!("{t}: message {n}: {m}")))?;
            posing.push(h.stamp, h.frame_id, n, (beams, max_range));
        }
        posing.release(false, true, &mut emit).map(|_| ())
    })?;
    if n == 0 {
        return Err(bad(format!("no messages on {topic}")));
    }
    posing.finish(bag, topic)?;
    let _ = posing.release(true, true, &mut emit)?; // (emit never breaks)
    Ok((scans, posing.skipped))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn posing() -> Posing<u32> {
        let options = BagOptions {
            depth_topic: "/d".into(),
            camera_info_topic: None,
            fixed_frame: None,
            pose_topic: Some("/pose".into()),
            max_pose_gap: 0.5,
        };
        Posing::new(&options, "image").unwrap()
    }

    /// A pose sample at `t` of a sensor at x = t.
    fn sample(p: &mut Posing<u32>, t: f64) {
        let Poses::Topic { series, .. } = &mut p.poses else { unreachable!() };
        series.push(t, &msgs::Transform { translation: [t, 0.0, 0.0], rotation: [0.0, 0.0, 0.0, 1.0] });
    }

    /// Releases what is due into `out` as (item, x of its pose).
    fn release(p: &mut Posing<u32>, end: bool, out: &mut Vec<(u32, f64)>) {
        let flow = p.release(end, true, |w, pose| {
            out.push((w.item, pose.translation.x));
            Ok(ControlFlow::Continue(()))
        });
        assert!(flow.unwrap().is_continue());
    }

    #[test]
    fn messages_wait_for_their_poses_and_go_in_stamp_order() {
        let mut p = posing();
        let mut out = Vec::new();
        sample(&mut p, 0.0);
        // Stamps 0.1, 0.3, 0.2 (logged out of order), then many more: each goes once poses
        // after it are in and JITTER messages came after it, in stamp order.
        for (n, stamp) in [0.1, 0.3, 0.2].into_iter().chain((4..40).map(|k| k as f64 * 0.1)).enumerate() {
            p.push(stamp, String::new(), n + 1, n as u32);
            sample(&mut p, stamp + 0.05);
            release(&mut p, false, &mut out);
        }
        let n = out.len();
        assert_eq!(n as u64, p.arrived - JITTER, "all but the last JITTER are out");
        assert_eq!(&out[..3].iter().map(|o| o.0).collect::<Vec<_>>(), &[0, 2, 1], "stamp order");
        assert!(out.iter().all(|&(item, x)| {
            let stamp = if item < 3 { [0.1, 0.3, 0.2][item as usize] } else { (item + 1) as f64 * 0.1 };
            (x - stamp).abs() < 1e-9
        }));
        release(&mut p, true, &mut out);
        assert_eq!(out.len(), 39);
        assert!(p.skipped.is_empty() && p.late == 0);
        // Old samples went: the series holds the last KEEP_POSES seconds at most, twice over.
        let Poses::Topic { series, .. } = &p.poses else { unreachable!() };
        assert_eq!(series.len(), 40, "(this recording is shorter than KEEP_POSES)");
    }

    #[test]
    fn a_missing_pose_is_skipped_once_settled_and_the_window_is_bounded() {
        let mut p = posing();
        let mut out = Vec::new();
        // Poses from 10 s on: a message stamped 1 s never gets one. It is settled (skipped)
        // once the poses pass 1 s + the allowed gap, and not before its JITTER followers.
        p.push(1.0, String::new(), 1, 0);
        for k in 0..JITTER {
            p.push(10.0 + k as f64, String::new(), k as usize + 2, k as u32 + 1);
        }
        release(&mut p, false, &mut out);
        assert!(out.is_empty() && p.skipped.is_empty(), "no pose known yet: waiting");
        sample(&mut p, 10.0);
        release(&mut p, false, &mut out);
        assert_eq!(p.skipped.len(), 1, "{:?}", p.skipped);
        assert!(p.skipped[0].starts_with("image 1 at 1.000 s: stamp 1.000 s is outside"), "{:?}", p.skipped);
        // Without any pose, at most WINDOW wait: the oldest goes (skipped) as more come.
        let mut q = posing();
        for k in 0..(WINDOW as u32 + 10) {
            q.push(k as f64, String::new(), k as usize + 1, k);
            release(&mut q, false, &mut out);
            assert!(q.waiting.len() <= WINDOW);
        }
        assert_eq!(q.skipped.len(), 10);
        // A message logged after a later-stamped one was released is counted as late.
        q.push(0.5, String::new(), 999, 999);
        release(&mut q, true, &mut out);
        assert_eq!(q.late, 1);
    }

    #[test]
    fn old_transforms_are_let_go() {
        let mut p = posing();
        let mut out = Vec::new();
        for k in 0..2000 {
            let t = k as f64 * 0.1;
            sample(&mut p, t);
            p.push(t, String::new(), k + 1, k as u32);
            release(&mut p, false, &mut out);
        }
        let Poses::Topic { series, .. } = &p.poses else { unreachable!() };
        // 200 s of samples at 10 Hz; those older than KEEP_POSES behind the last released go.
        assert!(series.len() <= 2 * (KEEP_POSES * 10.0) as usize + 2 * JITTER as usize, "{}", series.len());
        assert_eq!(out.len(), 2000 - JITTER as usize);
    }
}
