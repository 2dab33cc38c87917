//! Localization that knows when it is wrong (docs/DESIGN.md#tracking): every localized
//! scan gets its fitness, degeneracy, 6x6 covariance and a status `ok` / `degraded` /
//! `lost`; a correction the motion model does not allow is retried from wider
//! hypotheses and never adopted silently. Client-side and server-side localization
//! both run [`localize_scan`], so they decide alike.
//!
//! ```
//! use kfmap_geometry::cloud::PointCloud;
//! use kfmap_geometry::geometry::Pose;
//! use kfmap_geometry::registration::{PreparedCloud, align};
//! use kfmap_geometry::tracking::{
//!     Expectation, Stage, TrackingParams, TrackingStatus, localize_scan,
//! };
//! use nalgebra::Vector3;
//!
//! // A room: floor and three walls, 4 m, 10 cm apart; the scan is the room seen from
//! // 20 cm along x, predicted at the origin.
//! let mut room = Vec::new();
//! for i in 0..40 {
//!     for j in 0..40 {
//!         let (a, b) = (i as f32 * 0.1, j as f32 * 0.1);
//!         room.extend([[a, b, 0.0], [a, 0.0, b], [0.0, a, b], [a, 4.0, b]]);
//!     }
//! }
//! let scan: Vec<[f32; 3]> = room.iter().map(|p| [p[0] - 0.2, p[1], p[2]]).collect();
//! let params = TrackingParams::default();
//! let fine = Stage { coarse: false, max_pair_dist: 1.0, max_iterations: 30 };
//! let map = PreparedCloud::from_points(room, &fine.params(), "target").unwrap();
//! let coarse = params.coarse_scan(&scan, None).unwrap().points;
//! let (fine_scan, coarse_scan) = (
//!     PreparedCloud::from_points(scan, &fine.params(), "source").unwrap(),
//!     PreparedCloud::from_points(coarse, &fine.params(), "source").unwrap(),
//! );
//! let expected = Expectation { max_correction: Some(1.0), inlier_ratio: None };
//! let found = localize_scan(&Pose::identity(), &expected, fine, &params, |start, stage| {
//!     let source = if stage.coarse { &coarse_scan } else { &fine_scan };
//!     Ok::<_, ()>(align(&map, source, start, &stage.params()).ok())
//! })
//! .unwrap();
//! assert_eq!(found.health.status, TrackingStatus::Ok);
//! assert!((found.pose.translation.vector - Vector3::new(0.2, 0.0, 0.0)).norm() < 0.01);
//! ```

mod health;
mod ladder;
mod prepared;
#[cfg(test)]
mod tests;

pub use health::{
    Reasons, ScanHealth, TrackingStatus, covariance_from_wire, covariance_to_wire, pose_covariance,
    registration_covariance,
};
pub use ladder::{
    CORRECTION_RANGE_M, Expectation, Localization, Stage, TrackingParams, localize_scan,
};
pub use prepared::{PreparedParts, PreparedScan};
