//! Scan-to-local-map odometry: each scan is predicted by a constant-velocity model,
//! registered (GICP) against a voxel map of recent keyframes with a correspondence
//! distance that adapts to how wrong the predictions have been, and retried from wider
//! hypotheses (a coarser scan and a larger distance, then yaw turns) when the result
//! is poor or the correction is more than the motion model allows.

use std::collections::{HashMap, VecDeque};

use serde::{Deserialize, Serialize};

use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{PackedSym3, Pose, extend_moved};
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::motion::{
    AdaptiveThreshold, AdaptiveThresholdParams, DeskewMode, Gyro, GyroParams, PosePredictor,
    SweepParams, yaw_hypotheses,
};
use kfmap_geometry::options::{InvalidOption, ensure, ensure_distance, ensure_ratio};
use kfmap_geometry::registration::{
    Fitness, PreparedCloud, RegistrationError, RegistrationParams, RegistrationResult,
    RobustKernel, align, overlap,
};
use kfmap_map::map::KeyframeDecider;

/// Odometry settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct OdometryParams {
    /// Registration of each scan (voxel size, iterations, kernel); its correspondence
    /// distance is replaced by the adaptive one.
    pub registration: RegistrationParams,
    /// The correspondence distance, adapted to the observed prediction errors.
    pub adaptive_distance: AdaptiveThresholdParams,
    /// When a scan joins the local map.
    pub local_map_decider: KeyframeDecider,
    /// Keyframes the local map holds.
    pub local_map_keyframes: usize,
    /// Local-map voxel edge, metres: each voxel keeps at most `local_map_voxel_points`
    /// points (the newest keyframes' first), so overlapping keyframes do not stack.
    pub local_map_voxel: f64,
    /// Points per local-map voxel, at most.
    pub local_map_voxel_points: usize,
    /// A registration is accepted at once when at least this share of the scan's points
    /// lie within `fit-distance` of the map...
    pub min_inlier_ratio: f64,
    /// The distance the overlap is judged at, metres (independent of the adaptive
    /// pairing distance, which may be wide).
    pub fit_distance: f64,
    /// ...and its correction from the prediction is at most this many adaptive
    /// distances (further means it most likely slid into a wrong minimum).
    pub max_correction: f64,
    /// Retry: the scan's voxel size times this for the coarse pass.
    pub coarse_voxel_factor: f64,
    /// Retry: the coarse pass's correspondence distance, metres.
    pub coarse_distance: f64,
    /// Which scans are deskewed with the motion model's twist, mid-scan: those with
    /// per-point times, and with `azimuth` also those without, timed by `sweep`
    /// (`auto` is `per-point` here; `kfmap bake` settles it from the scan format).
    pub deskew: DeskewMode,
    /// The spinning sensor's sweep, for per-point times from the azimuth.
    pub sweep: SweepParams,
    /// The gyro's part in the motion model, when the dataset has IMU samples.
    pub gyro: GyroParams,
    /// Retry: yaw hypotheses every this many degrees...
    pub yaw_step_deg: f64,
    /// ...up to this far either side of the prediction (0 turns them off).
    pub yaw_max_deg: f64,
}

impl Default for OdometryParams {
    fn default() -> Self {
        Self {
            // Converge tightly: every step's residual error stays in the trajectory.
            registration: RegistrationParams {
                voxel_size: 0.5,
                translation_eps: 1e-4,
                rotation_eps: 0.01f64.to_radians(),
                max_iterations: 30,
                ..RegistrationParams::default()
            },
            adaptive_distance: AdaptiveThresholdParams::default(),
            // About 40 m of map: 8 keyframes 1 m apart left 43.5 cm keyframe ATE on the
            // simulated campus lap, 20 keyframes 2 m apart 2.2 cm (odometry alone).
            local_map_decider: KeyframeDecider {
                min_translation: 2.0,
                min_rotation_deg: 15.0,
            },
            local_map_keyframes: 20,
            local_map_voxel: 1.0,
            local_map_voxel_points: 20,
            min_inlier_ratio: 0.7,
            fit_distance: 0.5,
            max_correction: 3.0,
            coarse_voxel_factor: 2.0,
            coarse_distance: 3.0,
            deskew: DeskewMode::Auto,
            sweep: SweepParams::default(),
            gyro: GyroParams::default(),
            yaw_step_deg: 20.0,
            yaw_max_deg: 60.0,
        }
    }
}

