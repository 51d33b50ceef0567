//! Robot recordings: ROS 2 bags in MCAP or sqlite3 and ROS 1 bags, read without ROS (cargo
//! feature `bags`).
//!
//! A bag is one `.mcap`, `.db3` or ROS 1 `.bag` file, or a bag folder (`metadata.yaml` beside
//! one or more such files, read in name order). Messages are decoded by hand from CDR ([`msgs`]): depth images
//! (`sensor_msgs/Image`, 16UC1 millimetres or 32FC1 metres), `sensor_msgs/CameraInfo`,
//! `tf2_msgs/TFMessage` on `/tf` and `/tf_static`, `geometry_msgs/PoseStamped`,
//! `nav_msgs/Odometry`, and `sensor_msgs/LaserScan` and `sensor_msgs/PointCloud2` as range scans
//! ([`bag_scans`]). [`for_each_frame`] turns a depth topic into [`Frame`](crate::frames::Frame)s: intrinsics from
//! the camera-info topic (by default the `camera_info` beside the image topic, the ROS
//! convention), each image's pose in a fixed frame from the transform tree ([`tf`]) or from a
//! pose topic, interpolated at the image's stamp. The ROS optical frame (z forward, x right,
//! y down) is mrfmap's camera frame, so poses are used as they are. Images without a pose
//! within the allowed gap are reported and skipped.
//!
//! Every format is read forward a chunk or a row at a time ([`Bag::for_each`]), so a bag of
//! any size streams, and read once: each image waits for the poses logged after it and is
//! then decoded and handed on, in stamp order ([`for_each_frame`], on a thread of its own
//! [`DepthStream`]; [`bag_frames`] collects them all). Memory holds a few images and the
//! last seconds of transforms.

pub mod cdr;
mod mcap_reader;
pub mod msgs;
mod ros1;
mod stream;
pub mod tf;

pub use cdr::Encoding;
pub use stream::{DepthStream, JITTER, KEEP_POSES, StreamReport, WINDOW, bag_frames, bag_scans, for_each_frame};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

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

#[cfg(test)]
mod tests {
    use super::*;

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
