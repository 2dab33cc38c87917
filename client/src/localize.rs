//! Localization against the server: server-side (`Localize`, for thin clients) or
//! client-side (this process iterates the shared GICP solver over `Cov2Cov` answers).
//! Both run the same loop on the same pairings, so they land on the same pose.

use kfmap_shared::cov::{CovOptions, estimate_covariances};
use kfmap_shared::geometry::Pose;
use kfmap_shared::protocol::{
    Cov2CovMode, RequestHeader, RequestKind, ScanPayload, correspondences_from_wire,
    localize_registration, pose_from_wire, pose_to_wire,
};
use kfmap_shared::registration::solve_pose;
use nalgebra::Matrix6;

use crate::{Client, ClientError};

/// Localization settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizeOptions {
    /// Iterations at most.
    pub max_iterations: u32,
    /// Largest pairing distance, metres.
    pub max_pair_dist: f32,
    /// Cov2cov mode.
    pub mode: Cov2CovMode,
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            max_pair_dist: 1.0,
            mode: Cov2CovMode::MapDefault,
        }
    }
}

/// A solved pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localized {
    /// `T_map_sensor`.
    pub pose: Pose,
    /// Pose covariance (rotation first), the inverse GICP Hessian.
    pub covariance: Matrix6<f64>,
    /// Scan points with a pairing, over all.
    pub inlier_ratio: f64,
    /// RMS pairing distance, metres.
    pub rmse: f64,
    /// Iterations run.
    pub iterations: u32,
    /// True when the update fell below the thresholds.
    pub converged: bool,
}

impl Client {
    /// Server-side GICP of `scan` from `guess`.
    pub fn localize(
        &mut self,
        scan: &ScanPayload,
        guess: &Pose,
        options: &LocalizeOptions,
    ) -> Result<Localized, ClientError> {
        let header = RequestHeader {
            kind: RequestKind::Localize as u32,
            pose: pose_to_wire(guess),
            max_iterations: options.max_iterations,
            max_pair_dist: options.max_pair_dist,
            mode: options.mode as u32,
            ..Default::default()
        };
        let r = self.connection().call_scan(header, scan)?;
        let h = r.header;
        let pose = pose_from_wire(&h.pose)
            .ok_or_else(|| ClientError::Invalid("the server sent an invalid pose".into()))?;
        Ok(Localized {
            pose,
            covariance: Matrix6::from_row_slice(&h.covariance),
            inlier_ratio: h.fitness[0],
            rmse: h.fitness[1],
            iterations: h.iterations,
            converged: h.converged == 1,
        })
    }

    /// Client-side GICP: asks for cov2cov pairings at each iterate and solves here.
    pub fn localize_client_side(
        &mut self,
        scan: &ScanPayload,
        guess: &Pose,
        options: &LocalizeOptions,
    ) -> Result<Localized, ClientError> {
        let params = localize_registration(options.max_pair_dist, options.max_iterations);
        // Estimated once here rather than by the server at every iterate; the server's
        // shipped [covariance] settings are these defaults, so both solvers agree.
        let estimated;
        let covariances = match scan.covariances {
            Some(c) => c,
            None => {
                estimated = estimate_covariances(scan.points, &CovOptions::default()).values;
                &estimated
            }
        };
        let with_covs = ScanPayload {
            covariances: Some(covariances),
            ..*scan
        };
        let result = solve_pose(guess, &params, scan.points.len(), |pose| {
            self.cov2cov_with(
                &with_covs,
                pose,
                options.max_pair_dist,
                options.mode,
                |_, pairings| correspondences_from_wire(pairings, scan.points),
            )
        })?;
        Ok(Localized {
            pose: result.pose,
            covariance: result.hessian.try_inverse().unwrap_or_else(Matrix6::zeros),
            inlier_ratio: result.fitness.inlier_ratio,
            rmse: result.fitness.rmse,
            iterations: result.iterations as u32,
            converged: result.converged,
        })
    }
}
