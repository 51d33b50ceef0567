//! Robot recordings: ROS 2 bags in MCAP or sqlite3 and ROS 1 bags, read without ROS (cargo
//! feature `bags`).
//!
//! A bag is one `.mcap`, `.db3` or ROS 1 `.bag` file, or a bag folder (`metadata.yaml` beside
//! one or more such files, read in name order). Messages are decoded by hand from CDR ([`msgs`]): depth images
//! (`sensor_msgs/Image`, 16UC1 millimetres or 32FC1 metres), `sensor_msgs/CameraInfo`,
//! `tf2_msgs/TFMessage` on `/tf` and `/tf_static`, `geometry_msgs/PoseStamped`,
//! `nav_msgs/Odometry`, and `sensor_msgs/LaserScan` and `sensor_msgs/PointCloud2` as range scans
//! ([`bag_scans`]). [`bag_frames`] turns a depth topic into [`Frame`]s: intrinsics from
//! the camera-info topic (by default the `camera_info` beside the image topic, the ROS
//! convention), each image's pose in a fixed frame from the transform tree ([`tf`]) or from a
//! pose topic, interpolated at the image's stamp. The ROS optical frame (z forward, x right,
//! y down) is mrfmap's camera frame, so poses are used as they are. Images without a pose
//! within the allowed gap are reported and skipped.
//!
//! Every format is read forward a chunk or a row at a time ([`Bag::for_each`]), so a bag of
//! any size streams. Depth frames take two passes: [`depth_index`] reads the small messages
//! (camera info, poses) and each image's header, and [`for_each_frame`] / [`BagFrames`] then
//! decode the images one at a time in stamp order; [`bag_frames`] collects them all.

pub mod cdr;
mod mcap_reader;
pub mod msgs;
mod ros1;
pub mod tf;

pub use cdr::Encoding;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::frames::{Beam, Camera, Frame, NoiseModel, Pose, RangeScan};

/// A topic of a bag.
#[derive(Clone, Debug, PartialEq)]
pub struct TopicInfo {
    /// Topic name.
    pub topic: String,
    /// Message type (`sensor_msgs/msg/Image`, ...).
    pub msgtype: String,
    /// Messages.
    pub count: u64,
    /// Log time of the first and last message (seconds).
    pub span: (f64, f64),
}

/// An opened bag: the files its messages are in.
#[derive(Clone, Debug)]
pub struct Bag {
    /// What the user named.
    pub path: PathBuf,
    files: Vec<PathBuf>,
}

impl Bag {
    /// Opens a `.mcap` or `.db3` file, or a bag folder.
    pub fn open(path: &Path) -> Result<Self> {
        let is_bag_file = |p: &Path| p.extension().is_some_and(|e| e == "mcap" || e == "db3" || e == "bag");
        let files = if path.is_dir() {
            let mut f: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(|e| Error::io(path, e))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| is_bag_file(p))
                .collect();
            f.sort();
            if f.is_empty() {
                return Err(Error::file(path, "not a bag: no .mcap, .db3 or .bag files in the folder"));
            }
            f
        } else if is_bag_file(path) {
            if !path.exists() {
                return Err(Error::io(path, std::io::Error::from(std::io::ErrorKind::NotFound)));
            }
            vec![path.to_path_buf()]
        } else {
            return Err(Error::file(path, "not a bag: expected a .mcap, .db3 or .bag file, or a bag folder"));
        };
        Ok(Bag { path: path.to_path_buf(), files })
    }

    /// Calls `visit(topic, type, log_time_seconds, bytes, encoding)` for every message on
    /// `topics` (all topics when empty), file by file in name order. Types are named the ROS 2
    /// way (`sensor_msgs/msg/Image`) for ROS 1 bags too.
    pub fn for_each(
        &self,
        topics: &[&str],
        mut visit: impl FnMut(&str, &str, f64, &[u8], Encoding) -> Result<()>,
    ) -> Result<()> {
        for file in &self.files {
            if file.extension().is_some_and(|e| e == "db3") {
                sqlite_for_each(file, topics, &mut |t, ty, time, data| visit(t, ty, time, data, Encoding::Cdr))?;
                continue;
            }
            if file.extension().is_some_and(|e| e == "bag") {
                ros1::for_each(file, topics, &mut |t, ty, time, data| visit(t, ty, time, data, Encoding::Ros1))?;
                continue;
            }
            mcap_reader::for_each(file, topics, &mut |t, ty, time, data| visit(t, ty, time, data, Encoding::Cdr))?;
        }
        Ok(())
    }

    /// Topics, types, message counts and time spans.
    pub fn topics(&self) -> Result<Vec<TopicInfo>> {
        let mut t: BTreeMap<String, TopicInfo> = BTreeMap::new();
        self.for_each(&[], |topic, msgtype, time, _, _| {
            let e = t.entry(topic.to_string()).or_insert_with(|| TopicInfo {
                topic: topic.to_string(),
                msgtype: msgtype.to_string(),
                count: 0,
                span: (time, time),
            });
            e.count += 1;
            e.span = (e.span.0.min(time), e.span.1.max(time));
            Ok(())
        })?;
        Ok(t.into_values().collect())
    }

    /// The transform tree of `/tf` and `/tf_static`.
    pub fn tf(&self) -> Result<tf::TfBuffer> {
        let mut buffer = tf::TfBuffer::default();
        self.for_each(&["/tf", "/tf_static"], |topic, _, _, data, encoding| {
            insert_tf(&mut buffer, self, topic, data, encoding)
        })?;
        buffer.finish();
        Ok(buffer)
    }
}