impl OdometryParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        self.registration.validate()?;
        self.adaptive_distance.validate()?;
        self.local_map_decider.validate()?;
        self.gyro.validate()?;
        self.sweep.validate()?;
        ensure(
            self.local_map_keyframes >= 1,
            "local-map-keyframes",
            self.local_map_keyframes,
            "at least 1",
        )?;
        ensure(
            self.local_map_voxel.is_finite() && self.local_map_voxel > 0.0,
            "local-map-voxel",
            self.local_map_voxel,
            "a finite size > 0 m",
        )?;
        ensure(
            self.local_map_voxel_points >= 1,
            "local-map-voxel-points",
            self.local_map_voxel_points,
            "at least 1",
        )?;
        ensure_ratio("min-inlier-ratio", self.min_inlier_ratio)?;
        ensure_distance("fit-distance", self.fit_distance)?;
        ensure(
            self.max_correction.is_finite() && self.max_correction > 0.0,
            "max-correction",
            self.max_correction,
            "> 0",
        )?;
        ensure(
            self.coarse_voxel_factor.is_finite() && self.coarse_voxel_factor >= 1.0,
            "coarse-voxel-factor",
            self.coarse_voxel_factor,
            ">= 1",
        )?;
        ensure_distance("coarse-distance", self.coarse_distance)?;
        ensure(
            self.yaw_max_deg.is_finite()
                && self.yaw_max_deg >= 0.0
                && self.yaw_step_deg.is_finite()
                && (self.yaw_step_deg > 0.0 || self.yaw_max_deg == 0.0),
            "yaw-step-deg",
            self.yaw_step_deg,
            "> 0 deg (or yaw-max-deg = 0)",
        )
    }
}

/// How a scan's pose was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum OdometryOutcome {
    /// The first scan: the odometry frame's origin.
    First,
    /// Registered from the prediction and accepted at once.
    Tracked,
    /// The first registration was poor; a wider hypothesis gave the accepted pose.
    Recovered,
    /// No hypothesis registered well; the best one was kept (the scan may be off).
    Poor,
}

/// Odometry state: the motion model, the adaptive distance and the local map.
pub struct Odometry {
    params: OdometryParams,
    motion: PosePredictor,
    threshold: AdaptiveThreshold,
    /// Local-map keyframes: pose, downsampled points and their covariances (odometry
    /// frame).
    keyframes: VecDeque<LocalKeyframe>,
    local_map: Option<PreparedCloud>,
    /// Voxel edge of the finer sample each step also returns (`None`: none).
    fine_voxel: Option<f64>,
}

/// One odometry step.
pub struct OdometryStep {
    /// `T_odom_scan`: the sensor at the scan's stamp.
    pub pose: Pose,
    /// The pose of `prepared`'s frame: the sensor mid-scan for a deskewed scan, else
    /// `pose`.
    pub cloud_pose: Pose,
    /// The accepted registration against the local map (`None` for the first scan).
    pub registration: Option<RegistrationResult>,
    /// How the pose was found.
    pub outcome: OdometryOutcome,
    /// The scan as registered (deskewed, downsampled, covariances, tree; frame at
    /// `cloud_pose`), for callers that keep it.
    pub prepared: PreparedCloud,
    /// The deskewed scan on a finer voxel grid (frame at `cloud_pose`), when asked for
    /// by [`Odometry::keep_fine_points`]; else empty.
    pub fine: Vec<[f32; 3]>,
}

