//! The client-side tracker (docs/DESIGN.md#tracking): predicts each scan's pose with a
//! constant-velocity model (rotation from the gyro when it has an IMU log), deskews
//! scans that carry per-point times into their mid-scan frame, bounds the correction
//! localization may make by how wrong the predictions have been (an adaptive gate,
//! after KISS-ICP), and follows the status: a `lost` scan adopts no pose and the
//! tracker keeps predicting; it is `ok` again once scans agree with the prediction for
//! `recover-after` scans in a row. A tracker never wanders: after `lost-after-unfit`
//! adopted scans in a row that do not fit the map it says `lost` (and relocalizes, with
//! the IMU's tilt when it has one) instead of following its own prediction.

use kfmap_protocol::ScanPayload;
use kfmap_shared::cloud::PointCloud;
use kfmap_shared::geometry::Pose;
use kfmap_shared::imu::ImuSample;
use kfmap_shared::motion::{
    AdaptiveThreshold, AdaptiveThresholdParams, Gyro, GyroError, GyroParams, PosePredictor,
    point_displacement,
};
use kfmap_shared::tracking::{CORRECTION_RANGE_M, Reasons, ScanHealth, TrackingStatus};

use kfmap_shared::place::{RelocalizeStatus, levelling};

use crate::{Client, ClientError, LocalizeOptions, Localized, RelocalizeOptions};

/// Tracker settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerOptions {
    /// How each scan is localized (its `max_correction` is set by the tracker).
    pub localize: LocalizeOptions,
    /// Let the server run the checks and retry ladder (`Localize`) instead of this
    /// process (cov2cov answers); both decide alike.
    pub server_side: bool,
    /// The correction gate: `sigmas` times the RMS of past corrections (metres of
    /// point displacement at [`kfmap_shared::tracking::CORRECTION_RANGE_M`], whatever
    /// `range` says: the ladder measures corrections there), within `[min, max]`.
    pub gate: AdaptiveThresholdParams,
    /// Scans in a row that must be adopted after `lost` before the status is `ok`
    /// again (until then `degraded`, reason `recovering`).
    pub recover_after: usize,
    /// Deskew scans that carry per-point times ([`Tracker::track_cloud`]).
    pub deskew: bool,
    /// Ask the server where a scan is (`Relocalize`, no guess) when it is `lost`, and
    /// restart tracking there when the server finds one place.
    pub relocalize_when_lost: bool,
    /// Adopted scans in a row that do not fit the map (`degraded` for not converging,
    /// low fitness or a fitness drop) after which the tracker is `lost` (reason
    /// `unfit-streak`), and every further unfitting scan too until one is `ok` again.
    pub lost_after_unfit: usize,
}

impl Default for TrackerOptions {
    fn default() -> Self {
        Self {
            localize: LocalizeOptions::default(),
            server_side: false,
            gate: AdaptiveThresholdParams {
                initial: 3.0,
                min: 1.0,
                max: 10.0,
                range: CORRECTION_RANGE_M,
                min_motion: 0.1,
                sigmas: 3.0,
            },
            recover_after: 2,
            deskew: true,
            relocalize_when_lost: false,
            // Half a second at 10 Hz: long enough for a few hard scans (a turn, an
            // open square), short enough that a wrong pose is not followed for long.
            lost_after_unfit: 5,
        }
    }
}

/// One tracked scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedScan {
    /// The scan's time, seconds.
    pub t: f64,
    /// The motion model's prediction the scan was localized from, `T_map_sensor`.
    pub predicted: Pose,
    /// The correction bound used, metres (`None` before the motion model has a
    /// velocity).
    pub max_correction: Option<f64>,
    /// The localized pose (the prediction when `lost`) and its health, with the
    /// tracker's status (a scan adopted while recovering is `degraded`).
    pub localized: Localized,
}

/// Follows a sensor through a scan sequence against a map server.
#[derive(Debug, Clone)]
pub struct Tracker {
    options: TrackerOptions,
    /// Where the first scan is localized from; `None`: it is relocalized.
    initial: Option<Pose>,
    /// Adopted poses (at the scans' mid-scan times when deskewed).
    motion: PosePredictor,
    gate: AdaptiveThreshold,
    /// Scans lost since the last adopted one.
    lost_streak: usize,
    /// Scans adopted in a row since the last `lost` (saturating).
    adopted_streak: usize,
    /// Inlier ratio of the last adopted scan.
    last_inlier_ratio: Option<f64>,
    /// Scans in a row that did not fit the map, since the last `ok` or relocalized one.
    unfit_streak: usize,
}