/// Adds one `/tf` or `/tf_static` message's transforms to `buffer`.
fn insert_tf(buffer: &mut tf::TfBuffer, bag: &Bag, topic: &str, data: &[u8], encoding: Encoding) -> Result<()> {
    let entries = msgs::tf_message(data, encoding).map_err(|m| Error::file(&bag.path, format!("{topic}: {m}")))?;
    for (h, child, t) in entries {
        buffer.insert(&h.frame_id, &child, h.stamp, &t, topic == "/tf_static");
    }
    Ok(())
}

/// The messages of a ROS 2 sqlite3 bag file (`topics` and `messages` tables), in time order.
fn sqlite_for_each(
    file: &Path,
    topics: &[&str],
    visit: &mut impl FnMut(&str, &str, f64, &[u8]) -> Result<()>,
) -> Result<()> {
    use rusqlite::{Connection, OpenFlags};
    let bad = |e: rusqlite::Error| Error::file(file, format!("not a readable ROS 2 sqlite3 bag: {e}"));
    let db = Connection::open_with_flags(file, OpenFlags::SQLITE_OPEN_READ_ONLY).map_err(bad)?;
    let mut names = std::collections::HashMap::new();
    let mut stmt = db.prepare("SELECT id, name, type, serialization_format FROM topics").map_err(bad)?;
    let rows = stmt
        .query_map([], |r| {
            Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?, r.get::<_, String>(2)?, r.get::<_, String>(3)?))
        })
        .map_err(bad)?;
    for row in rows {
        let (id, name, msgtype, format) = row.map_err(bad)?;
        if topics.is_empty() || topics.contains(&name.as_str()) {
            if format != "cdr" {
                return Err(Error::file(file, format!("{name}: serialization {format:?} is not CDR")));
            }
            names.insert(id, (name, msgtype));
        }
    }
    let mut stmt = db.prepare("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp").map_err(bad)?;
    let mut rows = stmt.query([]).map_err(bad)?;
    while let Some(row) = rows.next().map_err(bad)? {
        let id: i64 = row.get(0).map_err(bad)?;
        if let Some((name, msgtype)) = names.get(&id) {
            let time: i64 = row.get(1).map_err(bad)?;
            let data = row.get_ref(2).map_err(bad)?.as_blob().map_err(|e| Error::file(file, format!("{name}: {e}")))?;
            visit(name, msgtype, time as f64 * 1e-9, data)?;
        }
    }
    Ok(())
}

