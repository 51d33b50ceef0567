//! Files a map leaves as (and some it comes back from): PLY voxel centres, OctoMap `.bt` /
//! `.ot` trees, ROS `map_server` 2D grids (PGM + YAML) and, with the `mcap` feature, Foxglove
//! scenes and timelines. Each format is one file here; every writer is atomic.

#[cfg(feature = "mcap")]
mod foxglove;
mod grid2d;
mod octomap;
mod ply;

#[cfg(feature = "mcap")]
pub use foxglove::{SCENE_TOPIC, SceneOptions, SceneSummary, SceneTimeline, write_scene_mcap};
pub use grid2d::{FREE_THRESH, Grid2dFiles, MapServerGrid, OCCUPIED_THRESH, read_map_server, write_map_server};
pub use octomap::{
    OctomapFormat, OctomapLeaf, OctomapSummary, OctomapTree, TREE_DEPTH, decode_octomap, read_octomap, write_octomap,
};
pub use ply::{PlyOptions, PlyVertices, parse_ply, read_ply, write_changes_ply, write_ply};
