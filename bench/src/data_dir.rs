//! Where the real LiDAR data beside the checkout is, for `demo --real` and the real-data
//! rows of `kfmap bench`.

use std::path::PathBuf;

/// Environment variable naming the shared data folder.
pub const DATA_DIR_ENV: &str = "KFMAP_DATA_DIR";

/// The shared data folder: `$KFMAP_DATA_DIR`, else `../shared/data` beside the source
/// checkout this binary was built from, else `../shared/data` relative to the working
/// directory. `None` if none exists.
pub fn shared_data_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os(DATA_DIR_ENV) {
        return Some(PathBuf::from(dir)).filter(|d| d.is_dir());
    }
    // This crate sits one folder below the checkout.
    let beside_checkout = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    let beside_cwd = PathBuf::from("../shared/data");
    [beside_checkout, beside_cwd]
        .into_iter()
        .find(|d| d.join("PROVENANCE.txt").is_file())
        .map(|d| d.canonicalize().unwrap_or(d))
}
