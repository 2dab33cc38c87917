//! The check of every built scan against its neighbours (docs/DESIGN.md#map-building):
//! after the graph is solved, each scan is registered onto a local map of the scans
//! either side of it at their built poses; a scan the local map pulls away, or that
//! lies badly on it, is re-registered onto its good neighbours from their poses, and
//! what still does not fit is reported poor.

use serde::{Deserialize, Serialize};

use kfmap_geometry::geometry::{PackedSym3, Pose, extend_moved};
use kfmap_geometry::motion::point_displacement;
use kfmap_geometry::options::{InvalidOption, ensure, ensure_distance, ensure_ratio};
use kfmap_geometry::registration::{
    Fitness, PreparedCloud, RegistrationError, RegistrationParams, RegistrationResult, align,
    overlap,
};
use kfmap_geometry::tracking::CORRECTION_RANGE_M;
use rayon::prelude::*;

/// The scan check's settings (`bake.toml`'s `[build.check]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ScanCheckParams {
    /// Check the scans at all (off: every scan is reported `unchecked`).
    pub enabled: bool,
    /// Scans either side whose clouds, at their built poses, make a scan's local map.
    pub neighbours: usize,
    /// Pairing distance of the check and the re-registration, metres; the inlier ratio
    /// and RMSE are measured at it (as tracking's health at its fine distance).
    pub max_distance: f64,
    /// A scan fits when registering it onto its local map moves it at most this far
    /// (translation plus the arc of a point 10 m away), metres...
    pub max_shift: f64,
    /// ...at least this share of its points has a partner...
    pub min_inlier_ratio: f64,
    /// ...and their RMS distance is at most this, metres.
    pub max_rmse: f64,
}

impl Default for ScanCheckParams {
    fn default() -> Self {
        Self {
            enabled: true,
            neighbours: 5,
            max_distance: 1.0,
            max_shift: 0.15,
            min_inlier_ratio: 0.5,
            max_rmse: 0.4,
        }
    }
}

impl ScanCheckParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            self.neighbours >= 1,
            "neighbours",
            self.neighbours,
            "at least 1",
        )?;
        ensure_distance("max-distance", self.max_distance)?;
        ensure_distance("max-shift", self.max_shift)?;
        ensure_ratio("min-inlier-ratio", self.min_inlier_ratio)?;
        ensure_distance("max-rmse", self.max_rmse)
    }
}

/// What the check found for one scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ScanVerdict {
    /// Not checked: the check is off, or the scan has no neighbour.
    Unchecked,
    /// Lies on its neighbours where it was built; pose kept.
    Fits,
    /// Did not fit; re-registered onto its good neighbours, it fits there now.
    Reregistered,
    /// Does not fit its neighbours, as built or re-registered; the built pose is kept
    /// and may be off.
    Poor,
}

impl ScanVerdict {
    /// The verdict's name, as in the JSON summary.
    pub fn name(self) -> &'static str {
        match self {
            ScanVerdict::Unchecked => "unchecked",
            ScanVerdict::Fits => "fits",
            ScanVerdict::Reregistered => "reregistered",
            ScanVerdict::Poor => "poor",
        }
    }
}

/// One scan's check.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanCheck {
    /// The verdict.
    pub verdict: ScanVerdict,
    /// How far registering the scan onto its local map moved it from its built pose
    /// (translation plus the arc of a point 10 m away), metres.
    pub shift: Option<f64>,
    /// How the scan lies on its local map at its final pose: share of its points with
    /// a partner within `max-distance`, and their RMS distance.
    pub fitness: Option<Fitness>,
    /// How far the check moved the pose (as `shift`), metres; 0 unless re-registered.
    pub moved: f64,
}

impl ScanCheck {
    /// A scan the check did not look at.
    pub const UNCHECKED: ScanCheck = ScanCheck {
        verdict: ScanVerdict::Unchecked,
        shift: None,
        fitness: None,
        moved: 0.0,
    };
}

/// A scan as odometry registered it: its prepared points and their covariances, in
/// its cloud frame (mid-scan when deskewed), `scan_from_cloud` away from its pose.
pub struct ScanCloud {
    /// `T_scan_cloud`: the cloud frame seen from the scan's pose frame.
    pub scan_from_cloud: Pose,
    /// Downsampled points, cloud frame.
    pub points: Vec<[f32; 3]>,
    /// Their covariances, cloud frame.
    pub covariances: Vec<PackedSym3>,
}

