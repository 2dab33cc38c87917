//! The pose predictor (motion model) odometry and the localization tracker share: constant velocity for
//! translation, the gyro for rotation where an IMU log covers the interval, and the
//! deskew of scans that carry per-point times into their mid-scan frame.

use nalgebra::Vector3;

use super::{ConstantVelocity, Gyro};
use crate::cloud::{DeskewError, PointCloud, Twist, deskew};
use crate::geometry::Pose;
use crate::gravity::STANDARD_GRAVITY_MPS2;

/// How far a right pose may sit from a right prediction beyond what the motion
/// explains, metres: the registration's error on the poses the velocity came from, at
/// the distance where a pose counts as wrong.
pub const REACH_SLACK_M: f64 = 0.5;
/// How wrong the velocity of two adopted poses may be, m/s: 0.5 m/s is 5 cm of
/// registration error over a 10 Hz scan interval.
const REACH_VELOCITY_SLACK_MPS: f64 = 0.5;
/// Added to the accelerometer's largest linear acceleration, m/s^2: its bias, the
/// map's tilt from gravity (0.17 m/s^2 per degree) and the IMU's lever arm in turns.
const REACH_ACCELERATION_MARGIN_MPS2: f64 = 1.0;

/// Predicts the sensor's pose from the poses accepted so far (and the gyro).
#[derive(Debug, Clone, Default)]
pub struct PosePredictor {
    velocity: ConstantVelocity,
    gyro: Option<Gyro>,
}

/// A scan moved into the sensor frame at mid-scan, where it is tracked.
#[derive(Debug, Clone)]
pub struct MidScan {
    /// The deskewed scan (`None`: use the scan as it is: no per-point times, deskew
    /// off, or no motion known yet).
    pub deskewed: Option<PointCloud>,
    /// Seconds after the scan's stamp of the frame the scan is in: the middle of its
    /// points' times when it has them (and deskewing is on), else 0.
    pub offset: f64,
}

impl PosePredictor {
    /// No pose yet; rotation from `gyro` where it covers the interval.
    pub fn new(gyro: Option<Gyro>) -> Self {
        Self {
            velocity: ConstantVelocity::new(),
            gyro,
        }
    }

    /// Forgets the poses and velocity (the gyro and its bias stay): the next pose
    /// starts a new track (after a relocalization).
    pub fn restart(&mut self) {
        self.velocity = ConstantVelocity::new();
    }

    /// The gyro, when there is one.
    pub fn gyro(&self) -> Option<&Gyro> {
        self.gyro.as_ref()
    }

    /// The gyro, to extend a live log; `None` when there is none.
    pub fn gyro_mut(&mut self) -> Option<&mut Gyro> {
        self.gyro.as_mut()
    }

    /// Predicts rotation with `gyro` from now on (the poses and velocity stay).
    pub fn set_gyro(&mut self, gyro: Gyro) {
        self.gyro = Some(gyro);
    }

    /// The last pose given to [`PosePredictor::update`].
    pub fn last(&self) -> Option<&Pose> {
        self.velocity.last()
    }

    /// When the last pose was taken, seconds.
    pub fn last_time(&self) -> Option<f64> {
        self.velocity.last_time()
    }

    /// The pose expected at time `t`, seconds: the constant-velocity prediction with the
    /// gyro's rotation since the last pose; `None` before the first pose.
    pub fn predict(&self, t: f64) -> Option<Pose> {
        let last = *self.velocity.last()?;
        let t_last = self.velocity.last_time()?;
        let motion = self.velocity.predicted_motion(t);
        let motion = match self.gyro.as_ref().and_then(|g| g.rotation(t_last, t)) {
            Some(rotation) => Pose::from_parts(motion.translation, rotation),
            None => motion,
        };
        Some(last * motion)
    }

    /// How far from [`PosePredictor::predict`]'s position the sensor can be at `t`,
    /// metres, for a platform that accelerates at most `max_acceleration` (m/s^2):
    /// [`REACH_SLACK_M`] plus half that acceleration times the squared time since the
    /// last pose. Where the IMU log covers that time, the acceleration it measured
    /// (gravity removed in the map's frame, plus [`REACH_ACCELERATION_MARGIN_MPS2`])
    /// with the velocity's own error ([`REACH_VELOCITY_SLACK_MPS`] times the time)
    /// bounds it tighter when it does: a car cruising through a lost second cannot
    /// have jumped to a look-alike 2 m along the street that 1 g would allow.
    /// `None` before the first pose.
    pub fn reach(&self, t: f64, max_acceleration: f64) -> Option<f64> {
        let t_last = self.velocity.last_time()?;
        let last = self.velocity.last()?;
        let dt = (t - t_last).max(0.0);
        let worst = REACH_SLACK_M + 0.5 * max_acceleration * dt * dt;
        // Down the map's z axis: a levelled map, as the relocalization tilt assumes.
        let gravity = Vector3::new(0.0, 0.0, -STANDARD_GRAVITY_MPS2);
        let measured = self
            .gyro
            .as_ref()
            .and_then(|g| g.max_linear_acceleration(t_last, t, &last.rotation, &gravity))
            .map(|a| {
                let a = a + REACH_ACCELERATION_MARGIN_MPS2;
                REACH_SLACK_M + REACH_VELOCITY_SLACK_MPS * dt + 0.5 * a * dt * dt
            });
        Some(measured.map_or(worst, |m| m.min(worst)))
    }

