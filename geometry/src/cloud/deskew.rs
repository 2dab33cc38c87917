//! Motion compensation ("deskewing") of one scan under a constant body-frame velocity.
//!
//! A spinning LiDAR measures each point in the sensor frame at the point's own firing
//! time; while the platform moves, one scan is several frames smeared together. With the
//! sensor's motion over the scan modelled as a constant twist `xi = (omega, v)`, the
//! sensor pose at time `t` is `T(t) = T(t_ref) Exp((t - t_ref) xi)` (SE(3) exponential,
//! rotation first, as [`crate::se3::exp`]), so a point `p` measured at `t` is
//! `Exp((t - t_ref) xi) p` in the sensor frame at `t_ref`. This is the constant-velocity
//! deskew of LiDAR odometry pipelines (KISS-ICP's `DeSkewScan`, on the SE(3) group).
//!
//! ```
//! use kfmap_geometry::cloud::{PointCloud, Twist, DeskewOutcome, deskew};
//! use nalgebra::Vector3;
//!
//! // Driving at 10 m/s along x: a wall point 20 m ahead, seen 0.1 s into the scan, was
//! // 21 m ahead at the scan stamp.
//! let mut cloud = PointCloud::from_points(vec![[20.0, 0.0, 0.0]]);
//! cloud.time = Some(vec![0.1]);
//! let twist = Twist::new(Vector3::zeros(), Vector3::new(10.0, 0.0, 0.0));
//! assert_eq!(deskew(&mut cloud, &twist, 0.0).unwrap(), DeskewOutcome::Deskewed);
//! assert!((cloud.points[0][0] - 21.0).abs() < 1e-5);
//! ```

use nalgebra::{Vector3, Vector6};

use super::PointCloud;
use crate::geometry::{Pose, to_point, to_vec3, transform_point};
use crate::se3::{exp, log};

/// A constant velocity of the sensor, both parts in the sensor (body) frame: the pose at
/// time `t` is `T(t) = T(0) Exp(t [angular; linear])`. Over a scan it is what an
/// odometry's constant-velocity model predicts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Twist {
    /// Angular velocity, rad/s, about the sensor frame's axes.
    pub angular: Vector3<f64>,
    /// Linear velocity, m/s, along the sensor frame's axes.
    pub linear: Vector3<f64>,
}

impl Twist {
    /// Standing still.
    pub const ZERO: Twist = Twist {
        angular: Vector3::new(0.0, 0.0, 0.0),
        linear: Vector3::new(0.0, 0.0, 0.0),
    };

    /// A twist from its angular (rad/s) and linear (m/s) velocity, sensor frame.
    pub fn new(angular: Vector3<f64>, linear: Vector3<f64>) -> Self {
        Self { angular, linear }
    }

    /// The constant twist that carries `previous` (`T_map_sensor` at one time) to
    /// `current` (`dt` seconds later): `Log(previous^-1 current) / dt`. `None` when `dt`
    /// is not a positive finite number of seconds or a pose is not finite.
    pub fn between(previous: &Pose, current: &Pose, dt: f64) -> Option<Twist> {
        if !(dt.is_finite() && dt > 0.0) {
            return None;
        }
        let xi = log(&(previous.inverse() * current)) / dt;
        xi.iter()
            .all(|x| x.is_finite())
            .then(|| Self::from_vector(&xi))
    }

    /// `T_a_b`: the sensor at time `b` seen from the sensor at time `a = b - seconds`,
    /// i.e. `Exp(seconds xi)`.
    pub fn motion(&self, seconds: f64) -> Pose {
        exp(&(self.to_vector() * seconds))
    }

    /// `(omega, v)`, the order of [`crate::se3::exp`].
    pub fn to_vector(&self) -> Vector6<f64> {
        let (w, v) = (self.angular, self.linear);
        Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
    }

    /// From `(omega, v)`.
    pub fn from_vector(xi: &Vector6<f64>) -> Self {
        Self {
            angular: xi.fixed_rows::<3>(0).into_owned(),
            linear: xi.fixed_rows::<3>(3).into_owned(),
        }
    }
}

/// What [`deskew`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeskewOutcome {
    /// Every point (and view direction) is now in the sensor frame at the reference time.
    Deskewed,
    /// The cloud has no per-point times: it is left as it is ("no per-point times: not
    /// deskewed").
    NoTimes,
}

