//! What the node publishes for a tracked scan: the base's pose with its covariance,
//! odometry, the map -> odom (or map -> base) transform and the diagnostics, built from
//! the tracker's `T_map_sensor` and health.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::tracking::{ScanHealth, TrackingStatus};
use nalgebra::{Matrix3, Matrix6, Vector3};

use crate::msgs::{
    DIAGNOSTIC_ERROR, DIAGNOSTIC_OK, DIAGNOSTIC_WARN, DiagnosticArray, DiagnosticStatus, Header,
    KeyValue, Odometry, PoseMsg, PoseWithCovariance, PoseWithCovarianceStamped, Stamp, Transform,
    TransformStamped, Twist, TwistWithCovariance,
};

/// The name of the node's diagnostic status.
pub const DIAGNOSTIC_NAME: &str = "kfmap: localization";

/// The covariance of `T_map_base` in ROS order (x, y, z, rotation about x, y, z; map
/// frame, row-major) from the tracker's covariance of `T_map_sensor` (right perturbation
/// in the sensor frame, rotation first) and the mounting `T_sensor_base`.
///
/// A sensor-frame perturbation `(dphi, drho)` moves the sensor by `R drho` and turns it
/// by `R dphi` in the map frame (to first order); the base, `R t` away from the sensor
/// (`t` the base's position in the sensor frame), moves by `R drho - [R t]x R dphi`.
pub fn base_covariance_ros(
    covariance: &Matrix6<f64>,
    map_sensor: &Pose,
    sensor_base: &Pose,
) -> [f64; 36] {
    let r = map_sensor.rotation.to_rotation_matrix().into_inner();
    let lever = r * sensor_base.translation.vector;
    let mut jacobian = Matrix6::zeros();
    // Rows: base position (map), base rotation (map); columns: dphi, drho (sensor).
    jacobian
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-skew(&lever) * r));
    jacobian.fixed_view_mut::<3, 3>(0, 3).copy_from(&r);
    jacobian.fixed_view_mut::<3, 3>(3, 0).copy_from(&r);
    let ros = jacobian * covariance * jacobian.transpose();
    let mut out = [0.0; 36];
    for row in 0..6 {
        for col in 0..6 {
            out[row * 6 + col] = ros[(row, col)];
        }
    }
    out
}

fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// ROS's way of saying "unknown" in a covariance: -1 first, as the Imu message does.
fn unknown_covariance() -> [f64; 36] {
    let mut c = [0.0; 36];
    c[0] = -1.0;
    c
}

/// One scan's outputs.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanOutputs {
    pub pose: PoseWithCovarianceStamped,
    pub odometry: Odometry,
    /// `map -> odom` with odometry on `/tf`, else `map -> base`.
    pub transform: TransformStamped,
}

/// Frame names the outputs use.
#[derive(Debug, Clone)]
pub struct FrameNames {
    pub map: String,
    pub odom: String,
    pub base: String,
}

/// The outputs of a scan stamped `stamp` localized at `map_sensor` with `health`:
/// `sensor_base` is the mounting's inverse, `odom_base` the robot's odometry at the
/// stamp when `/tf` has it, `velocity` the base's (linear, angular) velocity in its own
/// frame since the last scan.
pub fn scan_outputs(
    frames: &FrameNames,
    stamp: Stamp,
    map_sensor: &Pose,
    health: &ScanHealth,
    sensor_base: &Pose,
    odom_base: Option<&Pose>,
    velocity: Option<(Vector3<f64>, Vector3<f64>)>,
) -> ScanOutputs {
    let map_base = map_sensor * sensor_base;
    let covariance = match (&health.covariance, health.status) {
        (Some(c), TrackingStatus::Ok | TrackingStatus::Degraded) => {
            base_covariance_ros(c, map_sensor, sensor_base)
        }
        _ => unknown_covariance(),
    };
    let header = |frame: &str| Header {
        stamp,
        frame_id: frame.to_string(),
    };
    let pose = PoseWithCovariance {
        pose: PoseMsg::from(&map_base),
        covariance,
    };
    let twist = match velocity {
        Some((linear, angular)) => TwistWithCovariance {
            twist: Twist {
                linear: linear.into(),
                angular: angular.into(),
            },
            covariance: unknown_covariance(),
        },
        None => TwistWithCovariance {
            covariance: unknown_covariance(),
            ..TwistWithCovariance::default()
        },
    };
    let transform = match odom_base {
        Some(odom_base) => TransformStamped {
            header: header(&frames.map),
            child_frame_id: frames.odom.clone(),
            transform: Transform::from(&(map_base * odom_base.inverse())),
        },
        None => TransformStamped {
            header: header(&frames.map),
            child_frame_id: frames.base.clone(),
            transform: Transform::from(&map_base),
        },
    };
    ScanOutputs {
        pose: PoseWithCovarianceStamped {
            header: header(&frames.map),
            pose,
        },
        odometry: Odometry {
            header: header(&frames.map),
            child_frame_id: frames.base.clone(),
            pose,
            twist,
        },
        transform,
    }
}

