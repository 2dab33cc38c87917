//! Why a bake failed: one error for the whole pipeline, each variant naming the file
//! or option at fault.

use std::path::PathBuf;

use kfmap_geometry::io::IoError;
use kfmap_geometry::registration::RegistrationError;
use kfmap_graph::pose_graph::{G2oError, GraphError};
use kfmap_map::archive::ArchiveError;

use crate::gravity::GravityError;
use crate::mapping::GlobalError;
use crate::scan_range::ScanRangeError;

/// Why a bake failed.
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    /// The dataset directory has no scans.
    #[error("{0}: no scans (*.pcd, *.ply, *.bin) in it or in its scans/ folder")]
    NoScans(PathBuf),
    /// Poses and scans cannot be matched.
    #[error(
        "{poses}: {count} poses for {scans} scans; scans named by frame number need a pose per number, others exactly one pose each"
    )]
    PoseCount {
        /// The pose file.
        poses: PathBuf,
        /// Poses in it.
        count: usize,
        /// Scans found.
        scans: usize,
    },
    /// A scan or pose file could not be read.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A scan is unusable (empty after filtering and downsampling, ...).
    #[error("{path}: {message}")]
    Scan {
        /// The scan.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A bag could not be read (boxed: its errors carry the bag's topic listing).
    #[error(transparent)]
    Bag(Box<kfmap_bag::BagError>),
    /// The map file could not be written.
    #[error(transparent)]
    Archive(#[from] ArchiveError),
    /// The dataset's IMU log could not be used.
    #[error(transparent)]
    Gravity(#[from] GravityError),
    /// Building poses from the scans failed (registration).
    #[error("building poses from the scans: {0}")]
    Registration(#[from] RegistrationError),
    /// Building poses from the scans failed (loops, graph).
    #[error("building poses from the scans: {0}")]
    Mapping(#[from] GlobalError),
    /// The scan range does not fit the dataset.
    #[error(transparent)]
    ScanRange(#[from] ScanRangeError),
    /// A pose graph was asked for, but the poses come from a pose file.
    #[error(
        "--graph-out: the poses come from {}, so no pose graph is built; pass --build-poses to build the poses (and their graph) from the scans, the pose file then serving as ground truth",
        .0.display()
    )]
    NoPoseGraph(PathBuf),
    /// The tile set could not be cut (bad geometry, directory, ...).
    #[error("tiles: {0}")]
    Tiles(String),
    /// `--refine-only` cannot run as asked.
    #[error("--refine-only: {0}")]
    RefineOnly(String),
    /// A tile set's index could not be used.
    #[error(transparent)]
    TileIndex(#[from] kfmap_map::tiles::TileError),
    /// The pose graph could not be assembled or written.
    #[error("writing the pose graph: {0}")]
    Graph(#[from] G2oError),
}

impl From<GraphError> for BakeError {
    fn from(error: GraphError) -> Self {
        Self::Mapping(error.into())
    }
}

impl From<kfmap_bag::BagError> for BakeError {
    fn from(error: kfmap_bag::BagError) -> Self {
        Self::Bag(Box::new(error))
    }
}