impl ScanCloud {
    /// Keeps what the check needs of a prepared scan.
    pub fn new(scan_from_cloud: Pose, prepared: &PreparedCloud) -> Self {
        Self {
            scan_from_cloud,
            points: prepared.points.clone(),
            covariances: prepared.covariances.clone(),
        }
    }
}

/// Checks every scan (`poses`: `T_map_scan`, taken at `stamps`) against its
/// neighbours and moves the ones re-registered; one check per scan.
pub fn check_scans(
    clouds: &[ScanCloud],
    stamps: &[f64],
    poses: &mut [Pose],
    params: &ScanCheckParams,
) -> Result<Vec<ScanCheck>, RegistrationError> {
    let n = clouds.len();
    if !params.enabled || n < 2 {
        return Ok(vec![ScanCheck::UNCHECKED; n]);
    }
    let checker = Checker {
        clouds,
        params,
        registration: RegistrationParams {
            max_correspondence_distance: params.max_distance,
            max_iterations: 30,
            ..RegistrationParams::default()
        },
    };
    let everyone = vec![true; n];
    let first: Vec<ScanCheck> = (0..n)
        .into_par_iter()
        .map(|i| checker.check(i, poses, &everyone))
        .collect::<Result<_, _>>()?;
    // Failures are re-registered onto the scans that fit, so that one scan off does
    // not drag its neighbour's local map with it.
    let good: Vec<bool> = first
        .iter()
        .map(|c| c.verdict == ScanVerdict::Fits)
        .collect();
    let fixes: Vec<(usize, ScanCheck, Option<Pose>)> = (0..n)
        .into_par_iter()
        .filter(|&i| !good[i])
        .map(|i| {
            checker
                .reregister(i, stamps, poses, &good)
                .map(|(check, pose)| (i, check, pose))
        })
        .collect::<Result<_, _>>()?;
    let mut checks = first;
    for (i, check, pose) in fixes {
        checks[i] = check;
        if let Some(pose) = pose {
            poses[i] = pose;
        }
    }
    Ok(checks)
}

/// The clouds and settings every scan's check shares.
struct Checker<'a> {
    clouds: &'a [ScanCloud],
    params: &'a ScanCheckParams,
    registration: RegistrationParams,
}

