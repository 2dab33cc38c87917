//! Sparse SE(3) pose-graph optimization: relative-pose edges with information matrices,
//! Gauss-Newton or Levenberg-Marquardt on the Lie algebra, a sparse Cholesky (faer, AMD
//! ordering, the symbolic factorization reused across iterations), robust kernels per
//! edge and the first pose fixed. The error of an edge `i -> j` measuring `Z` is GTSAM's
//! `Log(Z^-1 X_i^-1 X_j)` in `(omega, v)` order, so costs compare with GTSAM's.
//!
//! ```
//! use kfmap_geometry::geometry::Pose;
//! use kfmap_graph::pose_graph::{GraphParams, PoseEdge, PoseGraph};
//! use nalgebra::{Matrix6, Vector3};
//!
//! let mut graph = PoseGraph::default();
//! let step = Pose::translation(1.0, 0.0, 0.0);
//! for id in 0..3 {
//!     graph.add_pose(id, Pose::translation(0.9 * id as f64, 0.1 * id as f64, 0.0)).unwrap();
//! }
//! for id in 0..2 {
//!     graph.add_edge(PoseEdge::new(id, id + 1, step, Matrix6::identity())).unwrap();
//! }
//! let report = graph.optimize(&GraphParams::default()).unwrap();
//! assert!(report.final_error < 1e-12);
//! assert!((graph.pose(2).unwrap().translation.vector - Vector3::new(2.0, 0.0, 0.0)).norm() < 1e-9);
//! ```

mod elch;
mod g2o;
mod solve;
pub(crate) use solve::linearize_edge;
#[cfg(test)]
mod tests;

use std::collections::HashMap;

use nalgebra::Matrix6;
use serde::{Deserialize, Serialize};

pub use elch::{ElchError, elch};
pub use g2o::{G2oError, read_g2o, write_g2o};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::{Optimizer, RobustKernel};
pub use kfmap_geometry::se3::{adjoint, exp, log};

/// Vertex id as in g2o files.
pub type VertexId = u64;

/// A relative-pose measurement `Z = X_from^-1 X_to` with its information.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseEdge {
    /// First vertex.
    pub from: VertexId,
    /// Second vertex.
    pub to: VertexId,
    /// The measured `T_from_to`.
    pub measurement: Pose,
    /// 6x6 information over `(omega, v)`.
    pub information: Matrix6<f64>,
    /// Down-weighting of this edge's error (loop closures may be wrong).
    pub kernel: RobustKernel,
}

impl PoseEdge {
    /// A least-squares edge.
    pub fn new(from: VertexId, to: VertexId, measurement: Pose, information: Matrix6<f64>) -> Self {
        Self {
            from,
            to,
            measurement,
            information,
            kernel: RobustKernel::None,
        }
    }
}

/// Why a graph could not be built or optimized.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GraphError {
    /// Two vertices with one id.
    #[error("vertex {0} is defined twice")]
    DuplicateVertex(VertexId),
    /// An edge names a vertex that does not exist.
    #[error("edge {from} -> {to} names vertex {missing}, which does not exist")]
    UnknownVertex {
        /// First vertex.
        from: VertexId,
        /// Second vertex.
        to: VertexId,
        /// The missing one.
        missing: VertexId,
    },
    /// An edge from a vertex to itself.
    #[error("edge {0} -> {0} joins a vertex to itself")]
    SelfEdge(VertexId),
    /// A non-finite pose or an information matrix that is not symmetric positive
    /// semi-definite.
    #[error("{0}")]
    BadValue(String),
    /// The graph has no vertices.
    #[error("the graph has no vertices")]
    Empty,
    /// The normal equations could not be solved: not positive definite (a vertex with no
    /// constraint) or not set up.
    #[error("the pose graph's linear system: {0} (is every vertex connected to the fixed one?)")]
    Solve(#[from] crate::sparse_blocks::BlockError),
}

/// Optimizer settings (GTSAM's Gauss-Newton defaults).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct GraphParams {
    /// Step method.
    pub optimizer: Optimizer,
    /// Iterations at most.
    pub max_iterations: usize,
    /// Stop when the error drops by less than this fraction.
    pub relative_error_tol: f64,
    /// Stop when the error is below this.
    pub absolute_error_tol: f64,
    /// The vertex held fixed (gauge); default: the first added.
    #[serde(skip)]
    pub fixed: Option<VertexId>,
}

impl Default for GraphParams {
    fn default() -> Self {
        Self {
            optimizer: Optimizer::GaussNewton,
            max_iterations: 100,
            relative_error_tol: 1e-5,
            absolute_error_tol: 1e-5,
            fixed: None,
        }
    }
}

