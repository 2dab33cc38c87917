//! Locating the real LiDAR data kept beside the repository (`../shared/data`), for
//! tests, benchmarks and the demo.

use std::io::Write;
use std::path::PathBuf;

/// Environment variable that overrides where the shared data folder is.
pub const DATA_DIR_ENV: &str = "KFMAP_DATA_DIR";

/// The shared data folder: `$KFMAP_DATA_DIR`, else `../shared/data` beside this
/// checkout, else `../shared/data` relative to the working directory. `None` if
/// none exists.
pub fn shared_data_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os(DATA_DIR_ENV) {
        return Some(PathBuf::from(dir)).filter(|d| d.is_dir());
    }
    // This crate lives at <checkout>/shared; the data at <checkout>/../shared/data.
    let beside_checkout = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    let beside_cwd = PathBuf::from("../shared/data");
    [beside_checkout, beside_cwd]
        .into_iter()
        .find(|d| d.join("PROVENANCE.txt").is_file())
        .map(|d| d.canonicalize().unwrap_or(d))
}

/// For tests and benchmarks: the path of `relative` inside the shared data folder.
/// When the data is missing it prints why the caller skips and returns `None`; under
/// `CI=true` it panics instead, because CI must run every data test.
pub fn require_test_data(relative: &str, test: &str) -> Option<PathBuf> {
    let found = shared_data_dir()
        .map(|d| d.join(relative))
        .filter(|p| p.exists());
    if found.is_none() {
        let reason = format!(
            "{test}: shared data '{relative}' not found (looked in ${DATA_DIR_ENV} and ../shared/data)"
        );
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("{reason}; CI=true requires it");
        }
        // Written to stderr directly: the test harness captures eprintln! of passing tests.
        let _ = writeln!(std::io::stderr(), "SKIPPED {reason}");
    }
    found
}

/// The keyframe poses of a `graph.txt` (gtsam_points' dump, as in `kitti07/`): one
/// `vN x y z qx qy qz qw` line per keyframe, in file order; other lines are ignored.
pub fn read_keyframe_graph(
    path: &std::path::Path,
) -> Result<Vec<crate::geometry::Pose>, crate::io::IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| crate::io::IoError::os(path, e))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| l.starts_with('v'))
        .map(|(n, l)| {
            let bad = |why: &str| {
                crate::io::IoError::malformed(path, crate::io::Location::Line(n + 1), why)
            };
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
            crate::geometry::pose_from_xyz_quat(values).ok_or_else(|| bad("invalid pose"))
        })
        .collect()
}