impl Odometry {
    /// Starts at `T_odom_scan0 = identity`; `imu` (on the scans' clock, may be empty)
    /// gives the motion model its rotation when `gyro` is enabled.
    pub fn new(params: OdometryParams, imu: Vec<ImuSample>) -> Result<Self, RegistrationError> {
        params.validate()?;
        let gyro = (params.gyro.enabled && !imu.is_empty())
            .then(|| Gyro::new(imu, params.gyro))
            .transpose()?;
        Ok(Self {
            params,
            motion: PosePredictor::new(gyro),
            threshold: AdaptiveThreshold::new(params.adaptive_distance),
            keyframes: VecDeque::new(),
            local_map: None,
            fine_voxel: None,
        })
    }

    /// Each step also returns the deskewed scan on a voxel grid of this edge (metres),
    /// for the joint refinement.
    pub fn keep_fine_points(&mut self, voxel: f64) {
        self.fine_voxel = Some(voxel);
    }

    /// Registers the next scan (sensor frame, taken at `stamp` seconds) and returns its
    /// pose.
    pub fn push(
        &mut self,
        stamp: f64,
        scan: &PointCloud,
    ) -> Result<OdometryStep, RegistrationError> {
        let reg = self.params.registration;
        let timed;
        let scan = if self.params.deskew == DeskewMode::Azimuth && scan.time.is_none() {
            let mut copy = scan.clone();
            self.params.sweep.time_scan(&mut copy);
            timed = copy;
            &timed
        } else {
            scan
        };
        let deskew = self.params.deskew.uses_point_times();
        let mid = self.motion.mid_scan(scan, stamp, deskew)?;
        let scan = mid.deskewed.as_ref().unwrap_or(scan);
        let prepared = PreparedCloud::new(scan, &reg, "scan")?;
        let fine = match self.fine_voxel {
            Some(voxel) => {
                scan.voxel_downsample(voxel)
                    .map_err(|e| RegistrationError::Downsample {
                        which: "scan",
                        message: e.to_string(),
                    })?
                    .points
            }
            None => Vec::new(),
        };
        let tracked_at = stamp + mid.offset;
        let predicted = self.motion.predict(tracked_at);
        let (cloud_pose, registration, outcome) = match (&self.local_map, predicted) {
            (Some(map), Some(predicted)) => {
                let (result, outcome) = self.register(map, scan, &prepared, &predicted)?;
                let motion = self.motion.last().expect("predicted").inverse() * result.pose;
                self.threshold.observe(&predicted, &result.pose, &motion);
                (result.pose, Some(result), outcome)
            }
            _ => (Pose::identity(), None, OdometryOutcome::First),
        };
        if outcome == OdometryOutcome::Poor {
            // The motion since the last good scan is unknown: do not extrapolate it.
            self.motion.forget_velocity();
        }
        let trusted = outcome == OdometryOutcome::Tracked;
        self.motion.update(tracked_at, cloud_pose, trusted);
        self.grow_local_map(&cloud_pose, &prepared)?;
        let pose = self.motion.carry(&cloud_pose, tracked_at, stamp);
        Ok(OdometryStep {
            pose,
            cloud_pose,
            registration,
            outcome,
            prepared,
            fine,
        })
    }

    /// The gyro bias learned so far, IMU frame, rad/s (`None` without a gyro).
    pub fn gyro_bias(&self) -> Option<nalgebra::Vector3<f64>> {
        self.motion.gyro().map(|g| g.bias())
    }

