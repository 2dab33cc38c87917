//! `ImuWindow`: an IMU window joins the session's gravity pool; the answer carries the
//! pool's current correction.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::gravity::ImuWindow;
use kfmap_protocol::{Rejection, RequestHeader, decode_imu, decode_stamp};

use super::answer::{Answer, AnswerPairings, with_active};
use super::session::Session;

pub(super) fn imu_window(
    session: &mut Session,
    request: &RequestHeader,
    payload: &[f32],
    pose: &Pose,
) -> Result<Answer, Rejection> {
    const MAX_IMU_SAMPLES: usize = 1 << 16;
    let samples = decode_imu(request, payload, MAX_IMU_SAMPLES)?;
    let stamp = decode_stamp(request)?;
    let id = request.keyframe_or_scan_id;
    session
        .gravity
        .add_window(id, ImuWindow::new(samples), *pose, stamp);
    let mut answer = with_active(AnswerPairings::default(), &[]);
    let h = &mut answer.header;
    let pool = session.gravity.answer();
    h.gravity_members = pool.members as u32;
    h.gravity_compensated = pool.compensated as u32;
    h.gravity_pending = pool.pending as u32;
    h.gravity_skipped = pool.skipped as u32;
    if let Some(c) = pool.correction {
        let q = nalgebra::UnitQuaternion::from_rotation_matrix(&c.rotation);
        let (health, bias) = (&c.estimate.health, &c.estimate.accel_bias);
        h.has_gravity = 1;
        h.gravity = c.estimate.g.into();
        h.roll_pitch = [c.roll, c.pitch];
        h.correction = [q.i, q.j, q.k, q.w];
        h.gravity_inliers = health.inliers as u32;
        h.gravity_spread_deg = health.spread_deg;
        h.accel_bias = bias.mps2.into();
        h.accel_bias_sigma = bias.sigma_mps2.map_or([0.0; 3], Into::into);
        h.bias_observable = bias.observable as u32;
    }
    Ok(answer)
}
