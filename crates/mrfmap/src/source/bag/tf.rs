//! A transform buffer, as ROS's tf2 keeps one: the tree of frames from `/tf` and `/tf_static`,
//! each dynamic edge a time series, looked up at an image's stamp with interpolation (linear in
//! translation, slerp in rotation). A stamp outside an edge's series, or between two samples
//! farther apart than the allowed gap, has no transform: the image is skipped, not guessed.

use std::collections::HashMap;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};

use super::msgs::Transform;
use crate::frames::Pose;

/// Samples of one moving transform, kept sorted by time as they come (in order, usually: a
/// sample is appended; one out of order is put in its place).
#[derive(Clone, Debug, Default)]
pub struct Series {
    samples: Vec<(f64, Pose)>,
}

impl Series {
    /// Adds a sample, in any order.
    pub fn push(&mut self, stamp: f64, t: &Transform) {
        let at = self.samples.partition_point(|s| s.0 <= stamp);
        self.samples.insert(at, (stamp, pose_of(t)));
    }

    /// The latest sample's time.
    pub fn latest(&self) -> Option<f64> {
        self.samples.last().map(|s| s.0)
    }

    /// Lets go of the samples no lookup at `t` or later needs (all before the last one at or
    /// before `t`), once they are at least half of the samples held (so a recording's series
    /// stays short, at a cost per sample that does not grow with it).
    pub fn forget_before(&mut self, t: f64) {
        let needed = self.samples.partition_point(|s| s.0 <= t).saturating_sub(1);
        if needed > 0 && 2 * needed >= self.samples.len() {
            self.samples.drain(..needed);
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True without samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The transform at `t`, interpolated between the samples around it when they are at most
    /// `max_gap` apart.
    pub fn at(&self, t: f64, max_gap: f64) -> Result<Pose, String> {
        let s = &self.samples;
        let (Some(first), Some(last)) = (s.first(), s.last()) else { return Err("no samples".into()) };
        if t < first.0 || t > last.0 {
            return Err(format!("stamp {t:.3} s is outside the samples ({:.3} to {:.3} s)", first.0, last.0));
        }
        let i = s.partition_point(|x| x.0 < t);
        if s[i].0 == t {
            return Ok(s[i].1);
        }
        let (a, b) = (&s[i - 1], &s[i]);
        if b.0 - a.0 > max_gap {
            return Err(format!("the nearest samples are {:.3} s apart, more than {max_gap} s", b.0 - a.0));
        }
        let f = (t - a.0) / (b.0 - a.0);
        let tr = a.1.translation.vector.lerp(&b.1.translation.vector, f);
        let rot = a.1.rotation.try_slerp(&b.1.rotation, f, 1e-9).unwrap_or(a.1.rotation);
        Ok(Pose::from_parts(Translation3::from(tr), rot))
    }
}

/// A message's transform as a pose (the quaternion normalised).
pub fn pose_of(t: &Transform) -> Pose {
    let [x, y, z, w] = t.rotation;
    let [tx, ty, tz] = t.translation;
    Pose::from_parts(Translation3::new(tx, ty, tz), UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)))
}

/// One edge of the tree: the child's pose in its parent.
#[derive(Clone, Debug)]
struct Edge {
    parent: String,
    fixed: Option<Pose>,
    series: Series,
}

/// The frame tree.
#[derive(Clone, Debug, Default)]
pub struct TfBuffer {
    edges: HashMap<String, Edge>,
}

impl TfBuffer {
    /// Adds `child`'s pose in `parent` at `stamp` (`/tf`), or for all time (`/tf_static`).
    /// A child with a new parent replaces the old edge (tf2 does the same).
    pub fn insert(&mut self, parent: &str, child: &str, stamp: f64, t: &Transform, is_static: bool) {
        let e = self.edges.entry(child.to_string()).or_insert_with(|| Edge {
            parent: parent.to_string(),
            fixed: None,
            series: Series::default(),
        });
        if e.parent != parent {
            *e = Edge { parent: parent.to_string(), fixed: None, series: Series::default() };
        }
        if is_static {
            e.fixed = Some(pose_of(t));
        } else {
            e.series.push(stamp, t);
        }
    }

    /// Lets go of the samples no lookup at `t` or later needs ([`Series::forget_before`]).
    pub fn forget_before(&mut self, t: f64) {
        self.edges.values_mut().for_each(|e| e.series.forget_before(t));
    }

    /// The time up to which every moving transform is known: the earliest of their latest
    /// samples (infinite when none moves; `None` when the tree is empty).
    pub fn known_until(&self) -> Option<f64> {
        if self.edges.is_empty() {
            return None;
        }
        let moving = self.edges.values().filter(|e| e.fixed.is_none()).filter_map(|e| e.series.latest());
        Some(moving.fold(f64::INFINITY, f64::min))
    }

    /// All frames named in the tree.
    pub fn frames(&self) -> Vec<String> {
        let mut f: Vec<String> = self.edges.iter().flat_map(|(c, e)| [c.clone(), e.parent.clone()]).collect();
        f.sort();
        f.dedup();
        f
    }

