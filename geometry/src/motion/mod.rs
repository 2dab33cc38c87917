//! Motion model for following a sensor through a scan sequence (odometry and the
//! localization tracker): a constant-velocity prediction (the gyro's rotation when
//! there is an IMU), an adaptive correspondence
//! distance learned from how wrong the prediction was (the idea of KISS-ICP's adaptive
//! threshold, Vizzo et al. 2023), a plausibility gate on corrections, and the wider
//! starting hypotheses to retry from when a registration looks wrong.

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::cloud::Twist;
use crate::geometry::Pose;
use crate::options::{InvalidOption, ensure, ensure_distance};
use crate::se3::{exp, log};

mod gyro;
mod predictor;
mod sweep;

pub use gyro::{Gyro, GyroError, GyroParams, MIN_UP_SAMPLES};
pub use predictor::{MidScan, PosePredictor, REACH_SLACK_M};
pub use sweep::{DeskewMode, SpinDirection, SweepParams};

/// `relative` scaled to a fraction `s` of itself along its screw motion,
/// `exp(s log(relative))`: exact for a constant body-frame twist, so a steady turn is
/// extrapolated on its circle.
pub fn scale_motion(relative: &Pose, s: f64) -> Pose {
    exp(&(log(relative) * s))
}

/// Constant-velocity prediction: the motion between the last two poses, per second,
/// carried forward.
#[derive(Debug, Clone, Default)]
pub struct ConstantVelocity {
    /// The last accepted pose and its time (seconds).
    last: Option<(f64, Pose)>,
    /// The last motion `T_prev^-1 T_last` and the seconds it took.
    motion: Option<(f64, Pose)>,
}

impl ConstantVelocity {
    /// No pose yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The last pose given to [`ConstantVelocity::update`].
    pub fn last(&self) -> Option<&Pose> {
        self.last.as_ref().map(|(_, p)| p)
    }

    /// The time of the last pose, seconds.
    pub fn last_time(&self) -> Option<f64> {
        self.last.map(|(t, _)| t)
    }

    /// The motion expected from the last pose to time `t` (identity before two poses,
    /// or when `t` is not after the last pose).
    pub fn predicted_motion(&self, t: f64) -> Pose {
        match (self.last, self.motion) {
            (Some((t_last, _)), Some((dt, motion))) if dt > 0.0 && t > t_last => {
                scale_motion(&motion, (t - t_last) / dt)
            }
            _ => Pose::identity(),
        }
    }

    /// The pose expected at time `t` (seconds); `None` before the first pose.
    pub fn predict(&self, t: f64) -> Option<Pose> {
        self.last.map(|(_, last)| last * self.predicted_motion(t))
    }

    /// The last motion as a constant body-frame twist, for deskewing the next scan.
    pub fn velocity(&self) -> Option<Twist> {
        let (dt, motion) = self.motion?;
        Twist::between(&Pose::identity(), &motion, dt)
    }

    /// Accepts `pose` at time `t`.
    pub fn update(&mut self, t: f64, pose: Pose) {
        if let Some((t_last, last)) = self.last {
            self.motion = Some((t - t_last, last.inverse() * pose));
        }
        self.last = Some((t, pose));
    }

    /// Keeps the last pose but forgets the velocity (after a lost scan: the motion
    /// since is unknown).
    pub fn forget_velocity(&mut self) {
        self.motion = None;
    }

    /// Puts the last pose at `pose` (same time), keeping the body-frame velocity: the
    /// same motion, from another place.
    pub fn relocate(&mut self, pose: Pose) {
        if let Some((_, last)) = self.last.as_mut() {
            *last = pose;
        }
    }
}

/// How far a pose is from another, seen from the points: translation plus the arc a
/// point at `range` metres sweeps under the rotation (KISS-ICP's model error).
pub fn point_displacement(a: &Pose, b: &Pose, range: f64) -> f64 {
    let delta = a.inverse() * b;
    delta.translation.vector.norm() + 2.0 * range * (delta.rotation.angle() / 2.0).sin()
}

/// Adaptive correspondence distance settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct AdaptiveThresholdParams {
    /// Correspondence distance before any correction was observed, metres.
    pub initial: f64,
    /// Never below this, metres (sensor noise and voxel size).
    pub min: f64,
    /// Never above this, metres (wrong pairs dominate beyond it).
    pub max: f64,
    /// Range the rotation error is measured at, metres (a typical point's distance).
    pub range: f64,
    /// Corrections of scans that moved less than this are not sampled, metres (a
    /// standing sensor's tiny corrections would shrink the distance below real motion).
    pub min_motion: f64,
    /// The distance is this many standard deviations of the observed correction.
    pub sigmas: f64,
}

