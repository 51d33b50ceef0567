//! A map as a Foxglove scene: an MCAP file with one `foxglove.SceneUpdate` message (JSON
//! encoding, with its JSON schema) that Foxglove's 3D panel draws as cubes.
//!
//! Layout follows the map's sparse bricks: one scene entity per 8x8x8 brick (id `brick/x/y/z`)
//! holding a cube per voxel above the threshold, so a viewer can show, hide or replace parts of
//! a large map brick by brick. Cubes are coloured like `mrfmap view` ([`Colouring`]): by
//! height, occupancy or sigma, all viridis. The frame id is the map's world frame (`map` by
//! default). Built behind the `mcap` cargo feature.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Cursor, Write};
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use crate::atomic_file::{Pending, create_atomic, write_atomic};
use crate::error::{Error, Result};
use crate::map::Map;
use crate::outputs::{Colouring, Up};

/// Topic the scene is published on.
pub const SCENE_TOPIC: &str = "/mrfmap/occupancy";

/// What goes into the scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneOptions {
    /// Voxels above this occupancy become cubes.
    pub threshold: f32,
    /// Cube colours.
    pub colouring: Colouring,
    /// Coordinate frame of the entities.
    pub frame_id: String,
}

impl Default for SceneOptions {
    fn default() -> Self {
        SceneOptions { threshold: 0.5, colouring: Colouring::Occupancy, frame_id: "map".into() }
    }
}

/// Counts of what [`write_scene_mcap`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneSummary {
    /// Entities (bricks with at least one cube).
    pub entities: usize,
    /// Cubes (voxels above the threshold).
    pub cubes: usize,
}

