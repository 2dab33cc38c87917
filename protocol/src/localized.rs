//! A localized pose and its health in a response header: written by the server's
//! `Localize` and `Track` answers, read by every client, in one place so both sides
//! agree field by field.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::Constraint;
use kfmap_geometry::tracking::{
    Reasons, ScanHealth, TrackingStatus, covariance_from_wire, covariance_to_wire,
};

use crate::{ResponseHeader, pose_from_wire, pose_to_wire};

/// Writes `pose` and `health` into the localization fields of `h`.
pub fn write_localized(h: &mut ResponseHeader, pose: &Pose, health: &ScanHealth) {
    h.pose = pose_to_wire(pose);
    h.covariance = covariance_to_wire(health.covariance.as_ref());
    h.fitness = [health.inlier_ratio, health.rmse];
    h.iterations = health.iterations;
    h.converged = health.converged as u32;
    h.tracking = health.status as u32;
    h.reasons = health.reasons.0;
    h.registrations = health.registrations;
    h.degenerate = health.degenerate as u32;
    h.constraint = [
        health.constraint.rotation_ratio,
        health.constraint.translation_ratio,
    ];
    h.pose_correction = health.correction;
}

/// The pose and health in the localization fields of `h`; the error names the field a
/// server sent wrong.
pub fn read_localized(h: &ResponseHeader) -> Result<(Pose, ScanHealth), String> {
    let pose = pose_from_wire(&h.pose).ok_or("an invalid pose")?;
    let status = TrackingStatus::from_code(h.tracking)
        .ok_or_else(|| format!("an unknown tracking status {}", h.tracking))?;
    Ok((
        pose,
        ScanHealth {
            status,
            reasons: Reasons(h.reasons),
            inlier_ratio: h.fitness[0],
            rmse: h.fitness[1],
            constraint: Constraint {
                rotation_ratio: h.constraint[0],
                translation_ratio: h.constraint[1],
            },
            degenerate: h.degenerate == 1,
            covariance: covariance_from_wire(&h.covariance),
            correction: h.pose_correction,
            registrations: h.registrations,
            iterations: h.iterations,
            converged: h.converged == 1,
        },
    ))
}