impl Default for AdaptiveThresholdParams {
    fn default() -> Self {
        Self {
            initial: 2.0,
            // The fixed distance before the motion model: tighter let a sharp turn at
            // 4 m/s (simulated courtyard) slide 0.3 m without tripping any gate.
            min: 1.0,
            max: 3.0,
            range: 10.0,
            min_motion: 0.1,
            sigmas: 3.0,
        }
    }
}

impl AdaptiveThresholdParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure_distance("min", self.min)?;
        ensure(
            positive(self.max) && self.max >= self.min,
            "max",
            self.max,
            "a finite distance >= min",
        )?;
        ensure_distance("initial", self.initial)?;
        ensure_distance("range", self.range)?;
        ensure(
            self.min_motion.is_finite() && self.min_motion >= 0.0,
            "min-motion",
            self.min_motion,
            ">= 0 m",
        )?;
        ensure(positive(self.sigmas), "sigmas", self.sigmas, "> 0")
    }
}

/// The correspondence distance, adapted to how far registration had to move scans from
/// their predicted poses so far.
#[derive(Debug, Clone)]
pub struct AdaptiveThreshold {
    params: AdaptiveThresholdParams,
    sum_sq: f64,
    samples: usize,
}

impl AdaptiveThreshold {
    /// No correction observed yet.
    pub fn new(params: AdaptiveThresholdParams) -> Self {
        Self {
            params,
            sum_sq: 0.0,
            samples: 0,
        }
    }

    /// Standard deviation of the corrections seen, metres (`None` before any).
    pub fn sigma(&self) -> Option<f64> {
        (self.samples > 0).then(|| (self.sum_sq / self.samples as f64).sqrt())
    }

    /// The correspondence distance to register the next scan with, metres.
    pub fn distance(&self) -> f64 {
        self.sigma()
            .map_or(self.params.initial, |s| s * self.params.sigmas)
            .clamp(self.params.min, self.params.max)
    }

    /// Records a registration that moved the scan from `predicted` to `corrected`, after
    /// the sensor moved `motion` since the last scan.
    pub fn observe(&mut self, predicted: &Pose, corrected: &Pose, motion: &Pose) {
        if motion.translation.vector.norm() < self.params.min_motion
            && motion.rotation.angle() < (self.params.min_motion / self.params.range)
        {
            return;
        }
        let error = point_displacement(predicted, corrected, self.params.range);
        self.sum_sq += error * error;
        self.samples += 1;
    }

    /// True when moving from `predicted` to `corrected` is far beyond what corrections
    /// have been so far (`factor` times the current distance): the registration most
    /// likely slid into a wrong minimum.
    pub fn implausible(&self, predicted: &Pose, corrected: &Pose, factor: f64) -> bool {
        point_displacement(predicted, corrected, self.params.range) > factor * self.distance()
    }
}