impl Checker<'_> {
    /// `T_map_cloud` of scan `j` at `poses`.
    fn cloud_pose(&self, poses: &[Pose], j: usize) -> Pose {
        poses[j] * self.clouds[j].scan_from_cloud
    }

    /// Scan `i`'s cloud ready to register.
    fn scan(&self, i: usize) -> Result<PreparedCloud, RegistrationError> {
        let c = &self.clouds[i];
        PreparedCloud::from_parts(c.points.clone(), c.covariances.clone(), "scan")
    }

    /// The `usable` scans within `neighbours` of `i` (not `i`) merged in `i`'s cloud
    /// frame at `poses`, each point with its own covariance; `None` without any.
    fn local_map(
        &self,
        i: usize,
        poses: &[Pose],
        usable: &[bool],
    ) -> Result<Option<PreparedCloud>, RegistrationError> {
        let w = self.params.neighbours;
        let to_i = self.cloud_pose(poses, i).inverse();
        let mut points = Vec::new();
        let mut covariances = Vec::new();
        let window = i.saturating_sub(w)..(i + w + 1).min(self.clouds.len());
        for j in window.filter(|&j| j != i && usable[j]) {
            let pose = to_i * self.cloud_pose(poses, j);
            let c = &self.clouds[j];
            extend_moved(
                &pose,
                &c.points,
                &c.covariances,
                &mut points,
                &mut covariances,
            );
        }
        if points.is_empty() {
            return Ok(None);
        }
        PreparedCloud::from_parts(points, covariances, "local map").map(Some)
    }

    /// Lies within the fitness bounds.
    fn fits(&self, fitness: &Fitness) -> bool {
        fitness.inlier_ratio >= self.params.min_inlier_ratio && fitness.rmse <= self.params.max_rmse
    }

    /// Scan `i` at its built pose against all its neighbours: `Fits` when the local
    /// map keeps it in place and it lies well on it, else `Poor` (for now).
    fn check(
        &self,
        i: usize,
        poses: &[Pose],
        usable: &[bool],
    ) -> Result<ScanCheck, RegistrationError> {
        let Some(map) = self.local_map(i, poses, usable)? else {
            return Ok(ScanCheck::UNCHECKED);
        };
        let scan = self.scan(i)?;
        let here = overlap(&map, &scan, &Pose::identity(), self.params.max_distance);
        let shift = align(&map, &scan, &Pose::identity(), &self.registration)
            .ok()
            .map(|r| point_displacement(&Pose::identity(), &r.pose, CORRECTION_RANGE_M));
        let stays = shift.is_some_and(|s| s <= self.params.max_shift);
        Ok(ScanCheck {
            verdict: if stays && self.fits(&here) {
                ScanVerdict::Fits
            } else {
                ScanVerdict::Poor
            },
            shift,
            fitness: Some(here),
            moved: 0.0,
        })
    }

    /// Scan `i` registered onto its `good` neighbours from the pose they place it at
    /// (interpolated between the nearest good scan before and after it at its stamp,
    /// or the nearest one's) and from its built pose; the result lying best
    /// ([`Checker::misfit`]) wins. The new pose (`T_map_scan`) when it fits and lies
    /// better than the built one.
    fn reregister(
        &self,
        i: usize,
        stamps: &[f64],
        poses: &[Pose],
        good: &[bool],
    ) -> Result<(ScanCheck, Option<Pose>), RegistrationError> {
        let Some(map) = self.local_map(i, poses, good)? else {
            return Ok((poor(None, None), None));
        };
        let scan = self.scan(i)?;
        let built = self.cloud_pose(poses, i);
        let here = overlap(&map, &scan, &Pose::identity(), self.params.max_distance);
        let w = self.params.neighbours;
        let before = (i.saturating_sub(w)..i).rev().find(|&j| good[j]);
        let after = (i + 1..(i + w + 1).min(good.len())).find(|&j| good[j]);
        let placed = match (before, after) {
            (Some(a), Some(b)) => {
                // Repeated stamps place it halfway.
                let span = stamps[b] - stamps[a];
                let t = if span > 0.0 {
                    ((stamps[i] - stamps[a]) / span).clamp(0.0, 1.0)
                } else {
                    0.5
                };
                poses[a].lerp_slerp(&poses[b], t)
            }
            (Some(a), None) => poses[a],
            (None, Some(b)) => poses[b],
            (None, None) => unreachable!("a local map has a good neighbour"),
        };
        let starts = [
            built.inverse() * placed * self.clouds[i].scan_from_cloud,
            Pose::identity(),
        ];
        let best = starts
            .iter()
            .filter_map(|start| align(&map, &scan, start, &self.registration).ok())
            .min_by(|a, b| self.misfit(&a.fitness).total_cmp(&self.misfit(&b.fitness)));
        let Some(best) = best else {
            return Ok((poor(None, Some(here)), None));
        };
        let shift = point_displacement(&Pose::identity(), &best.pose, CORRECTION_RANGE_M);
        if shift <= self.params.max_shift && self.fits(&here) {
            // On good neighbours alone it stays: only a bad neighbour pulled it.
            return Ok((
                ScanCheck {
                    verdict: ScanVerdict::Fits,
                    shift: Some(shift),
                    fitness: Some(here),
                    moved: 0.0,
                },
                None,
            ));
        }
        if !self.accepts(&best) || self.misfit(&best.fitness) >= self.misfit(&here) {
            return Ok((poor(Some(shift), Some(here)), None));
        }
        let pose = built * best.pose * self.clouds[i].scan_from_cloud.inverse();
        Ok((
            ScanCheck {
                verdict: ScanVerdict::Reregistered,
                shift: Some(shift),
                fitness: Some(best.fitness),
                moved: shift,
            },
            Some(pose),
        ))
    }

    /// How badly a scan lies, m^2: its points' mean squared distance to their partners,
    /// a point without one counting `max-distance`^2 (a truncated least squares, so
    /// that neither more pairs nor closer ones alone make a pose look better).
    fn misfit(&self, fitness: &Fitness) -> f64 {
        let d = self.params.max_distance;
        let paired = fitness.inlier_ratio;
        let rms = if paired > 0.0 { fitness.rmse } else { 0.0 };
        paired * rms * rms + (1.0 - paired) * d * d
    }

    /// A re-registration good enough to adopt.
    fn accepts(&self, result: &RegistrationResult) -> bool {
        result.converged && !result.degenerate && self.fits(&result.fitness)
    }
}