impl GraphParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), kfmap_geometry::options::InvalidOption> {
        use kfmap_geometry::options::ensure;
        ensure(
            self.max_iterations >= 1,
            "max-iterations",
            self.max_iterations,
            "at least 1",
        )?;
        ensure(
            self.relative_error_tol.is_finite() && self.relative_error_tol >= 0.0,
            "relative-error-tol",
            self.relative_error_tol,
            "a finite value >= 0",
        )?;
        ensure(
            self.absolute_error_tol.is_finite() && self.absolute_error_tol >= 0.0,
            "absolute-error-tol",
            self.absolute_error_tol,
            "a finite value >= 0",
        )
    }
}

/// What an optimization did. Errors are half the (robust) chi2, as GTSAM reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GraphReport {
    /// Error before.
    pub initial_error: f64,
    /// Error after.
    pub final_error: f64,
    /// Error after each iteration.
    pub errors: Vec<f64>,
    /// Iterations run.
    pub iterations: usize,
    /// True when a tolerance stopped it (not the iteration limit).
    pub converged: bool,
}

/// Poses and relative-pose edges; clouds never move, only these poses.
#[derive(Debug, Clone, Default)]
pub struct PoseGraph {
    ids: Vec<VertexId>,
    poses: Vec<Pose>,
    index: HashMap<VertexId, usize>,
    edges: Vec<PoseEdge>,
}

impl PoseGraph {
    /// Adds a vertex.
    pub fn add_pose(&mut self, id: VertexId, pose: Pose) -> Result<(), GraphError> {
        if self.index.contains_key(&id) {
            return Err(GraphError::DuplicateVertex(id));
        }
        check_pose(&pose, &format!("vertex {id}"))?;
        self.index.insert(id, self.ids.len());
        self.ids.push(id);
        self.poses.push(pose);
        Ok(())
    }

    /// Adds an edge between existing vertices.
    pub fn add_edge(&mut self, edge: PoseEdge) -> Result<(), GraphError> {
        if edge.from == edge.to {
            return Err(GraphError::SelfEdge(edge.from));
        }
        for v in [edge.from, edge.to] {
            if !self.index.contains_key(&v) {
                return Err(GraphError::UnknownVertex {
                    from: edge.from,
                    to: edge.to,
                    missing: v,
                });
            }
        }
        let name = format!("edge {} -> {}", edge.from, edge.to);
        check_pose(&edge.measurement, &name)?;
        let info = &edge.information;
        let symmetric = (info - info.transpose()).abs().max() <= 1e-9 * info.abs().max().max(1.0);
        if !info.iter().all(|v| v.is_finite())
            || !symmetric
            || info.symmetric_eigenvalues().min() < -1e-9 * info.abs().max()
        {
            return Err(GraphError::BadValue(format!(
                "{name}: the information matrix is not symmetric positive semi-definite"
            )));
        }
        self.edges.push(edge);
        Ok(())
    }

    /// Vertex ids in insertion order.
    pub fn ids(&self) -> &[VertexId] {
        &self.ids
    }

    /// A vertex's pose.
    pub fn pose(&self, id: VertexId) -> Option<&Pose> {
        self.index.get(&id).map(|&i| &self.poses[i])
    }

    /// Replaces a vertex's pose.
    pub fn set_pose(&mut self, id: VertexId, pose: Pose) -> Result<(), GraphError> {
        check_pose(&pose, &format!("vertex {id}"))?;
        let i = *self.index.get(&id).ok_or(GraphError::UnknownVertex {
            from: id,
            to: id,
            missing: id,
        })?;
        self.poses[i] = pose;
        Ok(())
    }

    /// The edges.
    pub fn edges(&self) -> &[PoseEdge] {
        &self.edges
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True without vertices.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Half the robust chi2 of every edge at the current poses.
    pub fn error(&self) -> f64 {
        self.edges
            .iter()
            .map(|e| {
                let r = self.residual(e);
                0.5 * e.kernel.rho(r.dot(&(e.information * r)))
            })
            .sum::<f64>()
            + 0.0 // An empty float sum is -0.0.
    }

    fn residual(&self, e: &PoseEdge) -> nalgebra::Vector6<f64> {
        let (xi, xj) = (
            &self.poses[self.index[&e.from]],
            &self.poses[self.index[&e.to]],
        );
        log(&(e.measurement.inverse() * xi.inverse() * xj))
    }

    /// Minimizes [`PoseGraph::error`] over every pose but the fixed one.
    pub fn optimize(&mut self, params: &GraphParams) -> Result<GraphReport, GraphError> {
        solve::optimize(self, params)
    }
}

fn check_pose(pose: &Pose, name: &str) -> Result<(), GraphError> {
    let q = pose.rotation.quaternion();
    if pose
        .translation
        .vector
        .iter()
        .chain(q.coords.iter())
        .all(|v| v.is_finite())
    {
        Ok(())
    } else {
        Err(GraphError::BadValue(format!(
            "{name}: the pose is not finite"
        )))
    }
}
