//! Outputs: what leaves the library — exported files, evaluation and pictures. Each folder
//! says what it holds: `files/` (formats), `evaluation/` (metrics), `pictures/` (images and
//! plots, with their raster canvas and map renderer); `query.rs` answers a planner. Everything
//! is re-exported here, so callers name `outputs::write_ply`, not its folder.
//!
//! - [`write_ply`] / [`read_ply`]: voxel centres with occupancy (and variance) as PLY;
//! - [`write_map_server`] / [`read_map_server`]: 2D occupancy grids as ROS `map_server` PGM + YAML;
//! - `write_scene_mcap` (cargo feature `mcap`): a Foxglove scene of the occupied voxels, and
//!   `SceneTimeline` a timeline of them as a map is built;
//! - [`write_octomap`] / [`read_octomap`]: OctoMap `.bt` and `.ot` files;
//! - [`query_point`], [`query_segment`], [`query_box`]: what a planner asks (occupancy with
//!   its sigma, the probability that a path or box is free, with a confidence bound);
//! - [`Scorer`] (and the shorthand [`score_view`]): the MRFMap accuracy metric on held-out views;
//! - [`truth_metrics`]: MAE, ROC AUC, inconsistency and sigma-error correlation against an
//!   analytic scene;
//! - [`render_map`] / [`slice_map`]: pictures of a map from a viewpoint, and slices;
//! - `pictures`: accuracy images, per-ray plots, map slices;
//! - [`Canvas`] and [`PlotArea`]: raster figures with text (plots of noise models, scaling
//!   curves) without a font or plotting dependency.

mod evaluation;
mod files;
pub mod pictures;
mod query;

pub use evaluation::{
    AccuracyParams, PeakRule, PixelClass, ProfileStep, RayVerdict, Scorer, TruthMetrics, VISIBILITY_FLOOR, ViewScore,
    VoxelTruth, grid_world_truths, mean_sigma, metrics_of, pearson, roc_auc, score_view, surface_truth, true_occupancy,
    truth_metrics, voxel_truths,
};
pub use files::{
    FREE_THRESH, Grid2dFiles, MapServerGrid, OCCUPIED_THRESH, OctomapFormat, OctomapLeaf, OctomapSummary, OctomapTree,
    PlyOptions, PlyVertices, TREE_DEPTH, decode_octomap, parse_ply, read_map_server, read_octomap, read_ply,
    write_changes_ply, write_map_server, write_octomap, write_ply,
};
#[cfg(feature = "mcap")]
pub use files::{SCENE_TOPIC, SceneOptions, SceneSummary, SceneTimeline, write_scene_mcap};
pub use pictures::{
    Canvas, Colouring, PlotArea, Rgb, Series, Up, View, line_plot, nice_step, render_grid2d, render_map, slice_map,
};
pub use query::{
    BoxAnswer, LazyTiles, LiveEngine, MAX_BOX_VOXELS, MAX_PATH_VOXELS, PointAnswer, QueryOptions, SegmentAnswer,
    VoxelSource, box_voxel_count, check_path, for_each_in_box, query_box, query_point, query_points, query_polyline,
    query_segment, query_segments,
};