/// Where a bag's depth images and their poses come from.
#[derive(Clone, Debug, PartialEq)]
pub struct BagOptions {
    /// The depth image topic.
    pub depth_topic: String,
    /// The camera-info topic (default: `camera_info` beside the image topic).
    pub camera_info_topic: Option<String>,
    /// Poses from the transform tree, in this frame...
    pub fixed_frame: Option<String>,
    /// ...or from this `PoseStamped`, `Odometry` or `TransformStamped` topic (the camera's pose).
    pub pose_topic: Option<String>,
    /// Largest gap between two pose samples an image's stamp may fall in (seconds).
    pub max_pose_gap: f64,
}

/// The camera-info topic ROS puts beside an image topic: `/ns/image_rect_raw` -> `/ns/camera_info`.
pub fn sibling_camera_info(image_topic: &str) -> String {
    match image_topic.rsplit_once('/') {
        Some((ns, _)) => format!("{ns}/camera_info"),
        None => "camera_info".into(),
    }
}

/// A function giving a frame's pose in the fixed frame at a stamp: from the TF tree, or from
/// the pose topic (the sensor's pose, whatever the frame).
type PoseSource = Box<dyn Fn(&str, f64) -> std::result::Result<Pose, String>>;

/// What poses are read from, gathered message by message ([`Poses::accept`]) in a pass over
/// the bag, then turned into a [`PoseSource`] ([`Poses::finish`]).
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
    fn topics(&self) -> Vec<&str> {
        match self {
            Poses::Topic { topic, .. } => vec![topic.as_str()],
            Poses::Tf { .. } => vec!["/tf", "/tf_static"],
        }
    }

    /// Takes in one message of [`Poses::topics`].
    fn accept(&mut self, bag: &Bag, topic: &str, msgtype: &str, data: &[u8], encoding: Encoding) -> Result<()> {
        let bad = |m: String| Error::file(&bag.path, format!("{topic}: {m}"));
        match self {
            Poses::Topic { series, .. } => {
                // Odometry and TransformStamped both put a child frame id before the pose.
                let odometry = msgtype.contains("Odometry") || msgtype.contains("TransformStamped");
                let (h, p) = msgs::pose(data, encoding, odometry).map_err(bad)?;
                series.push(h.stamp, &p);
            }
            Poses::Tf { buffer, .. } => insert_tf(buffer, bag, topic, data, encoding)?,
        }
        Ok(())
    }

    fn finish(self, bag: &Bag, max_gap: f64) -> Result<PoseSource> {
        let bad = |m: String| Error::file(&bag.path, m);
        Ok(match self {
            Poses::Topic { topic, mut series } => {
                if series.is_empty() {
                    return Err(bad(format!("no messages on the pose topic {topic}")));
                }
                series.sort();
                Box::new(move |_, t| series.at(t, max_gap))
            }
            Poses::Tf { fixed, mut buffer } => {
                buffer.finish();
                if buffer.frames().is_empty() {
                    return Err(bad("no transforms on /tf or /tf_static: name a --pose-topic".into()));
                }
                Box::new(move |frame, t| buffer.lookup(&fixed, frame, t, max_gap))
            }
        })
    }
}

fn pose_source(bag: &Bag, options: &BagOptions) -> Result<PoseSource> {
    let mut poses = Poses::new(options)?;
    let topics = poses.topics();
    let topics: Vec<String> = topics.into_iter().map(String::from).collect();
    let topics: Vec<&str> = topics.iter().map(String::as_str).collect();
    bag.for_each(&topics, |t, msgtype, _, data, encoding| poses.accept(bag, t, msgtype, data, encoding))?;
    poses.finish(bag, options.max_pose_gap)
}