/// Why a cloud could not be deskewed; the cloud is left unchanged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeskewError {
    /// An attribute does not have one entry per point.
    #[error("cannot deskew: {0}")]
    Cloud(#[from] super::CloudError),
    /// A point's time is NaN or infinite.
    #[error("cannot deskew: point {index} has a non-finite time ({value})")]
    NonFiniteTime {
        /// The first such point.
        index: usize,
        /// Its time as read, seconds.
        value: f32,
    },
    /// The twist or the reference time is NaN or infinite.
    #[error("cannot deskew: the motion is not finite ({0})")]
    NonFiniteMotion(String),
}

/// Moves every point of `cloud` from the sensor frame at its own time (`cloud.time`,
/// seconds relative to the scan stamp) into the sensor frame at `reference_time` (seconds
/// on the same clock: 0 is the scan stamp), assuming the sensor moved with the constant
/// `twist` over the scan. View directions are rotated with their points; times are kept.
///
/// A cloud without per-point times is returned unchanged with
/// [`DeskewOutcome::NoTimes`]. On error the cloud is unchanged.
pub fn deskew(
    cloud: &mut PointCloud,
    twist: &Twist,
    reference_time: f64,
) -> Result<DeskewOutcome, DeskewError> {
    let Some(times) = cloud.time.as_ref() else {
        return Ok(DeskewOutcome::NoTimes);
    };
    let xi = twist.to_vector();
    if !(xi.iter().all(|x| x.is_finite()) && reference_time.is_finite()) {
        return Err(DeskewError::NonFiniteMotion(format!(
            "twist {:?}, reference time {reference_time} s",
            xi.as_slice()
        )));
    }
    cloud.validate()?;
    if let Some(index) = times.iter().position(|t| !t.is_finite()) {
        return Err(DeskewError::NonFiniteTime {
            index,
            value: times[index],
        });
    }
    let mut last: Option<(f32, Pose)> = None;
    for (i, &t) in times.iter().enumerate() {
        // A spinning LiDAR fires a whole column at once: one exponential per column.
        let motion = match last {
            Some((at, motion)) if at == t => motion,
            _ => {
                let motion = exp(&(xi * (f64::from(t) - reference_time)));
                last = Some((t, motion));
                motion
            }
        };
        cloud.points[i] = to_point(&transform_point(&motion, &cloud.points[i]));
        if let Some(view) = cloud.view_dirs.as_mut() {
            view[i] = to_point(&(motion.rotation * to_vec3(&view[i])));
        }
    }
    Ok(DeskewOutcome::Deskewed)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Pose, b: &Pose) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9
            && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    #[test]
    fn twist_between_two_poses_round_trips_the_exponential() {
        let twist = Twist::new(Vector3::new(0.1, -0.3, 0.8), Vector3::new(4.0, 0.5, -0.2));
        let start = Pose::new(
            Vector3::new(10.0, -3.0, 1.8),
            Vector3::new(0.02, -0.01, 2.0),
        );
        let dt = 0.1;
        let end = start * twist.motion(dt);
        let back = Twist::between(&start, &end, dt).unwrap();
        assert!(
            (back.to_vector() - twist.to_vector()).norm() < 1e-9,
            "{back:?}"
        );
        // Constant twist: half the motion twice is the whole motion.
        assert!(close(
            &(twist.motion(0.05) * twist.motion(0.05)),
            &twist.motion(dt)
        ));
        assert!(Twist::between(&start, &end, 0.0).is_none());
        assert!(Twist::between(&start, &end, f64::NAN).is_none());
    }

    /// A sensor moving at a constant twist scans a static tilted plane: each return is
    /// cast in closed form (ray from the sensor pose at its firing time), so deskewing to
    /// time 0 must give the hit points themselves, exactly on the plane.
    #[test]
    fn a_static_plane_seen_at_constant_twist_deskews_back_onto_the_plane() {
        let twist = Twist::new(Vector3::new(0.05, -0.02, 0.9), Vector3::new(6.0, 0.4, 0.1));
        let normal = Vector3::new(1.0, 0.3, 0.1).normalize();
        let offset = 15.0; // The plane n . x = 15 m, in the sensor frame at t = 0.
        let (period, columns) = (0.1, 360);
        let mut cloud = PointCloud::default();
        let (mut times, mut views, mut hits) = (Vec::new(), Vec::new(), Vec::new());
        for column in 0..columns {
            let t = period * column as f64 / columns as f64;
            let pose = twist.motion(t);
            let azimuth = std::f64::consts::TAU * column as f64 / columns as f64;
            for elevation in [-0.2f64, 0.0, 0.15] {
                let u = Vector3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                );
                let (origin, dir) = (pose.translation.vector, pose.rotation * u);
                let range = (offset - normal.dot(&origin)) / normal.dot(&dir);
                if !(0.5..100.0).contains(&range) {
                    continue;
                }
                cloud.points.push(to_point(&(u * range)));
                times.push(t as f32);
                views.push(to_point(&-u));
                hits.push((origin + dir * range, t));
            }
        }
        cloud.time = Some(times);
        cloud.view_dirs = Some(views);
        assert!(cloud.len() > 300, "{}", cloud.len());
        let off_plane = |c: &PointCloud| {
            c.points
                .iter()
                .map(|p| (normal.dot(&to_vec3(p)) - offset).abs())
                .fold(0.0, f64::max)
        };
        // Raw, the plane is smeared by up to 0.6 m of travel and 5 deg of turn.
        assert!(off_plane(&cloud) > 0.3, "{}", off_plane(&cloud));

        let mut at_start = cloud.clone();
        assert_eq!(
            deskew(&mut at_start, &twist, 0.0).unwrap(),
            DeskewOutcome::Deskewed
        );
        assert!(off_plane(&at_start) < 2e-5, "{}", off_plane(&at_start));
        let views = at_start.view_dirs.as_ref().unwrap();
        for (i, (hit, t)) in hits.iter().enumerate() {
            let p = to_vec3(&at_start.points[i]);
            assert!((p - hit).norm() < 2e-5, "point {i}: {p:?} vs {hit:?}");
            // The view direction points back at the sensor where it was at firing time.
            let sensor = twist.motion(*t).translation.vector;
            let toward = (sensor - hit).normalize();
            assert!((to_vec3(&views[i]) - toward).norm() < 1e-6, "view {i}");
        }
        // Another reference time: the hits seen from the sensor at mid-scan.
        let mut at_middle = cloud.clone();
        deskew(&mut at_middle, &twist, period / 2.0).unwrap();
        let middle = twist.motion(period / 2.0).inverse();
        for (i, (hit, _)) in hits.iter().enumerate() {
            let want = middle * nalgebra::Point3::from(*hit);
            assert!((to_vec3(&at_middle.points[i]) - want.coords).norm() < 2e-5);
        }
        // Times are kept.
        assert_eq!(at_middle.time, cloud.time);
    }

    #[test]
    fn clouds_without_times_or_with_bad_ones_are_left_unchanged() {
        let twist = Twist::new(Vector3::new(0.0, 0.0, 1.0), Vector3::new(2.0, 0.0, 0.0));
        let mut bare = PointCloud::from_points(vec![[1.0, 2.0, 3.0]; 4]);
        let copy = bare.clone();
        assert_eq!(
            deskew(&mut bare, &twist, 0.0).unwrap(),
            DeskewOutcome::NoTimes
        );
        assert_eq!(bare, copy);

        let mut short = copy.clone();
        short.time = Some(vec![0.0; 3]);
        let error = deskew(&mut short, &twist, 0.0).unwrap_err();
        assert!(
            error.to_string().contains("'time' has 3 entries"),
            "{error}"
        );
        let mut nan = copy.clone();
        nan.time = Some(vec![0.0, 0.01, f32::NAN, 0.03]);
        let before = nan.clone();
        let error = deskew(&mut nan, &twist, 0.0).unwrap_err();
        assert!(matches!(error, DeskewError::NonFiniteTime { index: 2, .. }));
        assert!(error.to_string().contains("point 2"), "{error}");
        assert_eq!(nan.points, before.points);
        let mut timed = before.clone();
        timed.time = Some(vec![0.0; 4]);
        assert!(matches!(
            deskew(&mut timed, &twist, f64::INFINITY),
            Err(DeskewError::NonFiniteMotion(_))
        ));
    }
}
