//! The integration tests of this crate, as one binary (one link instead of one per
//! file: each release test binary is a thin-LTO link of every dependency).

mod drives_sim;
mod gravity_real;
mod gravity_sim;
mod kitti_raw;
mod mapping_real;

use kfmap_bake::mapping::GlobalError;
use kfmap_geometry::registration::RegistrationError;

/// What a map build in these tests can fail with: registration, the pose graph, reading
/// a scan.
#[derive(Debug, thiserror::Error)]
enum TestError {
    #[error(transparent)]
    Registration(#[from] RegistrationError),
    #[error(transparent)]
    Global(#[from] GlobalError),
    #[error(transparent)]
    Io(#[from] kfmap_geometry::io::IoError),
}
