//! Registrations of a scan against the served map: the shared GICP loop iterated over
//! the map's cov2cov pairings, in a client's session or outside any (in parallel).

use kfmap_geometry::cloud::{CloudError, PointCloud};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::{RegistrationError, RegistrationResult, solve_pose};
use kfmap_geometry::tracking::{PreparedScan, Stage};
use kfmap_map::map::{NearestMemo, Pairing};
use kfmap_map::select::SelectionOptions;
use kfmap_protocol::{DecodedScan, Rejection, correspondences_from_pairings};

use super::answer::{bad, map_error};
use super::limits::Limits;
use super::queries::{Activation, cov2cov};
use super::session::Session;
use super::state::ServedMap;

/// The scan of a request prepared as every localization prepares it: covariances it
/// lacks estimated with the server's `[covariance]`, the coarse copy with its
/// `[tracking]` ([`PreparedScan`], shared with client-side localization).
pub(super) fn prepare<'s>(scan: &DecodedScan<'s>, limits: &Limits) -> PreparedScan<'s> {
    PreparedScan::new(
        scan.points,
        scan.view_dirs,
        scan.covariances,
        limits.scan_covariance,
        limits.tracking,
    )
}

/// A scan whose coarse copy cannot be built.
pub(super) fn coarse_error(e: CloudError) -> Rejection {
    bad(format!("coarse scan: {e}"))
}

/// Registrations against the served map in one client's session.
pub(super) struct MapRegistration<'a> {
    pub(super) map: &'a ServedMap,
    pub(super) session: &'a mut Session,
    pub(super) activation: Activation,
    /// Keyframes of the last pairing.
    pub(super) active: Vec<u64>,
}

impl MapRegistration<'_> {
    /// One registration of `cloud` (with its covariances) from `start` over the map's
    /// cov2cov pairings; `None` when no scan point has a pair.
    pub(super) fn register(
        &mut self,
        cloud: &PointCloud,
        covs: &[[f32; 6]],
        start: &Pose,
        stage: &Stage,
    ) -> Result<Option<RegistrationResult>, Rejection> {
        register_over(cloud, start, stage, |at| {
            let (pairings, ids) = cov2cov(
                self.map,
                self.session,
                cloud,
                covs,
                at,
                stage.max_pair_dist as f32,
                self.activation,
            )?;
            self.active = ids;
            Ok(pairings)
        })
    }
}

/// As [`MapRegistration::register`] in approximate mode and outside any session (no
/// merged-submap cache to share), so registrations may run on several threads; the
/// active keyframes chosen with `selection`, each point's nearest map point recalled
/// from `memo` while it certifies it (the answers of a search, see [`NearestMemo`]).
pub(super) fn register_approximate(
    map: &ServedMap,
    selection: &SelectionOptions,
    cloud: &PointCloud,
    covs: &[[f32; 6]],
    start: &Pose,
    stage: &Stage,
    memo: &mut NearestMemo,
) -> Result<Option<RegistrationResult>, Rejection> {
    register_over(cloud, start, stage, |at| {
        let ids = map.map.select_with(at, selection);
        let active = map
            .map
            .activate_cached(ids, &mut None, false)
            .map_err(map_error)?;
        active
            .cov2cov_remembering(cloud, at, stage.max_pair_dist, Some(covs), Some(memo))
            .map_err(map_error)
    })
}

/// The registration loop over `pairings_at(pose)`; `None` when no scan point has a pair.
fn register_over(
    cloud: &PointCloud,
    start: &Pose,
    stage: &Stage,
    mut pairings_at: impl FnMut(&Pose) -> Result<Vec<Pairing>, Rejection>,
) -> Result<Option<RegistrationResult>, Rejection> {
    let result = solve_pose(start, &stage.params(), cloud.len(), |at| {
        let pairings = pairings_at(at).map_err(LocalizeError::Rejected)?;
        Ok::<_, LocalizeError>(correspondences_from_pairings(&pairings, &cloud.points))
    });
    match result {
        Ok(r) => Ok(Some(r)),
        Err(LocalizeError::Registration(RegistrationError::NoCorrespondences { .. })) => Ok(None),
        Err(LocalizeError::Registration(e)) => Err(bad(format!("localization: {e}"))),
        Err(LocalizeError::Rejected(r)) => Err(r),
    }
}

enum LocalizeError {
    Rejected(Rejection),
    Registration(RegistrationError),
}

impl From<RegistrationError> for LocalizeError {
    fn from(e: RegistrationError) -> Self {
        Self::Registration(e)
    }
}
