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
            let cloud = as_sent(points, view_dirs);
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

    /// As [`Self::new`], with what an earlier preparation built (`parts`, from
    /// [`Self::into_parts`]) when it prepared the same points with the same options:
    /// a tracker registers one scan at several places, and the covariances are most of
    /// a client-side localization's own work. Parts of another scan or other options
    /// are dropped, so the result is always what [`Self::new`] would give.
    pub fn resume(
        points: &'s [[f32; 3]],
        view_dirs: Option<&'s [[f32; 3]]>,
        covariances: Option<&'s [PackedSym3]>,
        options: CovOptions,
        tracking: TrackingParams,
        parts: PreparedParts,
    ) -> Self {
        let mut scan = Self::new(points, view_dirs, covariances, options, tracking);
        let same = parts.built_with == Some((options, tracking.coarse_voxel))
            && parts.given_covariances == covariances.is_some()
            && parts.scan.points == points
            && parts.scan.view_dirs.as_deref() == view_dirs;
        if same {
            scan.fine = parts.fine_covariances.map(|covs| (parts.scan, covs));
            scan.coarse = parts.coarse;
        }
        scan
    }

    /// What this preparation built, for [`Self::resume`] on the same scan (the scan as
    /// sent moves along when it was built, else it is copied once).
    pub fn into_parts(self) -> PreparedParts {
        let (scan, fine_covariances) = match self.fine {
            Some((cloud, covs)) => (cloud, Some(covs)),
            None => (as_sent(self.points, self.view_dirs), None),
        };
        PreparedParts {
            built_with: Some((self.options, self.tracking.coarse_voxel)),
            given_covariances: self.covariances.is_some(),
            scan,
            fine_covariances,
            coarse: self.coarse,
        }
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

/// The scan as sent, as a cloud.
fn as_sent(points: &[[f32; 3]], view_dirs: Option<&[[f32; 3]]>) -> PointCloud {
    PointCloud {
        points: points.to_vec(),
        view_dirs: view_dirs.map(<[_]>::to_vec),
        intensity: None,
        time: None,
    }
}

/// What a [`PreparedScan`] built, with the scan and options it was built for.
#[derive(Debug, Default, Clone)]
pub struct PreparedParts {
    built_with: Option<(CovOptions, f64)>,
    given_covariances: bool,
    /// The scan as sent: the fine stage's cloud, and what a resumed scan is compared with.
    scan: PointCloud,
    fine_covariances: Option<Vec<PackedSym3>>,
    coarse: Option<(PointCloud, Vec<PackedSym3>)>,
}