/// Range scans of the `sensor_msgs/LaserScan` or `sensor_msgs/PointCloud2` topic `topic`
/// (a cloud's points as beams from the sensor's origin), posed as `options` says (its depth
/// topic is not used); also the scans skipped and why.
pub fn bag_scans(
    bag: &Bag,
    topic: &str,
    options: &BagOptions,
    noise: Option<NoiseModel>,
) -> Result<(Vec<RangeScan>, Vec<String>)> {
    let bad = |m: String| Error::file(&bag.path, m);
    let poses = pose_source(bag, options)?;
    let noise = noise.map(std::sync::Arc::new);
    let (mut scans, mut skipped, mut n) = (Vec::new(), Vec::new(), 0);
    bag.for_each(&[topic], |t, msgtype, _, data, encoding| {
        n += 1;
        let decoded = match msgtype {
            "sensor_msgs/msg/LaserScan" => msgs::laser_scan(data, encoding).map(|(h, beams, max_range)| {
                let beams = beams.into_iter().map(|(a, range)| Beam { dir: [a.cos(), a.sin(), 0.0], range }).collect();
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
            other => return Err(bad(format!("{t} carries {other:?}, not sensor_msgs/msg/LaserScan or PointCloud2"))),
        };
        let (h, beams, max_range) = decoded.map_err(|m| bad(format!("{t}: message {n}: {m}")))?;
        match poses(&h.frame_id, h.stamp) {
            Ok(pose) => {
                let scan = RangeScan::new(0, pose, beams, max_range, noise.clone())
                    .map_err(|e| bad(format!("{t}: scan {n}: {e}")))?;
                scans.push((h.stamp, scan));
            }
            Err(why) => skipped.push(format!("scan {n} at {:.3} s: {why}", h.stamp)),
        }
        Ok(())
    })?;
    if n == 0 {
        return Err(bad(format!("no messages on {topic}")));
    }
    scans.sort_by(|a, b| a.0.total_cmp(&b.0));
    let scans = scans.into_iter().enumerate().map(|(i, (_, mut s))| {
        s.index = i;
        s
    });
    Ok((scans.collect(), skipped))
}

/// What a first pass over a bag finds about its depth images, without keeping them: the
/// camera, the stamp and pose of every image that has one (in stamp order: frame `i` of the
/// bag is the `i`-th of them), the images skipped and why, and a few decoded frames spread
/// over the bag (for estimates). [`for_each_frame`] and [`BagFrames`] then stream the images
/// themselves.
pub struct DepthIndex {
    /// The camera (from the first `CameraInfo`).
    pub camera: Camera,
    /// Stamp and pose of each posed image, in stamp order (log order among equal stamps).
    pub frames: Vec<(f64, Pose)>,
    /// Per image of the topic in log order, its frame index (its place in stamp order), or
    /// `None` for an image without a pose.
    slots: Vec<Option<usize>>,
    /// Images without a pose, and why.
    pub skipped: Vec<String>,
    /// Up to about `sample` decoded frames, evenly spread over the posed ones.
    pub sample: Vec<Frame>,
    options: BagOptions,
    noise: Option<std::sync::Arc<NoiseModel>>,
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

/// Reads the camera, the poses and every depth image's header of `options.depth_topic` in one
/// pass; memory holds the poses (small messages) and `sample` images, not the images.
pub fn depth_index(bag: &Bag, options: &BagOptions, noise: Option<NoiseModel>, sample: usize) -> Result<DepthIndex> {
    let bad = |m: String| Error::file(&bag.path, m);
    let info_topic = options.camera_info_topic.clone().unwrap_or_else(|| sibling_camera_info(&options.depth_topic));
    let mut poses = Poses::new(options)?;
    let pose_topics: Vec<String> = poses.topics().into_iter().map(String::from).collect();
    let mut topics: Vec<&str> = pose_topics.iter().map(String::as_str).collect();
    topics.extend([info_topic.as_str(), options.depth_topic.as_str()]);
    let mut camera = None;
    let mut headers = Vec::new();
    // Every `stride`-th image, decoded; the stride doubles (and every other kept image goes)
    // whenever more than twice `sample` are held, so they stay evenly spread and few.
    let (mut kept, mut stride) = (Vec::new(), 1usize);
    let mut last_stamp = f64::NEG_INFINITY;
    bag.for_each(&topics, |topic, msgtype, _, data, encoding| {
        if topic == options.depth_topic {
            let n = headers.len() + 1;
            let decode = image_decoder(bag, topic, msgtype)?;
            let h = msgs::image_header(data, encoding).map_err(|m| bad(format!("{topic}: image {n}: {m}")))?;
            if h.stamp < last_stamp {
                tracing::warn!("{topic}: image {n} is stamped before the one logged before it");
            }
            last_stamp = last_stamp.max(h.stamp);
            if (n - 1) % stride == 0 && sample > 0 {
                let (_, depth) = decode(data, encoding).map_err(|m| bad(format!("{topic}: image {n}: {m}")))?;
                kept.push((n - 1, depth));
                if kept.len() > 2 * sample {
                    stride *= 2;
                    kept.retain(|(i, _)| i % stride == 0);
                }
            }
            headers.push(h);
        } else if topic == info_topic {
            if camera.is_none() {
                let (_, w, h, k) = msgs::camera_info(data, encoding).map_err(|m| bad(format!("{topic}: {m}")))?;
                camera =
                    Some(Camera::new(k[0], k[4], k[2], k[5], w, h, 1000.0).map_err(|e| bad(format!("{topic}: {e}")))?);
            }
        } else {
            poses.accept(bag, topic, msgtype, data, encoding)?;
        }
        Ok(())
    })?;
    if headers.is_empty() {
        return Err(bad(format!("no messages on {}", options.depth_topic)));
    }
    let camera =
        camera.ok_or_else(|| bad(format!("no CameraInfo on {info_topic} (name it with --camera-info-topic)")))?;
    let poses = poses.finish(bag, options.max_pose_gap)?;
    let noise = noise.map(std::sync::Arc::new);
    let (mut frames, mut skipped, mut posed) = (Vec::new(), Vec::new(), Vec::with_capacity(headers.len()));
    for (n, h) in headers.iter().enumerate() {
        match poses(&h.frame_id, h.stamp) {
            Ok(pose) => {
                posed.push(Some(frames.len()));
                frames.push((h.stamp, pose));
            }
            Err(why) => {
                posed.push(None);
                skipped.push(format!("image {} at {:.3} s: {why}", n + 1, h.stamp));
            }
        }
    }
    // Frames go in stamp order, as a dataset's do. Images logged out of it wait for the ones
    // stamped before them: how many wait at once is known now, and must fit.
    let mut by_stamp: Vec<usize> = (0..frames.len()).collect();
    by_stamp.sort_by(|&a, &b| frames[a].0.total_cmp(&frames[b].0));
    let mut order = vec![0; frames.len()];
    for (rank, &i) in by_stamp.iter().enumerate() {
        order[i] = rank;
    }
    let waiting = most_waiting(&order);
    crate::limits::check_memory(
        &format!("holding {waiting} depth images of {} to put them in stamp order", options.depth_topic),
        waiting as f64 * camera.pixel_count() as f64 * 4.0,
        "record the images in stamp order, or split the bag",
    )?;
    let sample = kept
        .into_iter()
        .filter_map(|(n, depth)| {
            let index = order[posed[n]?];
            let (timestamp, pose) = frames[posed[n]?];
            Some(Frame { index, timestamp, depth, pose, camera, noise: noise.clone() })
        })
        .collect();
    let frames = by_stamp.iter().map(|&i| frames[i]).collect();
    let slots = posed.iter().map(|p| p.map(|i| order[i])).collect();
    Ok(DepthIndex { camera, frames, slots, skipped, sample, options: options.clone(), noise })
}

/// How many frames must wait at most when frames arrive in the order `order` (frame indices)
/// and are handed on in index order.
fn most_waiting(order: &[usize]) -> usize {
    let (mut waiting, mut next, mut most) = (std::collections::BTreeSet::new(), 0, 0);
    for &i in order {
        waiting.insert(i);
        most = most.max(waiting.len() - 1);
        while waiting.remove(&next) {
            next += 1;
        }
    }
    most
}

/// Calls `visit` with each posed depth frame of `index`'s topic in frame order (stamp order;
/// frame `i` is `index.frames[i]`), decoded as they are read, until it returns
/// `ControlFlow::Break`. Only images logged before ones stamped earlier wait in memory.
pub fn for_each_frame(
    bag: &Bag,
    index: &DepthIndex,
    mut visit: impl FnMut(Frame) -> Result<std::ops::ControlFlow<()>>,
) -> Result<()> {
    let bad = |m: String| Error::file(&bag.path, m);
    let (topic, camera) = (index.options.depth_topic.as_str(), index.camera);
    let (mut images, mut next, mut stopped) = (0, 0, false);
    let mut waiting = std::collections::BTreeMap::new();
    let result = bag.for_each(&[topic], |topic, msgtype, _, data, encoding| {
        images += 1;
        let decode = image_decoder(bag, topic, msgtype)?;
        let (h, depth) = decode(data, encoding).map_err(|m| bad(format!("{topic}: image {images}: {m}")))?;
        if (depth.width(), depth.height()) != (camera.width, camera.height) {
            return Err(bad(format!(
                "{topic}: image {images} is {}x{} but its camera info says {}x{}",
                depth.width(),
                depth.height(),
                camera.width,
                camera.height
            )));
        }
        // The first pass posed the images (and skipped those without a pose).
        let Some(&slot) = index.slots.get(images - 1) else {
            return Err(bad(format!("{topic}: more images than when the bag was indexed")));
        };
        let Some(i) = slot else { return Ok(()) };
        let (timestamp, pose) = index.frames[i];
        if timestamp != h.stamp {
            return Err(bad(format!("{topic}: image {images} is not the one indexed (the bag changed?)")));
        }
        waiting.insert(i, Frame { index: i, timestamp, depth, pose, camera, noise: index.noise.clone() });
        while let Some(frame) = waiting.remove(&next) {
            next += 1;
            if visit(frame)?.is_break() {
                // (An error is the readers' only way to stop early; it is not one.)
                stopped = true;
                return Err(Error::Invalid("stopped".into()));
            }
        }
        Ok(())
    });
    if stopped { Ok(()) } else { result }
}

/// The posed depth frames of a bag ([`for_each_frame`]), decoded on a thread of their own while
/// the caller works on the last ones (at most two wait), in frame order. Memory holds a few
/// images, whatever the bag's size.
pub struct BagFrames {
    frames: std::sync::mpsc::IntoIter<Result<Frame>>,
    next: usize,
}

impl BagFrames {
    /// Starts streaming `index`'s frames from `bag`.
    pub fn new(bag: Bag, index: std::sync::Arc<DepthIndex>) -> Self {
        let (send, receive) = std::sync::mpsc::sync_channel(2);
        std::thread::spawn(move || {
            let result = for_each_frame(&bag, &index, |frame| {
                // A closed channel: the caller has stopped reading.
                Ok(match send.send(Ok(frame)) {
                    Ok(()) => std::ops::ControlFlow::Continue(()),
                    Err(_) => std::ops::ControlFlow::Break(()),
                })
            });
            if let Err(e) = result {
                let _ = send.send(Err(e));
            }
        });
        BagFrames { frames: receive.into_iter(), next: 0 }
    }

    /// Frame `i`, reading past the frames before it; `i` must not be below a frame already
    /// returned.
    pub fn frame(&mut self, i: usize) -> Result<Frame> {
        if i < self.next {
            return Err(Error::Invalid(format!("bag frames stream forward: frame {i} asked after {}", self.next)));
        }
        for frame in self.frames.by_ref() {
            let frame = frame?;
            self.next = frame.index + 1;
            if frame.index == i {
                return Ok(frame);
            }
        }
        Err(Error::Invalid(format!("the bag ended before frame {i} (it changed since it was indexed?)")))
    }
}

/// Depth frames of `options.depth_topic` with poses, all in memory (see [`BagFrames`] to
/// stream them); also the images skipped and why.
pub fn bag_frames(bag: &Bag, options: &BagOptions, noise: Option<NoiseModel>) -> Result<(Vec<Frame>, Vec<String>)> {
    let index = depth_index(bag, options, noise, 0)?;
    let mut frames = Vec::new();
    for_each_frame(bag, &index, |frame| {
        // Decoded frames stay in memory (4 bytes a pixel): stop before they outgrow the limit.
        let held = (frames.len() + 1) as f64 * index.camera.pixel_count() as f64 * 4.0;
        crate::limits::check_memory(
            &format!("decoding {} images of {}", frames.len() + 1, options.depth_topic),
            held,
            "map part of the bag (split it, or export-dataset and build with --frames)",
        )?;
        frames.push(frame);
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    Ok((frames, index.skipped))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_wait_only_for_those_stamped_before_them() {
        assert_eq!(most_waiting(&[0, 1, 2, 3]), 0);
        assert_eq!(most_waiting(&[3, 2, 1, 0]), 3);
        assert_eq!(most_waiting(&[1, 0, 3, 2, 4]), 1);
        assert_eq!(most_waiting(&[]), 0);
    }

    #[test]
    fn compressed_mcap_chunks_and_bag_errors() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        for (name, compression) in [("zstd.mcap", mcap::Compression::Zstd), ("lz4.mcap", mcap::Compression::Lz4)] {
            let path = dir.join(name);
            let file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
            let mut w = mcap::WriteOptions::new().compression(Some(compression)).create(file).unwrap();
            let schema = w.add_schema("tf2_msgs/msg/TFMessage", "ros2msg", b"").unwrap();
            let channel = w.add_channel(schema, "/tf", "cdr", &Default::default()).unwrap();
            let mut cdr = msgs::tests::Writer::new();
            cdr.u32(1).header(2, 0, "map").string("base");
            for v in [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0] {
                cdr.f64(v);
            }
            for i in 0..50u64 {
                let header = mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: i as u32,
                    log_time: i,
                    publish_time: i,
                };
                w.write_to_known_channel(&header, &cdr.0).unwrap();
            }
            w.finish().unwrap();
            let bag = Bag::open(&path).unwrap();
            let topics = bag.topics().unwrap();
            assert_eq!((topics[0].topic.as_str(), topics[0].count), ("/tf", 50), "{name}");
            assert_eq!(bag.tf().unwrap().frames(), ["base", "map"]);
            // Cut anywhere, the file reads the messages of its complete records, more the later
            // the cut, or fails with an error naming it; it never panics.
            let bytes = std::fs::read(&path).unwrap();
            let cut = dir.join(format!("cut-{name}"));
            let mut last = 0;
            for at in (0..=bytes.len()).step_by(7).chain([bytes.len()]) {
                std::fs::write(&cut, &bytes[..at]).unwrap();
                match Bag::open(&cut).unwrap().topics() {
                    Ok(t) => {
                        let n = t.first().map_or(0, |t| t.count);
                        assert!(n >= last, "{name} cut at {at}: {n} messages, {last} at a shorter cut");
                        last = n;
                    }
                    Err(e) => assert!(e.to_string().contains("cut-"), "{e}"),
                }
            }
            assert_eq!(last, 50, "{name} whole");
        }
        assert!(Bag::open(&dir.join("missing.mcap")).is_err());
        std::fs::write(dir.join("x.txt"), b"hello").unwrap();
        assert!(Bag::open(&dir.join("x.txt")).unwrap_err().to_string().contains("expected a .mcap, .db3 or .bag"));
        // A ROS 1 bag cut before its first complete record holds nothing (read with a warning);
        // one that does not start like a ROS 1 bag is an error.
        std::fs::write(dir.join("x.bag"), b"#ROSBAG V2.0\ntruncated").unwrap();
        assert!(Bag::open(&dir.join("x.bag")).unwrap().topics().unwrap().is_empty());
        std::fs::write(dir.join("y.bag"), b"#ROSBAG V1.2\nold").unwrap();
        let e = Bag::open(&dir.join("y.bag")).unwrap().topics().unwrap_err().to_string();
        assert!(e.contains("y.bag") && e.contains("#ROSBAG V2.0"), "{e}");
        std::fs::write(dir.join("junk.db3"), b"not sqlite at all").unwrap();
        let bag = Bag::open(&dir.join("junk.db3")).unwrap();
        assert!(bag.topics().unwrap_err().to_string().contains("not a readable ROS 2 sqlite3 bag"));
    }
}
