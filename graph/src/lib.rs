//! Building a map's poses: the pose graph (Gauss-Newton / Levenberg-Marquardt with
//! robust kernels, g2o I/O, ELCH loop distribution), the joint refinement of poses
//! and planes (plane bundle adjustment) and the sparse block systems both solve.
//! Built on `kfmap-geometry`; independent of the keyframe map (`kfmap-map`), so the
//! two compile side by side.
#![warn(missing_docs)]

pub mod pose_graph;
pub mod refine;
pub mod sparse_blocks;