/// JSON schema of the parts of `foxglove.SceneUpdate` written here (the message follows
/// Foxglove's published schema; primitive lists we do not use are written empty).
fn schema() -> Value {
    let num = json!({"type": "number"});
    let vec3 = json!({"type": "object", "properties": {"x": num, "y": num, "z": num}});
    let quat = json!({"type": "object", "properties": {"x": num, "y": num, "z": num, "w": num}});
    let color = json!({"type": "object", "properties": {"r": num, "g": num, "b": num, "a": num}});
    let time = json!({"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}});
    let cube = json!({"type": "object", "properties": {
        "pose": {"type": "object", "properties": {"position": vec3, "orientation": quat}},
        "size": vec3, "color": color,
    }});
    let list = json!({"type": "array", "items": {"type": "object"}});
    json!({
        "title": "foxglove.SceneUpdate",
        "description": "An update to the entities displayed in a 3D scene",
        "type": "object",
        "properties": {
            "deletions": list,
            "entities": {"type": "array", "items": {"type": "object", "properties": {
                "timestamp": time, "frame_id": {"type": "string"}, "id": {"type": "string"},
                "lifetime": time, "frame_locked": {"type": "boolean"}, "metadata": list,
                "arrows": list, "cubes": {"type": "array", "items": cube}, "spheres": list,
                "cylinders": list, "lines": list, "triangles": list, "texts": list, "models": list,
            }}},
        },
    })
}

/// One scene entity per brick of `map` with cubes, in brick order: its id, the entity (stamped
/// `stamp`) and its cube count.
fn brick_entities(map: &Map, options: &SceneOptions, stamp: &Value) -> Vec<(String, Value, usize)> {
    let r = map.resolution();
    let z_range = map.bounds().map_or((0.0, 1.0), |(lo, hi)| (lo[2], hi[2]));
    let zero = json!({"sec": 0, "nsec": 0});
    let mut entities = Vec::new();
    for bk in map.voxels.sorted_brick_keys() {
        let brick = map.voxels.brick(bk).expect("own key");
        let cubes: Vec<Value> = brick
            .iter()
            .filter(|(_, v)| v.occupancy > options.threshold)
            .map(|(slot, v)| {
                let key = bk.voxel(slot);
                let c = key.center(r);
                let [red, green, blue] = options
                    .colouring
                    .colour(map, key, v, (Up::Z, z_range), options.threshold)
                    .map(|x| x as f64 / 255.0);
                json!({
                    "pose": {"position": {"x": c[0], "y": c[1], "z": c[2]},
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                    "size": {"x": r, "y": r, "z": r},
                    "color": {"r": red, "g": green, "b": blue, "a": 1.0},
                })
            })
            .collect();
        if cubes.is_empty() {
            continue;
        }
        let [x, y, z] = bk.0;
        let (id, count) = (format!("brick/{x}/{y}/{z}"), cubes.len());
        let entity = json!({
            "timestamp": stamp, "frame_id": options.frame_id, "id": id,
            "lifetime": zero, "frame_locked": false, "metadata": [],
            "arrows": [], "cubes": cubes, "spheres": [], "cylinders": [], "lines": [],
            "triangles": [], "texts": [], "models": [],
        });
        entities.push((id, entity, count));
    }
    entities
}

/// The scene message for `map`.
fn scene(map: &Map, options: &SceneOptions) -> (Value, SceneSummary) {
    let entities = brick_entities(map, options, &json!({"sec": 0, "nsec": 0}));
    let summary = SceneSummary { entities: entities.len(), cubes: entities.iter().map(|e| e.2).sum() };
    let entities: Vec<Value> = entities.into_iter().map(|e| e.1).collect();
    (json!({"deletions": [], "entities": entities}), summary)
}

/// The MCAP writer of a scene file, its schema and channel written.
fn scene_writer<W: Write + std::io::Seek>(
    out: W,
    map: &Map,
) -> std::result::Result<(mcap::Writer<W>, u16), mcap::McapError> {
    let mut out = mcap::Writer::new(out)?;
    let schema = out.add_schema("foxglove.SceneUpdate", "jsonschema", schema().to_string().as_bytes())?;
    let mut metadata = BTreeMap::new();
    metadata.insert("resolution".to_string(), map.resolution().to_string());
    metadata.insert("engine".to_string(), map.engine.to_string());
    let channel = out.add_channel(schema, SCENE_TOPIC, "json", &metadata)?;
    Ok((out, channel))
}

/// Checks that a scene of `map`'s cubes fits in memory (a cube is about 1 KiB as a JSON value
/// and again as text), before building them.
fn check_scene(map: &Map, options: &SceneOptions) -> Result<()> {
    let cubes = map.voxels.iter().filter(|(_, v)| v.occupancy > options.threshold).count();
    crate::limits::check_memory(
        &format!("a Foxglove scene of {cubes} cubes"),
        cubes as f64 * 2048.0,
        "crop the map or raise --threshold",
    )
}

/// A Foxglove timeline of a map as it is built: one `SceneUpdate` per snapshot at its log
/// time, holding the bricks whose cubes changed since the last snapshot and deleting the
/// bricks left without any, so a viewer scrubbing the timeline sees the map as it was.
/// Written as it goes into a temporary file; [`SceneTimeline::finish`] puts it in place.
pub struct SceneTimeline {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    pending: Pending,
    channel: u16,
    options: SceneOptions,
    /// Per entity shown, a hash of its cubes.
    shown: BTreeMap<String, u64>,
    sequence: u32,
}

impl SceneTimeline {
    /// Starts the timeline file `path` for maps like `first` (its resolution and engine go into
    /// the channel's metadata).
    pub fn create(path: &Path, first: &Map, options: SceneOptions) -> Result<Self> {
        let (file, pending) = create_atomic(path)?;
        let (writer, channel) =
            scene_writer(file, first).map_err(|e| Error::file(path, format!("writing MCAP: {e}")))?;
        let shown = BTreeMap::new();
        Ok(SceneTimeline { path: path.to_path_buf(), writer, pending, channel, options, shown, sequence: 0 })
    }

    /// Adds `map` as it was at `time` (seconds; log times must not decrease).
    pub fn add(&mut self, map: &Map, time: f64) -> Result<SceneSummary> {
        check_scene(map, &self.options)?;
        let ns = (time.max(0.0) * 1e9) as u64;
        let stamp = json!({"sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000});
        let entities = brick_entities(map, &self.options, &stamp);
        let summary = SceneSummary { entities: entities.len(), cubes: entities.iter().map(|e| e.2).sum() };
        let mut now = BTreeMap::new();
        let mut changed = Vec::new();
        for (id, entity, _) in entities {
            let mut h = std::hash::DefaultHasher::new();
            std::hash::Hash::hash(&entity["cubes"].to_string(), &mut h);
            let hash = std::hash::Hasher::finish(&h);
            if self.shown.get(&id) != Some(&hash) {
                changed.push(entity);
            }
            now.insert(id, hash);
        }
        let deletions: Vec<Value> = (self.shown.keys())
            .filter(|id| !now.contains_key(*id))
            .map(|id| json!({"timestamp": stamp, "type": 0, "id": id}))
            .collect();
        self.shown = now;
        let message = json!({"deletions": deletions, "entities": changed}).to_string();
        let header = mcap::records::MessageHeader {
            channel_id: self.channel,
            sequence: self.sequence,
            log_time: ns,
            publish_time: ns,
        };
        self.sequence += 1;
        (self.writer.write_to_known_channel(&header, message.as_bytes()))
            .map_err(|e| Error::file(&self.path, format!("writing MCAP: {e}")))?;
        Ok(summary)
    }

    /// Finishes the file and puts it in place; returns the snapshots written.
    pub fn finish(mut self) -> Result<u32> {
        let bad = |e: mcap::McapError| Error::file(&self.path, format!("writing MCAP: {e}"));
        self.writer.finish().map_err(bad)?;
        let file = self.writer.into_inner();
        self.pending.commit(file)?;
        Ok(self.sequence)
    }
}

/// Writes `map` as an MCAP file Foxglove opens: one `foxglove.SceneUpdate` on
/// [`SCENE_TOPIC`] (atomically: temp file + rename).
pub fn write_scene_mcap(map: &Map, path: &Path, options: &SceneOptions) -> Result<SceneSummary> {
    check_scene(map, options)?;
    let (message, summary) = scene(map, options);
    let encode = || -> std::result::Result<Vec<u8>, mcap::McapError> {
        let (mut out, channel) = scene_writer(Cursor::new(Vec::new()), map)?;
        let header = mcap::records::MessageHeader { channel_id: channel, sequence: 0, log_time: 0, publish_time: 0 };
        out.write_to_known_channel(&header, message.to_string().as_bytes())?;
        out.finish()?;
        Ok(out.into_inner().into_inner())
    };
    let bytes = encode().map_err(|e| Error::file(path, format!("writing MCAP: {e}")))?;
    write_atomic(path, |w| w.write_all(&bytes))?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::EngineKind;
    use crate::map::{MapVoxel, VoxelKey};

    #[test]
    fn a_timeline_sends_what_changed_and_deletes_what_emptied() {
        let map_of = |voxels: &[([i32; 3], f32)]| {
            let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
            for &(k, p) in voxels {
                map.voxels.insert(VoxelKey(k), MapVoxel { occupancy: p, variance: 0.0 });
            }
            map
        };
        // Brick 0/0/0 appears, brick 1/0/0 joins while 0/0/0 stays the same, then 0/0/0 empties.
        let steps = [
            map_of(&[([0, 0, 0], 0.9)]),
            map_of(&[([0, 0, 0], 0.9), ([9, 0, 0], 0.8)]),
            map_of(&[([0, 0, 0], 0.3), ([9, 0, 0], 0.8), ([9, 1, 0], 0.7)]),
        ];
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let path = dir.join("t.mcap");
        let mut timeline = SceneTimeline::create(&path, &steps[0], SceneOptions::default()).unwrap();
        for (k, map) in steps.iter().enumerate() {
            timeline.add(map, 10.0 + k as f64).unwrap();
        }
        assert!(!path.exists(), "the file appears when finished");
        assert_eq!(timeline.finish().unwrap(), 3);
        let bytes = std::fs::read(&path).unwrap();
        let messages: Vec<_> =
            mcap::MessageStream::new(&bytes).unwrap().collect::<std::result::Result<_, _>>().unwrap();
        let times: Vec<u64> = messages.iter().map(|m| m.log_time).collect();
        assert_eq!(times, [10_000_000_000, 11_000_000_000, 12_000_000_000]);
        let ids = |m: &mcap::Message, what: &str| -> Vec<String> {
            let v: Value = serde_json::from_slice(&m.data).unwrap();
            v[what].as_array().unwrap().iter().map(|e| e["id"].as_str().unwrap().to_string()).collect()
        };
        assert_eq!(ids(&messages[0], "entities"), ["brick/0/0/0"]);
        assert_eq!(ids(&messages[1], "entities"), ["brick/1/0/0"], "only what changed");
        assert_eq!(ids(&messages[2], "entities"), ["brick/1/0/0"]);
        assert_eq!(ids(&messages[2], "deletions"), ["brick/0/0/0"]);
        let v: Value = serde_json::from_slice(&messages[2].data).unwrap();
        assert_eq!(v["entities"][0]["cubes"].as_array().unwrap().len(), 2);
        assert_eq!(v["entities"][0]["timestamp"]["sec"], 12);
        // Dropped before it is finished, a timeline leaves nothing behind.
        let other = dir.join("u.mcap");
        drop(SceneTimeline::create(&other, &steps[0], SceneOptions::default()).unwrap());
        assert_eq!(std::fs::read_dir(dir).unwrap().count(), 1);
    }

    #[test]
    fn the_scene_reads_back_as_one_scene_update_with_a_cube_per_occupied_voxel() {
        let mut map = Map::new(EngineKind::LogOdds, 0.1).unwrap();
        for (k, p) in [([0, 0, 0], 0.9), ([1, 0, 0], 0.2), ([9, 0, 0], 0.7), ([-1, -1, 3], 0.99)] {
            map.voxels.insert(VoxelKey(k), MapVoxel { occupancy: p, variance: 0.0 });
        }
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let path = dir.join("m.mcap");
        let summary = write_scene_mcap(&map, &path, &SceneOptions::default()).unwrap();
        assert_eq!(summary, SceneSummary { entities: 3, cubes: 3 });
        let bytes = std::fs::read(&path).unwrap();
        let messages: Vec<_> =
            mcap::MessageStream::new(&bytes).unwrap().collect::<std::result::Result<_, _>>().unwrap();
        assert_eq!(messages.len(), 1);
        let m = &messages[0];
        assert_eq!((m.channel.topic.as_str(), m.channel.message_encoding.as_str()), (SCENE_TOPIC, "json"));
        let schema = m.channel.schema.as_ref().unwrap();
        assert_eq!((schema.name.as_str(), schema.encoding.as_str()), ("foxglove.SceneUpdate", "jsonschema"));
        let v: Value = serde_json::from_slice(&m.data).unwrap();
        let entities = v["entities"].as_array().unwrap();
        let ids: Vec<&str> = entities.iter().map(|e| e["id"].as_str().unwrap()).collect();
        assert_eq!(ids, ["brick/-1/-1/0", "brick/0/0/0", "brick/1/0/0"]);
        let cube = &entities[1]["cubes"][0];
        assert!((cube["pose"]["position"]["x"].as_f64().unwrap() - 0.05).abs() < 1e-12);
        assert_eq!(cube["size"]["z"].as_f64().unwrap(), 0.1);
        let colour = cube["color"]["g"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&colour));
        assert_eq!(entities[1]["frame_id"], "map");
    }
}
