//! The transforms the node reads: the sensor's mounting on the base (`/tf_static`, else
//! `ros2.toml`) and the robot's odometry (`odom -> base` on `/tf`), kept for the scans'
//! stamps.

use std::collections::{HashMap, VecDeque};

use kfmap_geometry::geometry::Pose;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::msgs::TransformStamped;

/// Odometry transforms kept (at 100 Hz, 5 s).
const ODOM_HISTORY: usize = 500;
/// An odometry transform is used for a scan stamped at most this long after it.
const ODOM_EXTRAPOLATION_S: f64 = 0.25;
/// Links followed from the base to the sensor frame at most.
const MAX_CHAIN: usize = 8;

/// `"x y z roll pitch yaw"` (metres, degrees) as `T_base_sensor`.
pub fn parse_mounting(text: &str) -> Option<Pose> {
    let values: Vec<f64> = text
        .split_whitespace()
        .map(|v| v.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()?;
    let [x, y, z, roll, pitch, yaw] = <[f64; 6]>::try_from(values).ok()?;
    Some(Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), yaw.to_radians()),
    ))
}

/// `T_base_sensor` for a cloud in `frame`: identity when it is the base frame, else the
/// `/tf_static` chain, else `configured` (`[frames] sensor-mounting`, parsed once);
/// `None` while neither knows it. Never guessed: a LiDAR 0.9 m up taken for the base
/// would put every published pose 0.9 m off.
pub fn sensor_mounting(
    frames: &Frames,
    base: &str,
    frame: &str,
    configured: Option<Pose>,
) -> Option<Pose> {
    frames.mounting(base, frame).or(configured)
}

/// What the node knows of the frames.
#[derive(Debug, Default)]
pub struct Frames {
    /// Static transforms, `T_parent_child` by (parent, child).
    fixed: HashMap<(String, String), Pose>,
    /// `odom -> base` transforms, oldest first: (stamp, `T_odom_base`).
    odometry: VecDeque<(f64, Pose)>,
}

impl Frames {
    /// Reads a `/tf_static` message's transforms (malformed ones are skipped and
    /// counted).
    pub fn add_static(&mut self, transforms: &[TransformStamped]) -> usize {
        let mut skipped = 0;
        for t in transforms {
            match t.transform.pose() {
                Some(pose) if !t.header.frame_id.is_empty() && !t.child_frame_id.is_empty() => {
                    self.fixed
                        .insert((trim(&t.header.frame_id), trim(&t.child_frame_id)), pose);
                }
                _ => skipped += 1,
            }
        }
        skipped
    }

    /// Reads a `/tf` message: keeps its `odom -> base` transforms.
    pub fn add_dynamic(&mut self, transforms: &[TransformStamped], odom: &str, base: &str) {
        for t in transforms {
            if trim(&t.header.frame_id) != trim(odom) || trim(&t.child_frame_id) != trim(base) {
                continue;
            }
            let Some(pose) = t.transform.pose() else {
                continue;
            };
            let stamp = t.header.stamp.seconds();
            // Out of order or repeated stamps are dropped: interpolation needs order.
            if self.odometry.back().is_some_and(|(s, _)| *s >= stamp) {
                continue;
            }
            if self.odometry.len() == ODOM_HISTORY {
                self.odometry.pop_front();
            }
            self.odometry.push_back((stamp, pose));
        }
    }

    /// `T_base_sensor` from the static transforms: the chain from `base` down to
    /// `sensor`, if one is known.
    pub fn mounting(&self, base: &str, sensor: &str) -> Option<Pose> {
        let (base, sensor) = (trim(base), trim(sensor));
        if base == sensor {
            return Some(Pose::identity());
        }
        // Breadth first from the base over parent -> child links.
        let mut frontier = vec![(base.clone(), Pose::identity())];
        for _ in 0..MAX_CHAIN {
            let mut next = Vec::new();
            for (frame, pose) in &frontier {
                for ((parent, child), link) in &self.fixed {
                    if parent == frame {
                        let reached = pose * link;
                        if *child == sensor {
                            return Some(reached);
                        }
                        next.push((child.clone(), reached));
                    }
                }
            }
            if next.is_empty() {
                return None;
            }
            frontier = next;
        }
        None
    }