/// Seconds of accelerometer before a scan that give its tilt for relocalization.
const TILT_WINDOW_S: f64 = 1.0;

/// True when a scan was adopted without fitting the map: its registration did not
/// converge or pairs too little of it (degeneracy alone is a corridor, not a misfit).
fn unfit(health: &ScanHealth) -> bool {
    health.status == TrackingStatus::Degraded
        && [
            Reasons::NOT_CONVERGED,
            Reasons::LOW_FITNESS,
            Reasons::FITNESS_DROP,
        ]
        .iter()
        .any(|r| health.reasons.contains(*r))
}

impl Tracker {
    /// A tracker whose first scan is localized from `initial` (`T_map_sensor`, e.g. a
    /// relocalization or a known start), with no bound on its correction.
    pub fn new(initial: Pose, options: TrackerOptions) -> Self {
        Self::starting(Some(initial), options)
    }

    /// A tracker with no idea where it starts: the first scan is relocalized (and so is
    /// every `lost` scan after it, whatever `relocalize_when_lost` says).
    pub fn relocalizing(options: TrackerOptions) -> Self {
        Self::starting(
            None,
            TrackerOptions {
                relocalize_when_lost: true,
                ..options
            },
        )
    }

    fn starting(initial: Option<Pose>, options: TrackerOptions) -> Self {
        Self {
            options,
            initial,
            motion: PosePredictor::new(None),
            // Corrections are compared with the ladder's, measured at its range.
            gate: AdaptiveThreshold::new(AdaptiveThresholdParams {
                range: CORRECTION_RANGE_M,
                ..options.gate
            }),
            lost_streak: 0,
            adopted_streak: usize::MAX,
            last_inlier_ratio: None,
            unfit_streak: 0,
        }
    }

    /// The same tracker predicting rotation with `gyro` (an IMU log on the scans' clock,
    /// its bias learned from the scans adopted).
    pub fn with_gyro(mut self, gyro: Gyro) -> Self {
        self.motion = PosePredictor::new(Some(gyro));
        self
    }

    /// Adds live IMU samples (on the scans' clock, after the last) to the gyro, made
    /// with `params` by the first call; samples more than `keep_s` seconds older than
    /// the newest are forgotten (a lost stretch longer than that is predicted without
    /// the gyro). Returns the samples refused: not after the last, or not finite.
    pub fn push_imu(
        &mut self,
        samples: &[ImuSample],
        params: GyroParams,
        keep_s: f64,
    ) -> Result<usize, GyroError> {
        if self.motion.gyro().is_none() {
            self.motion.set_gyro(Gyro::new(Vec::new(), params)?);
        }
        let Some(gyro) = self.motion.gyro_mut() else {
            return Ok(0);
        };
        let refused = gyro.extend(samples);
        if let Some(newest) = samples
            .iter()
            .map(|s| s.t)
            .filter(|t| t.is_finite())
            .reduce(f64::max)
        {
            gyro.forget_before(newest - keep_s);
        }
        Ok(refused)
    }

    /// The gyro (`None` without one): to carry a live log over to a new tracker.
    pub fn gyro(&self) -> Option<&Gyro> {
        self.motion.gyro()
    }

    /// The gyro's bias estimate, IMU frame, rad/s (`None` without a gyro).
    pub fn gyro_bias(&self) -> Option<nalgebra::Vector3<f64>> {
        self.motion.gyro().map(|g| g.bias())
    }

    /// The pose expected at time `t` (seconds): the last adopted pose carried forward
    /// at the last velocity (the initial pose before any; identity without one).
    pub fn predict(&self, t: f64) -> Pose {
        self.motion
            .predict(t)
            .or(self.initial)
            .unwrap_or_else(Pose::identity)
    }

    /// The correction bound for the next scan, metres: `None` until a pose was
    /// adopted; it widens with every scan lost since the last adopted one.
    pub fn max_correction(&self) -> Option<f64> {
        self.motion
            .last()
            .map(|_| self.gate.distance() * (1 + self.lost_streak) as f64)
    }

