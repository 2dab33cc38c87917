//! The keyframe map and what is found in it: keyframes with their KD-trees and
//! covariances, the covisibility graph and active sets, keyframe selection, the baked
//! archive a server memory-maps, the place grid and relocalization's search, and the
//! tiles of a large site. Built on `kfmap-geometry`; the pose graph that places the
//! keyframes is `kfmap-graph`.
#![warn(missing_docs)]

pub mod archive;
pub mod covis;
pub mod map;
pub mod place;
pub mod select;
pub mod tiles;