    /// The chain from `frame` up to its root: `(frame, pose in parent)` per step.
    fn chain<'a>(&'a self, frame: &'a str) -> Vec<(&'a str, &'a Edge)> {
        let mut out = Vec::new();
        let mut f = frame;
        while let Some(e) = self.edges.get(f) {
            if out.len() > self.edges.len() {
                break; // a cycle: tf2 refuses those; so do lookups through it
            }
            out.push((f, e));
            f = &e.parent;
        }
        out
    }

    /// The pose of `frame` in `fixed` at `t` (`fixed <- frame`).
    pub fn lookup(&self, fixed: &str, frame: &str, t: f64, max_gap: f64) -> Result<Pose, String> {
        if fixed == frame {
            return Ok(Pose::identity());
        }
        let (up, down) = (self.chain(frame), self.chain(fixed));
        let root = |c: &[(&str, &Edge)], f: &str| c.last().map_or(f.to_string(), |(_, e)| e.parent.clone());
        if root(&up, frame) != root(&down, fixed) {
            return Err(format!("the TF tree does not connect {fixed:?} and {frame:?}"));
        }
        let edge_pose = |name: &str, e: &Edge| -> Result<Pose, String> {
            match e.fixed {
                Some(p) => Ok(p),
                None => e.series.at(t, max_gap).map_err(|m| format!("{} -> {name}: {m}", e.parent)),
            }
        };
        // Pose of each frame in the common root.
        let in_root = |chain: &[(&str, &Edge)]| -> Result<Pose, String> {
            let mut p = Pose::identity();
            for (name, e) in chain.iter().rev() {
                p *= edge_pose(name, e)?;
            }
            Ok(p)
        };
        Ok(in_root(&down)?.inverse() * in_root(&up)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tr(x: f64, yaw: f64) -> Transform {
        Transform { translation: [x, 0.0, 0.0], rotation: [0.0, 0.0, (yaw / 2.0).sin(), (yaw / 2.0).cos()] }
    }

    #[test]
    fn chains_interpolation_and_refusals() {
        let mut tf = TfBuffer::default();
        tf.insert("map", "odom", 0.0, &tr(1.0, 0.0), true);
        tf.insert("odom", "base", 1.0, &tr(0.0, 0.0), false);
        tf.insert("odom", "base", 2.0, &tr(2.0, std::f64::consts::FRAC_PI_2), false);
        tf.insert("base", "camera", 0.0, &tr(0.5, 0.0), true);
        assert_eq!(tf.known_until(), Some(2.0));
        // Halfway: base at x = 1 turned 45 degrees; the camera 0.5 m ahead of it.
        let p = tf.lookup("map", "camera", 1.5, 1.0).unwrap();
        let h = std::f64::consts::FRAC_PI_4;
        let expect = [1.0 + 1.0 + 0.5 * h.cos(), 0.5 * h.sin(), 0.0];
        for (got, want) in p.translation.vector.iter().zip(expect) {
            assert!((got - want).abs() < 1e-12, "{p:?}");
        }
        assert!((p.rotation.angle() - h).abs() < 1e-12);
        // The inverse direction, and the identity.
        let q = tf.lookup("camera", "map", 1.5, 1.0).unwrap();
        assert!(((p * q).translation.vector.norm()) < 1e-12);
        assert_eq!(tf.lookup("base", "base", 9.0, 1.0).unwrap(), Pose::identity());
        // Outside the samples, too far apart, not connected.
        assert!(tf.lookup("map", "camera", 2.5, 1.0).unwrap_err().contains("outside"));
        assert!(tf.lookup("map", "camera", 1.5, 0.5).unwrap_err().contains("apart"));
        assert!(tf.lookup("map", "laser", 1.5, 1.0).unwrap_err().contains("does not connect"));
        assert_eq!(tf.frames(), ["base", "camera", "map", "odom"]);
    }

    #[test]
    fn series_stay_sorted_and_short() {
        let mut s = Series::default();
        for t in [1.0, 3.0, 2.0, 4.0, 0.5] {
            s.push(t, &tr(t, 0.0));
        }
        assert_eq!(s.samples.iter().map(|x| x.0).collect::<Vec<_>>(), [0.5, 1.0, 2.0, 3.0, 4.0]);
        assert!((s.at(2.5, 1.0).unwrap().translation.x - 2.5).abs() < 1e-12, "out-of-order samples interpolate");
        s.forget_before(3.5);
        // The sample at 3 still answers 3.5; the ones before it are gone.
        assert_eq!(s.samples.iter().map(|x| x.0).collect::<Vec<_>>(), [3.0, 4.0]);
        assert!((s.at(3.5, 1.0).unwrap().translation.x - 3.5).abs() < 1e-12);
        s.forget_before(3.9);
        assert_eq!(s.len(), 2, "the sample at 3 still answers 3.9");
    }
}