    /// The registration ladder: from the prediction at the adaptive distance; when that
    /// is poor, a coarse pass at a large distance from the prediction and from each yaw
    /// hypothesis, each refined; the result lying best on the map wins.
    fn register(
        &self,
        map: &PreparedCloud,
        scan: &PointCloud,
        prepared: &PreparedCloud,
        predicted: &Pose,
    ) -> Result<(RegistrationResult, OdometryOutcome), RegistrationError> {
        let p = &self.params;
        let fine = RegistrationParams {
            max_correspondence_distance: self.threshold.distance(),
            ..p.registration
        };
        let assess = |result: RegistrationResult| {
            let fit = overlap(map, prepared, &result.pose, p.fit_distance);
            (result, fit)
        };
        let first = align(map, prepared, predicted, &fine).ok().map(assess);
        if let Some((result, fit)) = &first
            && self.good(result, fit)
            && !self
                .threshold
                .implausible(predicted, &result.pose, p.max_correction)
        {
            return Ok((*result, OdometryOutcome::Tracked));
        }
        let coarse = RegistrationParams {
            voxel_size: p.registration.voxel_size * p.coarse_voxel_factor,
            max_correspondence_distance: p.coarse_distance,
            kernel: RobustKernel::Cauchy {
                delta: p.coarse_distance / 3.0,
            },
            ..p.registration
        };
        let coarse_scan = PreparedCloud::new(scan, &coarse, "coarse scan")?;
        let mut best = first;
        for start in yaw_hypotheses(predicted, p.yaw_step_deg, p.yaw_max_deg) {
            let Ok(rough) = align(map, &coarse_scan, &start, &coarse) else {
                continue;
            };
            let Ok(refined) = align(map, prepared, &rough.pose, &fine) else {
                continue;
            };
            let candidate = assess(refined);
            if best
                .as_ref()
                .is_none_or(|b| score(&candidate.1) > score(&b.1))
            {
                best = Some(candidate);
            }
        }
        let (result, fit) = best.ok_or(RegistrationError::NoCorrespondences {
            max_distance: p.coarse_distance,
        })?;
        let outcome = if self.good(&result, &fit) {
            OdometryOutcome::Recovered
        } else {
            OdometryOutcome::Poor
        };
        Ok((result, outcome))
    }

    /// Lies on the map (overlap at the fit distance) and is not degenerate.
    fn good(&self, result: &RegistrationResult, fit: &Fitness) -> bool {
        fit.inlier_ratio >= self.params.min_inlier_ratio && !result.degenerate
    }

    /// Adds the scan as a local-map keyframe when the decider says so and rebuilds the
    /// map: newest keyframes first, each voxel capped, so it stays current and bounded.
    fn grow_local_map(
        &mut self,
        pose: &Pose,
        prepared: &PreparedCloud,
    ) -> Result<(), RegistrationError> {
        let decider = &self.params.local_map_decider;
        if !decider.should_create(self.keyframes.iter().map(|k| &k.pose), pose) {
            return Ok(());
        }
        self.keyframes
            .push_back(LocalKeyframe::moved(pose, prepared));
        while self.keyframes.len() > self.params.local_map_keyframes {
            self.keyframes.pop_front();
        }
        // Keyframe points are voxelized already; averaging them again on a second grid
        // would misplace surfaces, so voxels only cap how many points they keep.
        let cell = self.params.local_map_voxel;
        let cap = self.params.local_map_voxel_points;
        let mut counts: HashMap<[i32; 3], usize> = HashMap::new();
        let mut merged = Vec::new();
        let mut covariances = Vec::new();
        for keyframe in self.keyframes.iter().rev() {
            for (p, c) in keyframe.points.iter().zip(&keyframe.covariances) {
                let key = p.map(|c| (c as f64 / cell).floor() as i32);
                let count = counts.entry(key).or_insert(0);
                if *count < cap {
                    *count += 1;
                    merged.push(*p);
                    covariances.push(*c);
                }
            }
        }
        self.local_map = Some(PreparedCloud::from_parts(merged, covariances, "local map")?);
        Ok(())
    }
}

/// A local-map keyframe in the odometry frame.
struct LocalKeyframe {
    pose: Pose,
    points: Vec<[f32; 3]>,
    /// Each point's covariance as estimated in its scan, rotated with it: estimated
    /// once per scan instead of again over the merged map at every rebuild.
    covariances: Vec<PackedSym3>,
}

impl LocalKeyframe {
    /// `prepared` (a scan registered at `pose`) moved into the odometry frame.
    fn moved(pose: &Pose, prepared: &PreparedCloud) -> Self {
        let (mut points, mut covariances) = (Vec::new(), Vec::new());
        extend_moved(
            pose,
            &prepared.points,
            &prepared.covariances,
            &mut points,
            &mut covariances,
        );
        Self {
            pose: *pose,
            points,
            covariances,
        }
    }
}

/// Ranks registrations by how they lie on the map: overlap first, then residuals.
fn score(fit: &Fitness) -> f64 {
    fit.inlier_ratio - 0.1 * fit.rmse
}