    /// The body twist over `[t0, t1]`: the last velocity's linear part, and the gyro's
    /// mean rate there (else the last velocity's); `None` when neither is known.
    pub fn twist_over(&self, t0: f64, t1: f64) -> Option<Twist> {
        let velocity = self.velocity.velocity();
        let rate = self.gyro.as_ref().and_then(|g| g.mean_rate(t0, t1));
        match (velocity, rate) {
            (Some(v), Some(w)) => Some(Twist::new(w, v.linear)),
            (None, Some(w)) => Some(Twist::new(w, Vector3::zeros())),
            (v, None) => v,
        }
    }

    /// Accepts `pose` at time `t`; `trusted` poses (registered well) also teach the gyro
    /// its bias.
    pub fn update(&mut self, t: f64, pose: Pose, trusted: bool) {
        if let (true, Some(gyro), Some(last), Some(t_last)) = (
            trusted,
            self.gyro.as_mut(),
            self.velocity.last(),
            self.velocity.last_time(),
        ) {
            gyro.observe(t_last, t, &(last.inverse() * pose).rotation);
        }
        self.velocity.update(t, pose);
    }

    /// Whether a velocity is known (two poses since the last restart, the velocity not
    /// forgotten): without one the prediction is the last pose, turned by the gyro.
    pub fn has_velocity(&self) -> bool {
        self.velocity.velocity().is_some()
    }

    /// Keeps the last pose but forgets the velocity (the motion since is unknown); the
    /// gyro still predicts rotation.
    pub fn forget_velocity(&mut self) {
        self.velocity.forget_velocity();
    }

    /// Puts the last pose at `pose` (same time) keeping the body-frame velocity and the
    /// gyro: the same motion from another place (a tracker following several places).
    pub fn relocate(&mut self, pose: Pose) {
        self.velocity.relocate(pose);
    }

    /// `pose` (at time `from`) carried to time `to` by the motion model's twist there.
    pub fn carry(&self, pose: &Pose, from: f64, to: f64) -> Pose {
        match self.twist_over(from.min(to), from.max(to)) {
            Some(twist) if to != from => pose * twist.motion(to - from),
            _ => *pose,
        }
    }

    /// `scan`, stamped `stamp`, moved into its sensor frame at mid-scan by the motion
    /// model's twist over the scan, when `enabled` and it has per-point times. Tracking
    /// at mid-scan keeps a velocity error from feeding back: it shifts the cloud
    /// symmetrically instead of along the motion (deskewing to the stamp oscillated and
    /// diverged on the simulated courtyard).
    pub fn mid_scan(
        &self,
        scan: &PointCloud,
        stamp: f64,
        enabled: bool,
    ) -> Result<MidScan, DeskewError> {
        let Some((first, last)) = time_span(scan).filter(|_| enabled) else {
            return Ok(MidScan {
                deskewed: None,
                offset: 0.0,
            });
        };
        let offset = (first + last) / 2.0;
        let deskewed = match self.twist_over(stamp + first, stamp + last) {
            Some(twist) => {
                let mut moved = scan.clone();
                deskew(&mut moved, &twist, offset)?;
                Some(moved)
            }
            None => None,
        };
        Ok(MidScan { deskewed, offset })
    }
}

