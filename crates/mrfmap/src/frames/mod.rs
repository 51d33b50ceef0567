//! Frames: what one sensor reading is — a depth image, the camera that took it, where it
//! was (pose) and how it errs (noise model, and its calibration from image pairs).
//!
//! Sources (`crate::source`) produce [`Frame`]s; ray generation (`crate::rays`) turns
//! them into world-space rays for the inference engines.

mod calibration;
mod camera;
mod depth;
mod noise;
mod pose;
mod scan;

use std::sync::Arc;

pub use calibration::{
    BinStats, Calibration, CalibrationOptions, Calibrator, IMPLAUSIBLE, PatchFit, RESERVOIR, weighted_polyfit,
};
pub use camera::{Camera, MAX_PIXELS, MAX_SIDE};
pub use depth::DepthImage;
pub use noise::{Intervals, NoiseModel, PatchModel, Poly, RayLikelihood, STD_FLOOR, TAIL_CUTOFF, upper_tail};
pub use pose::{Pose, Up, keyframes_by_motion, look_at, moved_beyond, pose_from_tum, pose_to_tum};
pub use scan::{Beam, RangeScan};

/// One depth reading ready for integration.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Position of the frame in its dataset (after timestamp association).
    pub index: usize,
    /// Timestamp in seconds.
    pub timestamp: f64,
    /// Z-depth image in metres.
    pub depth: DepthImage,
    /// Camera-to-world transform.
    pub pose: Pose,
    /// Intrinsics; the depth image has the camera's size.
    pub camera: Camera,
    /// Forward noise model, if the sensor has one (the engines that need one fall back to
    /// [`default_noise_model`] otherwise).
    pub noise: Option<Arc<NoiseModel>>,
}

/// The model used when a dataset has no `noise.toml` and none is given: no bias and a std of
/// `0.002 + 0.0035 z^2` metres, close to a Kinect-class structured-light sensor
/// (Khoshelham & Elberink 2012).
pub fn default_noise_model() -> NoiseModel {
    NoiseModel::aggregate(Poly([0.0, 0.0, 0.0]), Poly([0.002, 0.0, 0.0035]))
}