    /// `T_odom_base` at `stamp`: interpolated between the transforms around it, or the
    /// newest when the stamp is at most a quarter second past it.
    pub fn odometry_at(&self, stamp: f64) -> Option<Pose> {
        let after = self.odometry.iter().position(|(s, _)| *s >= stamp);
        match after {
            Some(0) => {
                let (s, pose) = self.odometry[0];
                (s == stamp).then_some(pose)
            }
            Some(i) => {
                let (s0, p0) = self.odometry[i - 1];
                let (s1, p1) = self.odometry[i];
                let f = (stamp - s0) / (s1 - s0);
                Some(p0.lerp_slerp(&p1, f))
            }
            None => self
                .odometry
                .back()
                .filter(|(s, _)| stamp - s <= ODOM_EXTRAPOLATION_S)
                .map(|(_, pose)| *pose),
        }
    }
}

/// Frame ids compare without a leading `/` (ROS 1 habit some drivers keep).
fn trim(frame: &str) -> String {
    frame.trim_start_matches('/').to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Stamp, Transform};

    fn link(parent: &str, child: &str, stamp: f64, pose: &Pose) -> TransformStamped {
        TransformStamped {
            header: Header {
                stamp: Stamp::from_seconds(stamp),
                frame_id: parent.into(),
            },
            child_frame_id: child.into(),
            transform: Transform::from(pose),
        }
    }

    fn pose(x: f64, y: f64, yaw_deg: f64) -> Pose {
        Isometry3::from_parts(
            Translation3::new(x, y, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_deg.to_radians()),
        )
    }

    #[test]
    fn the_mounting_is_the_product_of_the_static_chain() {
        let mut frames = Frames::default();
        let a = pose(0.2, 0.0, 90.0);
        let b = pose(0.0, 0.1, -30.0);
        let skipped = frames.add_static(&[
            link("base_link", "sensor_mount", 0.0, &a),
            link("/sensor_mount", "os_lidar", 0.0, &b),
            link("base_link", "", 0.0, &a),
        ]);
        assert_eq!(skipped, 1);
        let chain = frames.mounting("base_link", "os_lidar").unwrap();
        let expected = a * b;
        assert!((chain.translation.vector - expected.translation.vector).norm() < 1e-12);
        assert!(chain.rotation.angle_to(&expected.rotation) < 1e-12);
        assert_eq!(
            frames.mounting("base_link", "base_link"),
            Some(Pose::identity())
        );
        assert_eq!(frames.mounting("base_link", "camera"), None);
    }

    #[test]
    fn a_cloud_outside_the_base_frame_has_no_mounting_until_one_is_given() {
        let mut frames = Frames::default();
        // No /tf_static, nothing configured: unknown, not the identity.
        assert_eq!(sensor_mounting(&frames, "base_link", "lidar", None), None);
        // A cloud in the base frame needs none.
        assert_eq!(
            sensor_mounting(&frames, "base_link", "base_link", None),
            Some(Pose::identity())
        );
        // The configured mounting, until /tf_static gives one.
        let configured = parse_mounting("0 0 0.9 0 0 90");
        let used = sensor_mounting(&frames, "base_link", "lidar", configured).unwrap();
        assert!((used.translation.z - 0.9).abs() < 1e-12);
        let latched = pose(0.2, -0.1, 45.0);
        frames.add_static(&[link("base_link", "lidar", 0.0, &latched)]);
        let found = sensor_mounting(&frames, "base_link", "lidar", configured).unwrap();
        assert!((found.translation.vector - latched.translation.vector).norm() < 1e-12);
    }

    #[test]
    fn odometry_is_interpolated_at_a_stamp_and_not_guessed_far_past_it() {
        let mut frames = Frames::default();
        frames.add_dynamic(
            &[
                link("odom", "base_link", 10.0, &pose(0.0, 0.0, 0.0)),
                link("odom", "base_link", 10.1, &pose(1.0, 0.0, 10.0)),
                link("map", "base_link", 10.05, &pose(50.0, 0.0, 0.0)),
                link("odom", "base_link", 10.05, &pose(9.0, 9.0, 0.0)),
            ],
            "odom",
            "base_link",
        );
        let mid = frames.odometry_at(10.05).unwrap();
        assert!((mid.translation.vector.x - 0.5).abs() < 1e-9);
        assert!((mid.rotation.angle() - 5.0_f64.to_radians()).abs() < 1e-9);
        assert!(frames.odometry_at(10.2).is_some());
        assert!(frames.odometry_at(11.0).is_none());
        assert!(frames.odometry_at(9.0).is_none());
    }

    #[test]
    fn mountings_parse_in_metres_and_degrees() {
        let m = parse_mounting("0.1 0 0.5 0 0 90").unwrap();
        assert!((m.translation.vector.z - 0.5).abs() < 1e-12);
        assert!((m.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        for bad in ["", "1 2 3", "1 2 3 4 5 x", "1 2 3 4 5 6 7", "nan 0 0 0 0 0"] {
            assert!(parse_mounting(bad).is_none(), "{bad}");
        }
    }
}