/// Starting poses to retry a registration from, around `predicted`: the prediction
/// itself, then rotations about the map's vertical axis through the sensor by
/// `±step, ±2 step, ...` up to `max_deg` (fast turns are mostly yaw for ground and
/// handheld platforms).
pub fn yaw_hypotheses(predicted: &Pose, step_deg: f64, max_deg: f64) -> Vec<Pose> {
    let mut out = vec![*predicted];
    if step_deg <= 0.0 {
        return out;
    }
    let mut k = 1.0;
    while k * step_deg <= max_deg + 1e-9 {
        for sign in [1.0, -1.0] {
            let yaw = UnitQuaternion::from_axis_angle(
                &Vector3::z_axis(),
                (sign * k * step_deg).to_radians(),
            );
            out.push(Pose::from_parts(
                predicted.translation,
                yaw * predicted.rotation,
            ));
        }
        k += 1.0;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{rotation_distance, translation_distance};

    fn pose(x: f64, y: f64, yaw_deg: f64) -> Pose {
        Pose::new(
            Vector3::new(x, y, 0.0),
            Vector3::new(0.0, 0.0, yaw_deg.to_radians()),
        )
    }

    #[test]
    fn constant_velocity_extrapolates_a_steady_turn_exactly() {
        // A circle of radius 5 m at 0.2 rad/s: poses at t = 0, 0.5, 1.0 predict t = 2.0.
        let on_circle = |t: f64| {
            let a = 0.2 * t;
            Pose::new(
                Vector3::new(5.0 * a.sin(), 5.0 * (1.0 - a.cos()), 0.0),
                Vector3::new(0.0, 0.0, a),
            )
        };
        let mut model = ConstantVelocity::new();
        assert!(model.predict(0.0).is_none());
        for t in [0.0, 0.5, 1.0] {
            model.update(t, on_circle(t));
        }
        let predicted = model.predict(2.0).unwrap();
        let truth = on_circle(2.0);
        assert!(translation_distance(&predicted, &truth) < 1e-9);
        assert!(rotation_distance(&predicted, &truth) < 1e-12);
        let twist = model.velocity().unwrap();
        assert!((twist.angular.z - 0.2).abs() < 1e-12);
        // On a circle of radius 5 m at 0.2 rad/s the body moves forward at 1 m/s.
        assert!((twist.linear - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        // Half a step scaled twice is the step.
        let step = on_circle(0.0).inverse() * on_circle(1.0);
        let half = scale_motion(&step, 0.5);
        assert!(translation_distance(&(half * half), &step) < 1e-12);
    }

    #[test]
    fn forgetting_velocity_predicts_the_last_pose() {
        let mut model = ConstantVelocity::new();
        model.update(0.0, pose(0.0, 0.0, 0.0));
        model.update(1.0, pose(1.0, 0.0, 10.0));
        model.forget_velocity();
        assert_eq!(model.predict(2.0).unwrap(), pose(1.0, 0.0, 10.0));
    }

    #[test]
    fn point_displacement_is_translation_plus_chord() {
        let d = point_displacement(&pose(0.0, 0.0, 0.0), &pose(0.3, 0.4, 60.0), 10.0);
        // |t| = 0.5; chord of 60 deg at 10 m = 10 m.
        assert!((d - 10.5).abs() < 1e-9);
    }

    #[test]
    fn adaptive_threshold_follows_the_rms_correction() {
        let params = AdaptiveThresholdParams {
            min: 0.01,
            max: 100.0,
            ..Default::default()
        };
        let mut threshold = AdaptiveThreshold::new(params);
        assert_eq!(threshold.distance(), params.initial);
        let moved = pose(1.0, 0.0, 0.0);
        // Corrections of 0.3 and 0.4 m (pure translation): RMS 0.3536 m, times 3.
        threshold.observe(&pose(0.0, 0.0, 0.0), &pose(0.3, 0.0, 0.0), &moved);
        threshold.observe(&pose(0.0, 0.0, 0.0), &pose(0.0, 0.4, 0.0), &moved);
        let rms = ((0.09 + 0.16) / 2.0f64).sqrt();
        assert!((threshold.distance() - 3.0 * rms).abs() < 1e-12);
        // A standing sensor's correction is not sampled.
        threshold.observe(
            &pose(0.0, 0.0, 0.0),
            &pose(5.0, 0.0, 0.0),
            &Pose::identity(),
        );
        assert!((threshold.distance() - 3.0 * rms).abs() < 1e-12);
        assert!(threshold.implausible(&pose(0.0, 0.0, 0.0), &pose(3.5, 0.0, 0.0), 3.0));
        assert!(!threshold.implausible(&pose(0.0, 0.0, 0.0), &pose(0.5, 0.0, 0.0), 3.0));
    }

    #[test]
    fn adaptive_threshold_is_clamped() {
        let params = AdaptiveThresholdParams::default();
        let mut threshold = AdaptiveThreshold::new(params);
        threshold.observe(
            &Pose::identity(),
            &pose(50.0, 0.0, 0.0),
            &pose(1.0, 0.0, 0.0),
        );
        assert_eq!(threshold.distance(), params.max);
        assert!(
            AdaptiveThresholdParams {
                min: 2.0,
                max: 1.0,
                ..params
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn yaw_hypotheses_turn_about_the_vertical_through_the_sensor() {
        let predicted = pose(2.0, 3.0, 30.0);
        let hypotheses = yaw_hypotheses(&predicted, 15.0, 30.0);
        assert_eq!(hypotheses.len(), 5);
        assert_eq!(hypotheses[0], predicted);
        let yaws: Vec<f64> = hypotheses
            .iter()
            .map(|h| h.rotation.euler_angles().2.to_degrees())
            .collect();
        for (got, want) in yaws.iter().zip([30.0, 45.0, 15.0, 60.0, 0.0]) {
            assert!((got - want).abs() < 1e-9, "{yaws:?}");
        }
        assert!(
            hypotheses
                .iter()
                .all(|h| h.translation == predicted.translation)
        );
    }
}
