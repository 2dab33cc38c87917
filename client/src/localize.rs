//! Localization of one scan against the server: server-side (`Localize`, for thin
//! clients) or client-side (this process iterates the shared GICP solver over
//! `Cov2Cov` answers). Both run the same checks and retry ladder
//! ([`kfmap_geometry::tracking::localize_scan`]) on the same pairings, so they land on the
//! same pose with the same health.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::{RegistrationError, solve_pose};
use kfmap_geometry::tracking::{
    Expectation, PreparedParts, PreparedScan, ScanHealth, TrackingParams, localize_scan,
};
use kfmap_protocol::{
    Cov2CovMode, FLAG_STAMPED, RequestHeader, RequestKind, ScanPayload, correspondences_from_wire,
    localize_stage, pose_to_wire, read_localized,
};

use crate::{Client, ClientError};

/// Localization settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizeOptions {
    /// Iterations per registration at most.
    pub max_iterations: u32,
    /// Largest pairing distance, metres.
    pub max_pair_dist: f32,
    /// Cov2cov mode (`MapDefault`: the server's choice).
    pub mode: Cov2CovMode,
    /// The largest correction from the guess the caller's motion model allows: metres
    /// of translation plus the chord a point at
    /// [`kfmap_geometry::tracking::CORRECTION_RANGE_M`] sweeps; `None` for no bound (no
    /// motion model yet). Sent as f32.
    pub max_correction: Option<f64>,
    /// The inlier ratio the caller expects (e.g. that of the scans before); a first
    /// registration well below it is retried from wider hypotheses. Sent as f32.
    pub expected_inlier_ratio: Option<f64>,
    /// Checks and retry ladder of client-side localization (server-side localization
    /// uses the server's `[tracking]`, the same defaults). Scan covariances are
    /// estimated with the server's `[covariance]` either way.
    pub tracking: TrackingParams,
    /// The scan's time, seconds on the IMU's clock: server-side localization then adds
    /// the adopted pose to the session's motion, which its gravity pool removes from
    /// the IMU windows.
    pub stamp: Option<f64>,
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            max_pair_dist: 1.0,
            mode: Cov2CovMode::MapDefault,
            max_correction: None,
            expected_inlier_ratio: None,
            tracking: TrackingParams::default(),
            stamp: None,
        }
    }
}

impl LocalizeOptions {
    /// The expectation as it travels (f32), so both sides compare alike.
    fn expectation(&self) -> Expectation {
        let wire = |v: Option<f64>| v.filter(|v| *v > 0.0).map(|v| v as f32 as f64);
        Expectation {
            max_correction: wire(self.max_correction),
            inlier_ratio: wire(self.expected_inlier_ratio.map(|e| e.min(1.0))),
        }
    }
}

/// A localized scan: the pose and its health.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localized {
    /// `T_map_sensor`; the guess when `health.status` is `Lost`.
    pub pose: Pose,
    /// Status, fitness, degeneracy, covariance.
    pub health: ScanHealth,
}

impl Client {
    /// Server-side localization of `scan` from `guess` (the server's checks and retry
    /// ladder; a scan that fails them comes back `Lost` with the guess as its pose).
    pub fn localize(
        &mut self,
        scan: &ScanPayload,
        guess: &Pose,
        options: &LocalizeOptions,
    ) -> Result<Localized, ClientError> {
        let expected = options.expectation();
        let header = RequestHeader {
            kind: RequestKind::Localize as u32,
            pose: pose_to_wire(guess),
            max_iterations: options.max_iterations,
            max_pair_dist: options.max_pair_dist,
            max_correction: expected.max_correction.unwrap_or(0.0) as f32,
            expected_inlier_ratio: expected.inlier_ratio.unwrap_or(0.0) as f32,
            mode: options.mode as u32,
            ..Default::default()
        };
        let header = stamped(header, options.stamp);
        let r = self.connection().call_scan(header, scan)?;
        let (pose, health) = read_localized(&r.header)
            .map_err(|what| ClientError::Invalid(format!("the server sent {what}")))?;
        Ok(Localized { pose, health })
    }

    /// Client-side localization: the checks and retry ladder run here, each
    /// registration asking the server for cov2cov pairings at every iterate.
    pub fn localize_client_side(
        &mut self,
        scan: &ScanPayload,
        guess: &Pose,
        options: &LocalizeOptions,
    ) -> Result<Localized, ClientError> {
        self.localize_client_side_reusing(scan, guess, options, &mut PreparedParts::default())
    }

    /// [`Self::localize_client_side`] that takes the scan's covariances and coarse copy
    /// from `parts` when an earlier call on the same scan built them there, and leaves
    /// what it built in `parts`: a tracker registering one scan at several places
    /// estimates its covariances once. The pose is the same either way.
    pub fn localize_client_side_reusing(
        &mut self,
        scan: &ScanPayload,
        guess: &Pose,
        options: &LocalizeOptions,
        parts: &mut PreparedParts,
    ) -> Result<Localized, ClientError> {
        let tracking = &options.tracking;
        tracking
            .validate()
            .map_err(|e| ClientError::Invalid(format!("tracking: {e}")))?;
        // Covariances estimated once here rather than by the server at every iterate,
        // with the server's own [covariance], as server-side localization prepares it.
        let served = self.served_covariance_options()?;
        let mut prepared = PreparedScan::resume(
            scan.points,
            scan.view_dirs,
            scan.covariances,
            served,
            *tracking,
            std::mem::take(parts),
        );
        let found = localize_scan(
            guess,
            &options.expectation(),
            localize_stage(options.max_pair_dist, options.max_iterations),
            tracking,
            |start, stage| {
                let (cloud, covariances) = prepared
                    .for_stage(stage)
                    .map_err(|e| ClientError::Invalid(format!("coarse scan: {e}")))?;
                let payload = ScanPayload {
                    points: &cloud.points,
                    view_dirs: cloud.view_dirs.as_deref(),
                    covariances: Some(covariances),
                };
                let result = solve_pose(start, &stage.params(), payload.points.len(), |pose| {
                    self.cov2cov_with(
                        &payload,
                        pose,
                        stage.max_pair_dist as f32,
                        options.mode,
                        |_, pairings| correspondences_from_wire(pairings, payload.points),
                    )
                });
                match result {
                    Ok(r) => Ok(Some(r)),
                    Err(ClientError::Registration(RegistrationError::NoCorrespondences {
                        ..
                    })) => Ok(None),
                    Err(e) => Err(e),
                }
            },
        )?;
        *parts = prepared.into_parts();
        Ok(Localized {
            pose: found.pose,
            health: found.health,
        })
    }
}

/// `header` carrying `stamp` as its pose's time (`FLAG_STAMPED`), when there is one.
pub(crate) fn stamped(mut header: RequestHeader, stamp: Option<f64>) -> RequestHeader {
    if let Some(t) = stamp {
        header.flags |= FLAG_STAMPED;
        header.stamp = t;
    }
    header
}