/// The first and last finite per-point time of `scan`, seconds after its stamp.
fn time_span(scan: &PointCloud) -> Option<(f64, f64)> {
    let (lo, hi) = scan
        .time
        .as_deref()?
        .iter()
        .filter(|t| t.is_finite())
        .fold((f32::MAX, f32::MIN), |(lo, hi), &t| (lo.min(t), hi.max(t)));
    (lo <= hi).then(|| (f64::from(lo), f64::from(hi)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{rotation_distance, translation_distance};
    use crate::imu::ImuSample;
    use crate::motion::GyroParams;
    use nalgebra::UnitQuaternion;

    /// Yaw rate `w(t)` (rad/s) sampled at 200 Hz for 3 s.
    fn yaw_log(w: impl Fn(f64) -> f64) -> Gyro {
        let samples = (0..=600)
            .map(|k| {
                let t = k as f64 / 200.0;
                ImuSample {
                    t,
                    acc: [0.0, 0.0, 9.81],
                    gyro: [0.0, 0.0, w(t)],
                }
            })
            .collect();
        Gyro::new(samples, GyroParams::default()).unwrap()
    }

    fn yawed(x: f64, yaw: f64) -> Pose {
        Pose::from_parts(
            nalgebra::Translation3::new(x, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    #[test]
    fn the_gyro_predicts_a_turn_that_starts_after_the_last_pose() {
        // Straight at 1 m/s until t = 1 s, then yawing at 1 rad/s: constant velocity
        // predicts no turn at t = 1.5, the gyro the half radian.
        let rate = |t: f64| if t < 1.0 { 0.0 } else { 1.0 };
        let mut with_gyro = PosePredictor::new(Some(yaw_log(rate)));
        let mut without = PosePredictor::new(None);
        // Untrusted: the interpolated rate step would teach a bias here.
        for (t, pose) in [(0.5, yawed(0.5, 0.0)), (1.0, yawed(1.0, 0.0))] {
            with_gyro.update(t, pose, false);
            without.update(t, pose, false);
        }
        let predicted = with_gyro.predict(1.5).unwrap();
        assert!((predicted.rotation.euler_angles().2 - 0.5).abs() < 1e-6);
        assert!(translation_distance(&predicted, &yawed(1.5, 0.5)) < 1e-9);
        assert!(rotation_distance(&without.predict(1.5).unwrap(), &yawed(1.5, 0.0)) < 1e-12);
        // Without a velocity the gyro still turns the prediction.
        with_gyro.forget_velocity();
        let held = with_gyro.predict(1.5).unwrap();
        assert!(translation_distance(&held, &yawed(1.0, 0.0)) < 1e-12);
        assert!((held.rotation.euler_angles().2 - 0.5).abs() < 1e-6);
    }

    #[test]
    fn mid_scan_deskews_with_the_gyro_rate_over_the_scan() {
        let mut model = PosePredictor::new(Some(yaw_log(|_| 2.0)));
        let mut scan = PointCloud::from_points(vec![[10.0, 0.0, 0.0], [10.0, 0.0, 0.0]]);
        scan.time = Some(vec![0.0, 0.1]);
        // No pose yet: the gyro alone deskews.
        let mid = model.mid_scan(&scan, 1.0, true).unwrap();
        assert!((mid.offset - 0.05).abs() < 1e-9);
        let moved = mid.deskewed.unwrap();
        // Turning at 2 rad/s, a point seen 0.05 s before (after) mid-scan lies at -0.1
        // (+0.1) rad yaw in the mid-scan frame.
        let expect = |dt: f64| {
            let a = 2.0 * dt;
            [10.0 * a.cos(), 10.0 * a.sin()]
        };
        for (p, dt) in moved.points.iter().zip([-0.05, 0.05]) {
            let [x, y] = expect(dt);
            assert!((p[0] as f64 - x).abs() < 1e-4 && (p[1] as f64 - y).abs() < 1e-4);
        }
        model.update(1.0, Pose::identity(), true);
        // Off, or without times: nothing moves and the frame stays at the stamp.
        let off = model.mid_scan(&scan, 1.0, false).unwrap();
        assert!(off.deskewed.is_none() && off.offset == 0.0);
        scan.time = None;
        let bare = model.mid_scan(&scan, 1.0, true).unwrap();
        assert!(bare.deskewed.is_none() && bare.offset == 0.0);
    }

    /// A platform at rest on level ground that starts pulling 2 m/s^2 along x: the
    /// constant-velocity prediction falls `t^2` behind (closed form), the reach
    /// measured by the accelerometer holds that and is far short of 1 g's; without
    /// the log the reach is 1 g's.
    #[test]
    fn the_reach_holds_a_measured_acceleration_and_is_tighter_than_one_g() {
        let samples = (0..=600)
            .map(|k| {
                let t = k as f64 / 200.0;
                let pulling = if t > 1.0 { 2.0 } else { 0.0 };
                ImuSample {
                    t,
                    acc: [pulling, 0.0, STANDARD_GRAVITY_MPS2],
                    gyro: [0.0; 3],
                }
            })
            .collect();
        let gyro = Gyro::new(samples, GyroParams::default()).unwrap();
        let mut with_imu = PosePredictor::new(Some(gyro));
        let mut without = PosePredictor::new(None);
        for model in [&mut with_imu, &mut without] {
            model.update(0.9, Pose::identity(), false);
            model.update(1.0, Pose::identity(), false);
        }
        let one_g = 9.81;
        for ahead in [0.1, 0.5, 1.0, 1.5] {
            let t = 1.0 + ahead;
            let behind = ahead * ahead;
            let reach = with_imu.reach(t, one_g).unwrap();
            let measured = REACH_SLACK_M
                + REACH_VELOCITY_SLACK_MPS * ahead
                + 0.5 * (2.0 + REACH_ACCELERATION_MARGIN_MPS2) * ahead * ahead;
            let worst = REACH_SLACK_M + 0.5 * one_g * ahead * ahead;
            assert!(
                (reach - measured.min(worst)).abs() < 1e-6,
                "{ahead}: {reach}"
            );
            assert!(
                reach - REACH_SLACK_M >= behind,
                "{ahead}: {reach} < {behind}"
            );
            assert!((without.reach(t, one_g).unwrap() - worst).abs() < 1e-12);
        }
        assert!(PosePredictor::new(None).reach(1.0, one_g).is_none());
    }
}
