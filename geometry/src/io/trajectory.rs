//! Trajectories: TUM (`t x y z qx qy qz qw` per line) and KITTI (3x4 row-major
//! `[R | t]` per line, no stamps).

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::error::{IoError, Location};
use crate::geometry::{Pose, pose_from_matrix, pose_from_xyz_quat, pose_to_xyz_quat};

/// A sequence of poses `T_world_body`, with stamps (seconds) when the format has them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// Time of each pose in seconds; `None` for KITTI files.
    pub stamps: Option<Vec<f64>>,
    /// The poses, in file order.
    pub poses: Vec<Pose>,
}

/// Numbers of each non-empty, non-comment line, with its 1-based line number.
fn numeric_lines<'a>(
    path: &'a Path,
    text: &'a str,
    width: usize,
) -> impl Iterator<Item = Result<(usize, Vec<f64>), IoError>> + 'a {
    text.lines().enumerate().filter_map(move |(k, line)| {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            return None;
        }
        let line_no = k + 1;
        let values: Result<Vec<f64>, IoError> = line
            .split_whitespace()
            .map(|w| {
                w.parse::<f64>().map_err(|_| {
                    IoError::malformed(
                        path,
                        Location::Line(line_no),
                        format!("'{w}' is not a number"),
                    )
                })
            })
            .collect();
        Some(values.and_then(|v| {
            if v.len() == width {
                Ok((line_no, v))
            } else {
                Err(IoError::malformed(
                    path,
                    Location::Line(line_no),
                    format!("expected {width} numbers, found {}", v.len()),
                ))
            }
        }))
    })
}

/// Parses a TUM trajectory.
pub fn parse_tum(path: &Path, text: &str) -> Result<Trajectory, IoError> {
    let mut traj = Trajectory {
        stamps: Some(Vec::new()),
        poses: Vec::new(),
    };
    for item in numeric_lines(path, text, 8) {
        let (line_no, v) = item?;
        let pose =
            pose_from_xyz_quat([v[1], v[2], v[3], v[4], v[5], v[6], v[7]]).ok_or_else(|| {
                IoError::malformed(
                    path,
                    Location::Line(line_no),
                    "pose is not finite or its quaternion is zero",
                )
            })?;
        traj.stamps.get_or_insert_with(Vec::new).push(v[0]);
        traj.poses.push(pose);
    }
    Ok(traj)
}

/// Parses a KITTI pose file.
pub fn parse_kitti_poses(path: &Path, text: &str) -> Result<Trajectory, IoError> {
    let mut traj = Trajectory::default();
    for item in numeric_lines(path, text, 12) {
        let (line_no, v) = item?;
        let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
        let t = Vector3::new(v[3], v[7], v[11]);
        let pose = pose_from_matrix(r, t).ok_or_else(|| {
            IoError::malformed(
                path,
                Location::Line(line_no),
                "the 3x3 block is not a rotation matrix",
            )
        })?;
        traj.poses.push(pose);
    }
    Ok(traj)
}

/// Formats a trajectory as TUM; poses without stamps get their index as the stamp.
pub fn format_tum(traj: &Trajectory) -> String {
    let mut out = String::from("# t x y z qx qy qz qw\n");
    for (i, pose) in traj.poses.iter().enumerate() {
        let t = traj.stamps.as_ref().map_or(i as f64, |s| s[i]);
        let v = pose_to_xyz_quat(pose);
        let _ = writeln!(
            out,
            "{t:.9} {:.9} {:.9} {:.9} {:.12} {:.12} {:.12} {:.12}",
            v[0], v[1], v[2], v[3], v[4], v[5], v[6]
        );
    }
    out
}

/// Formats a trajectory as KITTI 3x4 rows.
pub fn format_kitti_poses(traj: &Trajectory) -> String {
    let mut out = String::new();
    for pose in &traj.poses {
        let m = pose.to_homogeneous();
        let row: Vec<String> = (0..3)
            .flat_map(|r| (0..4).map(move |c| (r, c)))
            .map(|(r, c)| format!("{:.12e}", m[(r, c)]))
            .collect();
        let _ = writeln!(out, "{}", row.join(" "));
    }
    out
}

/// Reads a trajectory file; the format is KITTI for 12 numbers a line, else TUM.
pub fn read_trajectory(path: &Path) -> Result<Trajectory, IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::os(path, e))?;
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'));
    match first.map(|l| l.split_whitespace().count()) {
        Some(12) => parse_kitti_poses(path, &text),
        _ => parse_tum(path, &text),
    }
}

/// The keyframe poses of a `graph.txt` (gtsam_points' dump, as in `kitti07/`): one
/// `vN x y z qx qy qz qw` line per keyframe, in file order; other lines are ignored.
pub fn read_keyframe_graph(path: &Path) -> Result<Vec<Pose>, IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::os(path, e))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| l.starts_with('v'))
        .map(|(n, l)| {
            let bad = |why: &str| IoError::malformed(path, Location::Line(n + 1), why);
            let values: Vec<f64> = l
                .split_whitespace()
                .skip(1)
                .map(|w| {
                    w.parse()
                        .map_err(|_| bad(&format!("'{w}' is not a number")))
                })
                .collect::<Result<_, _>>()?;
            let values: [f64; 7] = values
                .try_into()
                .map_err(|_| bad("expected vN x y z qx qy qz qw"))?;
            pose_from_xyz_quat(values).ok_or_else(|| bad("invalid pose"))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{rotation_distance, translation_distance};

    fn sample() -> Trajectory {
        let poses = (0..5)
            .map(|i| {
                Pose::new(
                    Vector3::new(i as f64, -0.5 * i as f64, 0.1),
                    Vector3::new(0.0, 0.1 * i as f64, 0.3),
                )
            })
            .collect();
        Trajectory {
            stamps: Some((0..5).map(|i| 100.0 + i as f64 * 0.1).collect()),
            poses,
        }
    }

    fn assert_same_poses(a: &Trajectory, b: &Trajectory) {
        assert_eq!(a.poses.len(), b.poses.len());
        for (p, q) in a.poses.iter().zip(&b.poses) {
            assert!(translation_distance(p, q) < 1e-8 && rotation_distance(p, q) < 1e-9);
        }
    }

    #[test]
    fn tum_round_trip() {
        let traj = sample();
        let back = parse_tum(Path::new("t.txt"), &format_tum(&traj)).unwrap();
        assert_same_poses(&traj, &back);
        let (s, b) = (traj.stamps.unwrap(), back.stamps.unwrap());
        assert!(s.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-9));
    }

    #[test]
    fn kitti_round_trip() {
        let traj = sample();
        let back = parse_kitti_poses(Path::new("k.txt"), &format_kitti_poses(&traj)).unwrap();
        assert_same_poses(&traj, &back);
        assert!(back.stamps.is_none());
    }

    #[test]
    fn errors_name_the_line() {
        let text = "# header\n0 0 0 0 0 0 0 1\n1 0 0 zero 0 0 0 1\n";
        let err = parse_tum(Path::new("traj.txt"), text)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("traj.txt") && err.contains("line 3") && err.contains("'zero'"),
            "{err}"
        );
        let short = parse_tum(Path::new("traj.txt"), "0 1 2 3\n")
            .unwrap_err()
            .to_string();
        assert!(
            short.contains("line 1") && short.contains("expected 8"),
            "{short}"
        );
        let zero_q = parse_tum(Path::new("traj.txt"), "0 1 2 3 0 0 0 0\n")
            .unwrap_err()
            .to_string();
        assert!(zero_q.contains("quaternion"), "{zero_q}");
    }
}
