//! Camera poses: camera-to-world rigid transforms `T_wc` (docs/ALGORITHMS.md section 1).

use nalgebra::{Isometry3, Matrix3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};

/// A camera-to-world transform.
pub type Pose = Isometry3<f64>;

/// How far a quaternion's norm may stray from 1 before we warn (files with 6 digits are ~1e-6 off).
const UNIT_TOLERANCE: f64 = 1e-4;

/// A pose from TUM's `tx ty tz qx qy qz qw`.
///
/// Errors on NaN or infinite values and on a zero quaternion. A non-unit quaternion is
/// normalised; the returned flag says whether its norm was off by more than 1e-4, so the
/// caller can warn, naming the file and line.
///
/// ```
/// let (pose, fixed) = mrfmap::frames::pose_from_tum([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 2.0]).unwrap();
/// assert!(fixed);
/// assert_eq!(pose.translation.vector.x, 1.0);
/// ```
pub fn pose_from_tum(t: [f64; 3], q_xyzw: [f64; 4]) -> Result<(Pose, bool), String> {
    if t.iter().chain(q_xyzw.iter()).any(|v| !v.is_finite()) {
        return Err("pose has a NaN or infinite value".into());
    }
    let [qx, qy, qz, qw] = q_xyzw;
    let q = Quaternion::new(qw, qx, qy, qz); // nalgebra takes w first
    let norm = q.norm();
    if norm < 1e-9 {
        return Err("pose quaternion is zero".into());
    }
    let rotation = UnitQuaternion::from_quaternion(q);
    Ok((Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), rotation), (norm - 1.0).abs() > UNIT_TOLERANCE))
}

/// The TUM fields `[tx, ty, tz, qx, qy, qz, qw]` of a pose.
pub fn pose_to_tum(pose: &Pose) -> [f64; 7] {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// Whether `pose` has moved more than `translation` metres or turned more than `rotation`
/// radians (the angle of the relative rotation) from `reference`.
pub fn moved_beyond(reference: &Pose, pose: &Pose, translation: f64, rotation: f64) -> bool {
    let d = reference.inverse() * pose;
    d.translation.vector.norm() > translation || d.rotation.angle() > rotation
}

/// The MRFMap paper's keyframe heuristic (its sec. V-B2): the first pose, then every pose that
/// [`moved_beyond`] the thresholds from the *last* keyframe. Returns the keyframes' indices.
///
/// ```
/// use mrfmap::frames::{Pose, keyframes_by_motion};
/// let poses: Vec<Pose> = (0..10).map(|i| Pose::translation(0.04 * i as f64, 0.0, 0.0)).collect();
/// assert_eq!(keyframes_by_motion(&poses, 0.1, 0.1), vec![0, 3, 6, 9]);
/// ```
pub fn keyframes_by_motion<'a>(
    poses: impl IntoIterator<Item = &'a Pose>,
    translation: f64,
    rotation: f64,
) -> Vec<usize> {
    let mut keyframes = Vec::new();
    let mut last: Option<&Pose> = None;
    for (i, pose) in poses.into_iter().enumerate() {
        if last.is_none_or(|l| moved_beyond(l, pose, translation, rotation)) {
            keyframes.push(i);
            last = Some(pose);
        }
    }
    keyframes
}

/// A camera at `eye` looking at `target`, world up `+z` (the scene-file convention):
/// `z_cam = normalize(target - eye)`, `x_cam = normalize(z_cam x up)`, `y_cam = z_cam x x_cam`.
///
/// Fails when the view direction is vertical (no unique right vector) or `eye == target`.
pub fn look_at(eye: Vector3<f64>, target: Vector3<f64>) -> Result<Pose, String> {
    let forward = target - eye;
    if forward.norm() < 1e-12 {
        return Err("eye and target coincide".into());
    }
    let z = forward.normalize();
    let right = z.cross(&Vector3::z());
    if right.norm() < 1e-9 {
        return Err("view direction is vertical: up vector +z is ambiguous".into());
    }
    let x = right.normalize();
    let y = z.cross(&x);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Ok(Isometry3::from_parts(Translation3::from(eye), UnitQuaternion::from_rotation_matrix(&rotation)))
}