    /// Localizes `scan`, taken at time `t` (seconds), from the prediction, and updates
    /// the tracker.
    pub fn track(
        &mut self,
        client: &mut Client,
        scan: &ScanPayload,
        t: f64,
    ) -> Result<TrackedScan, ClientError> {
        let predicted = self.predict(t);
        let max_correction = self.max_correction();
        let options = LocalizeOptions {
            max_correction,
            expected_inlier_ratio: self.last_inlier_ratio,
            stamp: Some(t),
            ..self.options.localize
        };
        if self.initial.is_none() && self.motion.last().is_none() {
            // Nowhere to localize from yet: only the map can say where this is.
            let lost = Localized {
                pose: predicted,
                health: ScanHealth::no_fit(0, 0),
            };
            return self.relocalize(client, scan, t, predicted, None, lost);
        }
        let mut localized = if self.options.server_side {
            client.localize(scan, &predicted, &options)?
        } else {
            client.localize_client_side(scan, &predicted, &options)?
        };
        self.give_up_when_unfit(&predicted, &mut localized);
        if localized.health.status == TrackingStatus::Lost && self.options.relocalize_when_lost {
            return self.relocalize(client, scan, t, predicted, max_correction, localized);
        }
        Ok(self.observe(t, predicted, max_correction, localized))
    }

    /// Counts scans that do not fit the map and turns the `lost-after-unfit`th in a row,
    /// and every unfitting one after it, into `lost` at the prediction.
    fn give_up_when_unfit(&mut self, predicted: &Pose, localized: &mut Localized) {
        if localized.health.status == TrackingStatus::Ok {
            self.unfit_streak = 0;
            return;
        }
        if !unfit(&localized.health) {
            return;
        }
        self.unfit_streak += 1;
        if self.unfit_streak >= self.options.lost_after_unfit.max(1) {
            localized.pose = *predicted;
            localized.health.status = TrackingStatus::Lost;
            localized.health.reasons.insert(Reasons::UNFIT_STREAK);
        }
    }

    /// The sensor's tilt at time `t` from the IMU's accelerometer (`R_map_sensor` up
    /// to yaw, map levelled on gravity), when the tracker has an IMU log covering it.
    pub fn tilt(&self, t: f64) -> Option<nalgebra::UnitQuaternion<f64>> {
        let up = self.motion.gyro()?.up(t, TILT_WINDOW_S)?;
        Some(levelling(&up))
    }

    /// Asks the server where `scan` is; when it finds one place, tracking restarts
    /// there (the scan `degraded`: relocalized, recovering); otherwise the scan is
    /// `lost` as `lost` says.
    fn relocalize(
        &mut self,
        client: &mut Client,
        scan: &ScanPayload,
        t: f64,
        predicted: Pose,
        max_correction: Option<f64>,
        lost: Localized,
    ) -> Result<TrackedScan, ClientError> {
        let options = RelocalizeOptions {
            max_pair_dist: self.options.localize.max_pair_dist,
            max_iterations: self.options.localize.max_iterations,
            tilt: self.tilt(t),
        };
        let place = client.relocalize(scan, &options)?;
        let (RelocalizeStatus::Found, Some(pose)) = (place.status, place.pose) else {
            return Ok(self.observe(t, predicted, max_correction, lost));
        };
        self.motion.restart();
        self.adopted_streak = 0;
        self.unfit_streak = 0;
        let localized = Localized {
            pose,
            health: ScanHealth {
                status: TrackingStatus::Degraded,
                reasons: Reasons::RELOCALIZED,
                inlier_ratio: place.inlier_ratio,
                rmse: place.rmse,
                degenerate: place.degenerate,
                converged: place.converged,
                covariance: place.covariance,
                correction: point_displacement(&predicted, &pose, CORRECTION_RANGE_M),
                ..ScanHealth::no_fit(lost.health.registrations, lost.health.iterations)
            },
        };
        Ok(self.observe(t, predicted, None, localized))
    }

