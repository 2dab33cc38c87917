//! g2o files: `VERTEX_SE3:QUAT id x y z qx qy qz qw`, `EDGE_SE3:QUAT i j x y z qx qy qz qw`
//! followed by the upper triangle of the 6x6 information over `(x y z qx qy qz)` row by
//! row, and `FIX id`. The information is reordered to `(omega, v)` as GTSAM does.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::Matrix6;

use super::{GraphError, PoseEdge, PoseGraph, VertexId};
use kfmap_geometry::geometry::{Pose, pose_from_xyz_quat, pose_to_xyz_quat};
use kfmap_geometry::io::{IoError, Location, write_atomic};

/// Why a g2o file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum G2oError {
    /// Reading or writing failed, or a line is malformed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The lines parse but do not form a graph.
    #[error("{path}: line {line}: {source}")]
    Graph {
        /// The file.
        path: String,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        source: GraphError,
    },
}

/// Swaps the translation and rotation blocks (g2o `(t, q)` <-> kfmap `(omega, v)`).
fn swap_blocks(m: &Matrix6<f64>) -> Matrix6<f64> {
    Matrix6::from_fn(|r, c| m[((r + 3) % 6, (c + 3) % 6)])
}

/// Reads a g2o file of SE(3) vertices and edges; the first vertex (or the `FIX`ed one)
/// is returned as the gauge.
pub fn read_g2o(path: &Path) -> Result<(PoseGraph, Option<VertexId>), G2oError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::os(path, e))?;
    let mut graph = PoseGraph::default();
    let mut fixed = None;
    for (k, line) in text.lines().enumerate() {
        let bad = |reason: String| IoError::malformed(path, Location::Line(k + 1), reason);
        let graph_error = |source| G2oError::Graph {
            path: path.display().to_string(),
            line: k + 1,
            source,
        };
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some((&tag, rest)) = words.split_first() else {
            continue;
        };
        if tag.starts_with('#') {
            continue;
        }
        let numbers = |count: usize| -> Result<Vec<f64>, IoError> {
            if rest.len() != count {
                return Err(bad(format!(
                    "{tag} needs {count} values, found {}",
                    rest.len()
                )));
            }
            rest.iter()
                .map(|w| {
                    w.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| bad(format!("'{w}' is not a finite number")))
                })
                .collect()
        };
        let pose = |v: &[f64]| -> Result<Pose, IoError> {
            let xyz_quat: [f64; 7] = v.try_into().expect("seven values");
            pose_from_xyz_quat(xyz_quat).ok_or_else(|| bad("the quaternion is zero".into()))
        };
        let id = |v: f64| -> Result<VertexId, IoError> {
            if v >= 0.0 && v.fract() == 0.0 && v < 9.0e15 {
                Ok(v as VertexId)
            } else {
                Err(bad(format!("'{v}' is not a vertex id")))
            }
        };
        match tag {
            "VERTEX_SE3:QUAT" => {
                let v = numbers(8)?;
                graph
                    .add_pose(id(v[0])?, pose(&v[1..])?)
                    .map_err(graph_error)?;
            }
            "EDGE_SE3:QUAT" => {
                let v = numbers(30)?;
                let mut info = Matrix6::zeros();
                let mut upper = v[9..].iter();
                for r in 0..6 {
                    for c in r..6 {
                        let x = *upper.next().expect("21 values");
                        info[(r, c)] = x;
                        info[(c, r)] = x;
                    }
                }
                let edge = PoseEdge::new(id(v[0])?, id(v[1])?, pose(&v[2..9])?, swap_blocks(&info));
                graph.add_edge(edge).map_err(graph_error)?;
            }
            "FIX" => fixed = Some(id(numbers(1)?[0])?),
            other => {
                return Err(bad(format!(
                    "unsupported element '{other}' (kfmap reads VERTEX_SE3:QUAT, EDGE_SE3:QUAT and FIX)"
                ))
                .into());
            }
        }
    }
    Ok((graph, fixed))
}

fn push_pose(out: &mut String, pose: &Pose) {
    let v = pose_to_xyz_quat(pose);
    let _ = write!(
        out,
        "{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
        v[0], v[1], v[2], v[3], v[4], v[5], v[6]
    );
}

/// Writes `graph` as g2o, atomically.
pub fn write_g2o(path: &Path, graph: &PoseGraph, fixed: Option<VertexId>) -> Result<(), G2oError> {
    let mut out = String::new();
    for (&id, pose) in graph.ids.iter().zip(&graph.poses) {
        let _ = write!(out, "VERTEX_SE3:QUAT {id} ");
        push_pose(&mut out, pose);
        out.push('\n');
    }
    for e in &graph.edges {
        let _ = write!(out, "EDGE_SE3:QUAT {} {} ", e.from, e.to);
        push_pose(&mut out, &e.measurement);
        let info = swap_blocks(&e.information);
        for r in 0..6 {
            for c in r..6 {
                let _ = write!(out, " {:.9e}", info[(r, c)]);
            }
        }
        out.push('\n');
    }
    if let Some(id) = fixed {
        let _ = writeln!(out, "FIX {id}");
    }
    write_atomic(path, out.as_bytes())?;
    Ok(())
}