/// A poor verdict, the built pose kept.
fn poor(shift: Option<f64>, fitness: Option<Fitness>) -> ScanCheck {
    ScanCheck {
        verdict: ScanVerdict::Poor,
        shift,
        fitness,
        moved: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_sim::{Preset, SimConfig, Simulation};

    /// A few simulated campus scans at their true poses, prepared as odometry does.
    fn campus(count: usize) -> (Vec<ScanCloud>, Vec<f64>, Vec<Pose>) {
        let sim = Simulation::new(SimConfig {
            preset: Preset::Campus,
            seconds: 3.0,
            ..SimConfig::default()
        })
        .unwrap();
        let registration = crate::mapping::OdometryParams::default().registration;
        let count = count.min(sim.config().scan_count());
        let scans: Vec<_> = (0..count).map(|i| sim.scan(i)).collect();
        let clouds = scans
            .iter()
            .map(|s| {
                let prepared = PreparedCloud::new(&s.cloud, &registration, "scan");
                ScanCloud::new(Pose::identity(), &prepared.unwrap())
            })
            .collect();
        let stamps = scans.iter().map(|s| s.stamp).collect();
        let truth = scans.iter().map(|s| s.pose).collect();
        (clouds, stamps, truth)
    }

    /// hku2_avia's scans 157 and 256: one scan built 1 m off while its neighbours are
    /// right is found and re-registered onto them; the others are left where they are.
    #[test]
    fn a_scan_built_off_its_neighbours_is_reregistered_onto_them() {
        let (clouds, stamps, truth) = campus(11);
        let off = 5;
        let mut poses = truth.clone();
        poses[off] *= Pose::translation(1.0, 0.3, 0.0);
        let checks =
            check_scans(&clouds, &stamps, &mut poses, &ScanCheckParams::default()).unwrap();
        assert_eq!(checks[off].verdict, ScanVerdict::Reregistered, "{checks:?}");
        let error = (poses[off].translation.vector - truth[off].translation.vector).norm();
        assert!(error < 0.05, "re-registered {error} m from the truth");
        for (i, check) in checks.iter().enumerate().filter(|&(i, _)| i != off) {
            assert_eq!(check.verdict, ScanVerdict::Fits, "scan {i}: {check:?}");
            assert_eq!(poses[i], truth[i]);
        }
    }

    #[test]
    fn an_unchecked_run_keeps_every_pose() {
        let (clouds, stamps, truth) = campus(4);
        let mut poses = truth.clone();
        poses[2] *= Pose::translation(1.0, 0.0, 0.0);
        let off = ScanCheckParams {
            enabled: false,
            ..ScanCheckParams::default()
        };
        let checks = check_scans(&clouds, &stamps, &mut poses, &off).unwrap();
        assert!(checks.iter().all(|c| c.verdict == ScanVerdict::Unchecked));
        assert_eq!(poses[2], truth[2] * Pose::translation(1.0, 0.0, 0.0));
    }

    #[test]
    fn every_option_is_validated() {
        let bad = |p: ScanCheckParams| p.validate().unwrap_err().to_string();
        let d = ScanCheckParams::default();
        assert!(bad(ScanCheckParams { neighbours: 0, ..d }).contains("neighbours"));
        assert!(
            bad(ScanCheckParams {
                max_distance: -1.0,
                ..d
            })
            .contains("max-distance")
        );
        assert!(
            bad(ScanCheckParams {
                max_shift: f64::NAN,
                ..d
            })
            .contains("max-shift")
        );
        assert!(
            bad(ScanCheckParams {
                min_inlier_ratio: 1.5,
                ..d
            })
            .contains("min-inlier-ratio")
        );
        assert!(bad(ScanCheckParams { max_rmse: 0.0, ..d }).contains("max-rmse"));
    }
}