    /// Localizes `cloud` (sensor frame, stamped `stamp` seconds): deskewed into its
    /// mid-scan frame first when it carries per-point times (and `deskew` is on), tracked
    /// there, and reported at the stamp like an undistorted scan.
    pub fn track_cloud(
        &mut self,
        client: &mut Client,
        cloud: &PointCloud,
        stamp: f64,
    ) -> Result<TrackedScan, ClientError> {
        let mid = self
            .motion
            .mid_scan(cloud, stamp, self.options.deskew)
            .map_err(kfmap_shared::registration::RegistrationError::from)?;
        let cloud = mid.deskewed.as_ref().unwrap_or(cloud);
        let scan = ScanPayload {
            points: &cloud.points,
            view_dirs: None,
            covariances: None,
        };
        let tracked_at = stamp + mid.offset;
        let mut tracked = self.track(client, &scan, tracked_at)?;
        if mid.offset != 0.0 {
            tracked.t = stamp;
            tracked.predicted = self.motion.carry(&tracked.predicted, tracked_at, stamp);
            tracked.localized.pose = self
                .motion
                .carry(&tracked.localized.pose, tracked_at, stamp);
        }
        Ok(tracked)
    }

    /// Records a scan whose localization failed (e.g. the server did not answer) as
    /// `lost`, with the prediction as its pose.
    pub fn unanswered(&mut self, t: f64) -> TrackedScan {
        let predicted = self.predict(t);
        let max_correction = self.max_correction();
        let localized = Localized {
            pose: predicted,
            health: ScanHealth::no_fit(0, 0),
        };
        self.observe(t, predicted, max_correction, localized)
    }