/// A world's up axis (against gravity): `+x`, `-x`, `+y`, `-y`, `+z` or `-z`. ROS worlds are
/// `+z`; ICL-NUIM, 7-Scenes and Redwood are `+y`. A dataset may declare it (`world.toml`); maps
/// built from it record it, and pictures stand the map on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Up {
    /// 0, 1, 2 for x, y, z.
    pub axis: usize,
    /// Up is the axis's negative direction.
    pub negative: bool,
}

impl Up {
    /// `+z`, the default: ROS and most robot worlds.
    pub const Z: Up = Up { axis: 2, negative: false };

    /// The unit vector pointing up.
    pub fn vector(self) -> [f64; 3] {
        let mut v = [0.0; 3];
        v[self.axis] = if self.negative { -1.0 } else { 1.0 };
        v
    }

    /// Height of world point `p`.
    pub fn height(self, p: [f64; 3]) -> f64 {
        if self.negative { -p[self.axis] } else { p[self.axis] }
    }

    /// The range of heights over the box `lo`..`hi`.
    pub fn heights(self, lo: [f64; 3], hi: [f64; 3]) -> (f64, f64) {
        let (a, b) = (self.height(lo), self.height(hi));
        (a.min(b), a.max(b))
    }
}

impl std::str::FromStr for Up {
    type Err = crate::error::Error;

    /// `+x`, `-x`, `+y`, `-y`, `+z`, `-z` (a bare axis is its positive direction).
    fn from_str(s: &str) -> crate::error::Result<Self> {
        let (negative, axis) = match s.trim().strip_prefix('-') {
            Some(rest) => (true, rest),
            None => (false, s.trim().strip_prefix('+').unwrap_or(s.trim())),
        };
        let axis = match axis {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            _ => return Err(crate::error::Error::Invalid(format!("up axis {s:?}: use +x, -x, +y, -y, +z or -z"))),
        };
        Ok(Up { axis, negative })
    }
}

impl std::fmt::Display for Up {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}{}", if self.negative { '-' } else { '+' }, ["x", "y", "z"][self.axis])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keyframes_follow_the_last_keyframe_in_translation_and_rotation() {
        // Turning in place by 0.04 rad a frame, then sliding 0.04 m a frame.
        let mut poses: Vec<Pose> = (0..8).map(|i| Pose::rotation(Vector3::z() * (0.04 * i as f64))).collect();
        let turned = poses[7];
        poses.extend((1..8).map(|i| Pose::translation(0.04 * i as f64, 0.0, 0.0) * turned));
        // 0.1 rad: frames 0, 3, 6; then more than 0.1 m from the last keyframe: frame 10 (0.12 m
        // from frame 6's place, which frame 7 shares) and 13.
        assert_eq!(keyframes_by_motion(&poses, 0.1, 0.1), vec![0, 3, 6, 10, 13]);
        // Relative to every keyframe so far instead, a path that comes back is not new.
        let back: Vec<Pose> = [0.0, 0.3, 0.05].iter().map(|&x| Pose::translation(x, 0.0, 0.0)).collect();
        assert_eq!(keyframes_by_motion(&back, 0.1, 0.1), vec![0, 1, 2]);
        assert!(!moved_beyond(&back[0], &back[2], 0.1, 0.1));
    }

    #[test]
    fn tum_round_trip() {
        let q = [0.1, -0.2, 0.3, 0.9];
        let n = (0.01f64 + 0.04 + 0.09 + 0.81).sqrt();
        let (pose, fixed) = pose_from_tum([1.0, 2.0, 3.0], q).unwrap();
        assert!(fixed);
        let back = pose_to_tum(&pose);
        for k in 0..4 {
            assert!((back[3 + k] - q[k] / n).abs() < 1e-12);
        }
    }

    #[test]
    fn nan_rejected() {
        assert!(pose_from_tum([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).is_err());
        assert!(pose_from_tum([0.0; 3], [0.0; 4]).is_err());
    }

    #[test]
    fn look_at_axes() {
        let pose = look_at(Vector3::new(3.6, 2.0, 1.4), Vector3::new(2.0, 2.0, 1.4)).unwrap();
        let r = pose.rotation.to_rotation_matrix();
        let fwd = r * Vector3::z();
        let right = r * Vector3::x();
        let down = r * Vector3::y();
        assert!((fwd - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!((right - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
        assert!((down - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        assert!(look_at(Vector3::zeros(), Vector3::new(0.0, 0.0, -1.0)).is_err());
    }
}
