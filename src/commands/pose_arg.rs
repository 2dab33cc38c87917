//! The pose argument of `register`, `localize` and `query`.

use anyhow::Context;
use kfmap_geometry::geometry::Pose;
use nalgebra::{Matrix4, Rotation3, UnitQuaternion, Vector3};

/// A pose argument (`--initial`) from "x y z roll pitch yaw" or a 4x4 matrix file.
pub fn parse_pose(text: &str) -> anyhow::Result<Pose> {
    let path = std::path::Path::new(text);
    let (numbers, what) = if path.is_file() {
        let body = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
        (body, "a 4x4 matrix file")
    } else {
        (text.to_string(), "\"x y z roll pitch yaw\"")
    };
    let v: Vec<f64> = numbers
        .split_whitespace()
        .map(|w| {
            w.parse::<f64>()
                .with_context(|| format!("--initial: '{w}' is not a number"))
        })
        .collect::<anyhow::Result<_>>()?;
    if v.iter().any(|x| !x.is_finite()) {
        anyhow::bail!("--initial: values must be finite");
    }
    match v.len() {
        6 => Ok(Pose::from_parts(
            Vector3::new(v[0], v[1], v[2]).into(),
            UnitQuaternion::from_euler_angles(
                v[3].to_radians(),
                v[4].to_radians(),
                v[5].to_radians(),
            ),
        )),
        16 => {
            let m = Matrix4::from_row_slice(&v);
            let r = m.fixed_view::<3, 3>(0, 0).into_owned();
            if (r.transpose() * r - nalgebra::Matrix3::identity()).norm() > 1e-4 {
                anyhow::bail!("--initial: the 3x3 block of the matrix is not a rotation");
            }
            Ok(Pose::from_parts(
                Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]).into(),
                UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r)),
            ))
        }
        n => anyhow::bail!("--initial: expected {what} (6 or 16 numbers), found {n}"),
    }
}