    /// Updates the tracker with a scan localized from `predicted` (what
    /// [`Self::track`] does after localizing), and returns it with the tracker's
    /// status.
    pub fn observe(
        &mut self,
        t: f64,
        predicted: Pose,
        max_correction: Option<f64>,
        mut localized: Localized,
    ) -> TrackedScan {
        if localized.health.status == TrackingStatus::Lost {
            // Keep predicting from the last adopted pose at the last velocity.
            self.lost_streak += 1;
            self.adopted_streak = 0;
        } else {
            self.adopted_streak = self.adopted_streak.saturating_add(1);
            if self.adopted_streak < self.options.recover_after {
                localized.health.reasons.insert(Reasons::RECOVERING);
                localized.health.status = TrackingStatus::Degraded;
            }
            if let Some(last) = self.motion.last() {
                let moved = last.inverse() * localized.pose;
                self.gate.observe(&predicted, &localized.pose, &moved);
            }
            self.lost_streak = 0;
            self.last_inlier_ratio = Some(localized.health.inlier_ratio);
            let trusted = localized.health.status == TrackingStatus::Ok;
            self.motion.update(t, localized.pose, trusted);
        }
        TrackedScan {
            t,
            predicted,
            max_correction,
            localized,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_shared::geometry::translation_distance;

    fn at(x: f64) -> Pose {
        Pose::translation(x, 0.0, 0.0)
    }

    fn scan(pose: Pose, status: TrackingStatus, inlier_ratio: f64) -> Localized {
        Localized {
            pose,
            health: ScanHealth {
                status,
                reasons: Reasons::NONE,
                inlier_ratio,
                ..ScanHealth::no_fit(1, 3)
            },
        }
    }

    #[test]
    fn a_streak_of_scans_that_do_not_fit_becomes_lost_until_one_is_ok() {
        let options = TrackerOptions::default();
        let mut tracker = Tracker::new(at(0.0), options);
        let unfit = |reasons: Reasons| Localized {
            health: ScanHealth {
                reasons,
                ..scan(at(5.0), TrackingStatus::Degraded, 0.4).health
            },
            ..scan(at(5.0), TrackingStatus::Degraded, 0.4)
        };
        let predicted = at(1.0);
        // Degenerate but converged and fitting (a corridor) is never counted.
        for _ in 0..3 * options.lost_after_unfit {
            let mut corridor = unfit(Reasons::DEGENERATE);
            tracker.give_up_when_unfit(&predicted, &mut corridor);
            assert_eq!(corridor.health.status, TrackingStatus::Degraded);
        }
        for k in 1..=options.lost_after_unfit + 2 {
            let reasons = [
                Reasons::NOT_CONVERGED,
                Reasons::LOW_FITNESS,
                Reasons::FITNESS_DROP,
            ][k % 3]
                | Reasons::DEGENERATE;
            let mut localized = unfit(reasons);
            tracker.give_up_when_unfit(&predicted, &mut localized);
            if k < options.lost_after_unfit {
                assert_eq!(
                    localized.health.status,
                    TrackingStatus::Degraded,
                    "scan {k}"
                );
                assert_eq!(localized.pose, at(5.0));
            } else {
                // From the streak's length on: lost at the prediction, with the reason.
                assert_eq!(localized.health.status, TrackingStatus::Lost, "scan {k}");
                assert!(localized.health.reasons.contains(Reasons::UNFIT_STREAK));
                assert_eq!(localized.pose, predicted);
            }
        }
        // An ok scan ends the streak: the next unfitting one is degraded again.
        let mut ok = scan(at(1.0), TrackingStatus::Ok, 0.9);
        tracker.give_up_when_unfit(&predicted, &mut ok);
        let mut again = unfit(Reasons::NOT_CONVERGED);
        tracker.give_up_when_unfit(&predicted, &mut again);
        assert_eq!(again.health.status, TrackingStatus::Degraded);
    }

    #[test]
    fn a_lost_scan_keeps_predicting_and_recovery_needs_scans_that_agree_again() {
        let mut tracker = Tracker::new(at(0.0), TrackerOptions::default());
        assert_eq!(tracker.predict(0.0), at(0.0));
        assert_eq!(tracker.max_correction(), None, "no motion model yet");
        let first = tracker.observe(0.0, at(0.0), None, scan(at(0.1), TrackingStatus::Ok, 0.9));
        assert_eq!(first.localized.health.status, TrackingStatus::Ok);
        tracker.observe(
            1.0,
            at(0.1),
            Some(3.0),
            scan(at(1.1), TrackingStatus::Ok, 0.9),
        );
        // Constant velocity: 1 m/s along x.
        assert!(translation_distance(&tracker.predict(2.0), &at(2.1)) < 1e-12);
        let bound = tracker.max_correction().unwrap();

        // A lost scan adopts nothing: the prediction carries on at the same velocity and
        // the bound widens with the time since the last adopted scan.
        let lost = tracker.observe(
            2.0,
            at(2.1),
            Some(bound),
            scan(at(2.1), TrackingStatus::Lost, 0.9),
        );
        assert_eq!(lost.localized.health.status, TrackingStatus::Lost);
        assert!(translation_distance(&tracker.predict(3.0), &at(3.1)) < 1e-12);
        assert_eq!(tracker.max_correction(), Some(2.0 * bound));

        // The first scan adopted after it is degraded (recovering), the next one ok.
        let back = tracker.observe(
            3.0,
            at(3.1),
            Some(2.0 * bound),
            scan(at(3.12), TrackingStatus::Ok, 0.9),
        );
        assert_eq!(back.localized.health.status, TrackingStatus::Degraded);
        assert!(back.localized.health.reasons.contains(Reasons::RECOVERING));
        let ok = tracker.observe(
            4.0,
            at(4.12),
            Some(bound),
            scan(at(4.1), TrackingStatus::Ok, 0.9),
        );
        assert_eq!(ok.localized.health.status, TrackingStatus::Ok);
        assert_eq!(tracker.max_correction(), Some(tracker.gate.distance()));
    }

    #[test]
    fn the_gate_follows_how_wrong_the_predictions_were() {
        let options = TrackerOptions::default();
        let mut tracker = Tracker::new(at(0.0), options);
        assert_eq!(tracker.gate.distance(), options.gate.initial);
        // Steady 1 m steps, each prediction 0.2 m short of where the scan landed.
        for i in 0..10 {
            let t = i as f64;
            let predicted = tracker.predict(t);
            // The first scan lands where it was predicted.
            let landed = if i == 0 {
                at(0.0)
            } else {
                predicted * Pose::translation(0.2, 0.0, 0.0)
            };
            tracker.observe(
                t,
                predicted,
                tracker.max_correction(),
                scan(landed, TrackingStatus::Ok, 0.9),
            );
        }
        // 3 sigma of 0.2 m corrections is 0.6 m: clamped to the 1 m minimum.
        assert_eq!(tracker.max_correction(), Some(options.gate.min));
    }

    #[test]
    fn a_failed_request_counts_as_lost() {
        let mut tracker = Tracker::new(at(5.0), TrackerOptions::default());
        let failed = tracker.unanswered(0.0);
        assert_eq!(failed.localized.health.status, TrackingStatus::Lost);
        assert_eq!(failed.localized.pose, at(5.0));
        assert_eq!(tracker.predict(1.0), at(5.0));
    }
}