/// The base's velocity in its own frame between two poses `dt` seconds apart.
pub fn base_velocity(before: &Pose, after: &Pose, dt: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
    if !(dt.is_finite() && dt > 1e-6) {
        return None;
    }
    let delta = before.inverse() * after;
    Some((
        delta.translation.vector / dt,
        delta.rotation.scaled_axis() / dt,
    ))
}

/// What the diagnostics say about the node.
#[derive(Debug, Clone, PartialEq)]
pub enum Condition<'a> {
    /// A scan was tracked with this health.
    Tracked(&'a ScanHealth),
    /// A cloud could not be used (bad layout, no valid point): the reason.
    BadCloud(&'a str),
    /// The server did not answer: why.
    NoServer(&'a str),
    /// A cloud was localized but its pose held back: why (no mounting on the base).
    Unmounted(&'a str),
    /// No cloud yet.
    Waiting,
}

/// The diagnostics for `condition`, with counters as key-values.
pub fn diagnostics(
    stamp: Stamp,
    condition: &Condition<'_>,
    map_name: &str,
    counters: &[(&str, String)],
) -> DiagnosticArray {
    let (level, message) = match condition {
        Condition::Tracked(h) => {
            let level = match h.status {
                TrackingStatus::Ok => DIAGNOSTIC_OK,
                TrackingStatus::Degraded => DIAGNOSTIC_WARN,
                TrackingStatus::Lost => DIAGNOSTIC_ERROR,
            };
            let reasons = h.reasons.names();
            let message = if reasons.is_empty() {
                h.status.name().to_string()
            } else {
                format!("{}: {}", h.status.name(), reasons.join(", "))
            };
            (level, message)
        }
        Condition::BadCloud(why) => (DIAGNOSTIC_WARN, format!("bad cloud: {why}")),
        Condition::NoServer(why) => (DIAGNOSTIC_ERROR, format!("no server: {why}")),
        Condition::Unmounted(why) => (DIAGNOSTIC_WARN, format!("pose held back: {why}")),
        Condition::Waiting => (DIAGNOSTIC_WARN, "waiting for a cloud".to_string()),
    };
    let mut values = Vec::new();
    if let Condition::Tracked(h) = condition {
        values.push(kv("status", h.status.name()));
        values.push(kv("fitness", format!("{:.4}", h.inlier_ratio)));
        values.push(kv("rmse_m", format!("{:.4}", h.rmse)));
        values.push(kv("degenerate", h.degenerate.to_string()));
    }
    values.extend(counters.iter().map(|(k, v)| kv(k, v.clone())));
    DiagnosticArray {
        header: Header {
            stamp,
            frame_id: String::new(),
        },
        status: vec![DiagnosticStatus {
            level,
            name: DIAGNOSTIC_NAME.into(),
            message,
            hardware_id: map_name.into(),
            values,
        }],
    }
}

fn kv(key: &str, value: impl Into<String>) -> KeyValue {
    KeyValue {
        key: key.into(),
        value: value.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn pose(t: [f64; 3], rpy: [f64; 3]) -> Pose {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
        )
    }

    /// Oracle: sample sensor-frame perturbations, move the base, and compare the sample
    /// covariance of its map-frame position and rotation with the propagated one.
    #[test]
    fn the_base_covariance_is_the_sampled_one() {
        let map_sensor = pose([3.0, -1.0, 0.5], [0.1, -0.05, 1.2]);
        let sensor_base = pose([-0.4, 0.1, -0.8], [0.0, 0.0, 0.3]);
        // A covariance with cross terms (rotation first), small enough to be linear.
        let a = Matrix6::from_fn(|i, j| {
            ((i * 7 + j * 3) % 5) as f64 * 1e-3 + if i == j { 4e-3 } else { 0.0 }
        });
        let covariance = a * a.transpose();
        let ros = base_covariance_ros(&covariance, &map_sensor, &sensor_base);
        let l = covariance.cholesky().unwrap().l();
        let map_base = map_sensor * sensor_base;
        let mut state = 12345_u64;
        let mut normal = || {
            // Box-Muller from a 64-bit LCG: a deterministic standard normal.
            let mut uniform = || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (u, v) = (uniform(), uniform());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let n = 40_000;
        let mut sum = Matrix6::zeros();
        for _ in 0..n {
            let z = nalgebra::Vector6::from_fn(|_, _| normal());
            let d = l * z;
            let (dphi, drho) = (
                d.fixed_rows::<3>(0).into_owned(),
                d.fixed_rows::<3>(3).into_owned(),
            );
            let perturbed = map_sensor
                * Isometry3::from_parts(
                    Translation3::from(drho),
                    UnitQuaternion::from_scaled_axis(dphi),
                );
            let base = perturbed * sensor_base;
            let dp = base.translation.vector - map_base.translation.vector;
            let dtheta = (base.rotation * map_base.rotation.inverse()).scaled_axis();
            let e = nalgebra::Vector6::new(dp.x, dp.y, dp.z, dtheta.x, dtheta.y, dtheta.z);
            sum += e * e.transpose();
        }
        let sampled = sum / n as f64;
        for row in 0..6 {
            for col in 0..6 {
                let scale = (sampled[(row, row)] * sampled[(col, col)]).sqrt();
                let gap = (ros[row * 6 + col] - sampled[(row, col)]).abs() / scale;
                assert!(
                    gap < 0.03,
                    "({row}, {col}): {} vs {}",
                    ros[row * 6 + col],
                    sampled[(row, col)]
                );
            }
        }
    }

    #[test]
    fn the_transform_is_map_to_odom_with_odometry_and_map_to_base_without() {
        let frames = FrameNames {
            map: "map".into(),
            odom: "odom".into(),
            base: "base_link".into(),
        };
        let map_sensor = pose([10.0, 5.0, 1.0], [0.0, 0.0, 0.7]);
        let sensor_base = pose([0.0, 0.0, -1.0], [0.0, 0.0, 0.0]);
        let odom_base = pose([2.0, 1.0, 0.0], [0.0, 0.0, 0.2]);
        let health = ScanHealth::no_fit(0, 0);
        let stamp = Stamp { sec: 7, nanosec: 5 };
        let with = scan_outputs(
            &frames,
            stamp,
            &map_sensor,
            &health,
            &sensor_base,
            Some(&odom_base),
            None,
        );
        assert_eq!(with.transform.child_frame_id, "odom");
        let map_odom = with.transform.transform.pose().unwrap();
        let map_base = map_sensor * sensor_base;
        let chained = map_odom * odom_base;
        assert!((chained.translation.vector - map_base.translation.vector).norm() < 1e-12);
        assert!(chained.rotation.angle_to(&map_base.rotation) < 1e-12);
        assert_eq!(with.pose.header.stamp, stamp);
        assert_eq!(with.pose.pose.covariance[0], -1.0, "no fit: unknown");
        let without = scan_outputs(
            &frames,
            stamp,
            &map_sensor,
            &health,
            &sensor_base,
            None,
            None,
        );
        assert_eq!(without.transform.child_frame_id, "base_link");
        let p = without.pose.pose.pose.pose().unwrap();
        assert!((p.translation.vector - map_base.translation.vector).norm() < 1e-12);
    }

    #[test]
    fn velocity_is_in_the_base_frame() {
        let before = pose([0.0, 0.0, 0.0], [0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let after = pose(
            [0.0, 1.0, 0.0],
            [0.0, 0.0, std::f64::consts::FRAC_PI_2 + 0.1],
        );
        let (linear, angular) = base_velocity(&before, &after, 0.5).unwrap();
        assert!(
            (linear - Vector3::new(2.0, 0.0, 0.0)).norm() < 1e-9,
            "{linear}"
        );
        assert!(
            (angular - Vector3::new(0.0, 0.0, 0.2)).norm() < 1e-9,
            "{angular}"
        );
        assert!(base_velocity(&before, &after, 0.0).is_none());
    }
}
