//! Fuzzes the trajectory readers, TUM (`t x y z qx qy qz qw`) and KITTI (3x4 `[R|t]`
//! rows): any text gives poses or a named error, never a panic. Poses read are finite
//! with a unit rotation, and a trajectory read writes back (`format_tum`,
//! `format_kitti_poses`) and reads again with as many poses.
//! Run: `cargo +nightly fuzz run trajectory`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{
    Trajectory, format_kitti_poses, format_tum, parse_kitti_poses, parse_tum,
};
use libfuzzer_sys::fuzz_target;

fn check_poses(what: &str, traj: &Trajectory) {
    for (i, pose) in traj.poses.iter().enumerate() {
        check_pose(&format!("{what} pose {i}"), pose);
    }
}

fn check_pose(what: &str, pose: &Pose) {
    let q = pose.rotation.quaternion();
    let t = pose.translation.vector;
    assert!(
        t.iter().chain(q.coords.iter()).all(|v| v.is_finite()),
        "{what} is not finite: t {t:?} q {q:?}"
    );
    assert!(
        (q.norm() - 1.0).abs() < 1e-6,
        "{what}: quaternion {q:?} is not unit (norm {})",
        q.norm()
    );
}

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let path = Path::new("fuzz.txt");
    let strict = common::strict();
    if let Ok(traj) = parse_tum(path, &text) {
        if strict {
            assert_eq!(traj.stamps.as_ref().map(Vec::len), Some(traj.poses.len()));
            check_poses("tum", &traj);
            let again = parse_tum(path, &format_tum(&traj))
                .unwrap_or_else(|e| panic!("format_tum output does not parse: {e}"));
            assert_eq!(again.poses.len(), traj.poses.len());
            let again = parse_kitti_poses(path, &format_kitti_poses(&traj)).unwrap_or_else(|e| {
                panic!("format_kitti_poses output of a TUM file does not parse: {e}")
            });
            assert_eq!(again.poses.len(), traj.poses.len());
        }
    }
    if let Ok(traj) = parse_kitti_poses(path, &text) {
        if strict {
            assert!(traj.stamps.is_none());
            check_poses("kitti", &traj);
            let again = parse_kitti_poses(path, &format_kitti_poses(&traj))
                .unwrap_or_else(|e| panic!("format_kitti_poses output does not parse: {e}"));
            assert_eq!(again.poses.len(), traj.poses.len());
            let again = parse_tum(path, &format_tum(&traj)).unwrap_or_else(|e| {
                panic!("format_tum output of a KITTI file does not parse: {e}")
            });
            assert_eq!(again.poses.len(), traj.poses.len());
        }
    }
});
