//! One scan preparation for every localization, client-side or server-side: the scan as
//! sent and its coarse copy, each with per-point covariances estimated with the options
//! of the server that answers (its `[covariance]`), each built once on first use. Both
//! sides registering the same clouds with the same covariances is what makes them land
//! on the same pose.

use super::ladder::{Stage, TrackingParams};
use crate::cloud::{CloudError, PointCloud};
use crate::cov::{CovOptions, estimate_covariances};
use crate::geometry::PackedSym3;

/// A scan as the registrations of one localization take it.
#[derive(Debug)]
pub struct PreparedScan<'s> {
    points: &'s [[f32; 3]],
    view_dirs: Option<&'s [[f32; 3]]>,
    covariances: Option<&'s [PackedSym3]>,
    options: CovOptions,
    tracking: TrackingParams,
    fine: Option<(PointCloud, Vec<PackedSym3>)>,
    coarse: Option<(PointCloud, Vec<PackedSym3>)>,
}

impl<'s> PreparedScan<'s> {
    /// The scan (`points`, optional `view_dirs`, optional client `covariances`);
    /// covariances it lacks are estimated with `options`, the coarse copy is built with
    /// `tracking`'s coarse voxel.
    pub fn new(
        points: &'s [[f32; 3]],
        view_dirs: Option<&'s [[f32; 3]]>,
        covariances: Option<&'s [PackedSym3]>,
        options: CovOptions,
        tracking: TrackingParams,
    ) -> Self {
        Self {
            points,
            view_dirs,
            covariances,
            options,
            tracking,
            fine: None,
            coarse: None,
        }
    }

    /// The scan as sent, with its covariances: the given ones, else estimated.
    pub fn fine(&mut self) -> (&PointCloud, &[PackedSym3]) {
        let (points, view_dirs, given, options) =
            (self.points, self.view_dirs, self.covariances, &self.options);
        let (cloud, covs) = self.fine.get_or_insert_with(|| {
            let cloud = PointCloud {
                points: points.to_vec(),
                view_dirs: view_dirs.map(<[_]>::to_vec),
                intensity: None,
                time: None,
            };
            let covs = match given {
                Some(c) => c.to_vec(),
                None => estimate_covariances(points, options).values,
            };
            (cloud, covs)
        });
        (cloud, covs.as_slice())
    }

    /// The coarse scan ([`TrackingParams::coarse_scan`]) with covariances estimated on
    /// it (a client's covariances belong to the full scan's points).
    pub fn coarse(&mut self) -> Result<(&PointCloud, &[PackedSym3]), CloudError> {
        if self.coarse.is_none() {
            let cloud = self.tracking.coarse_scan(self.points, self.view_dirs)?;
            let covs = estimate_covariances(&cloud.points, &self.options).values;
            self.coarse = Some((cloud, covs));
        }
        let (cloud, covs) = self.coarse.as_ref().expect("built above");
        Ok((cloud, covs.as_slice()))
    }

    /// The cloud and covariances `stage` registers.
    pub fn for_stage(&mut self, stage: &Stage) -> Result<(&PointCloud, &[PackedSym3]), CloudError> {
        if stage.coarse {
            self.coarse()
        } else {
            Ok(self.fine())
        }
    }
}
