//! Helpers shared by the fuzz targets (included with `#[path]`, not a target itself).
#![allow(dead_code)]

use std::path::PathBuf;

use kfmap_geometry::cloud::PointCloud;
use std::sync::OnceLock;

/// A temporary file path private to this process: `kfmap-fuzz-<tag>-<pid><ext>`.
pub fn temp_path(tag: &str, ext: &str) -> PathBuf {
    std::env::temp_dir().join(format!("kfmap-fuzz-{tag}-{}{ext}", std::process::id()))
}

/// Besides "no panic", targets check what the readers promise (a parsed file writes
/// back and reads again, poses are unit rotations, ...). Set `KFMAP_FUZZ_PANIC_ONLY=1`
/// to fuzz for panics alone, e.g. to get past a known invariant failure.
pub fn strict() -> bool {
    static STRICT: OnceLock<bool> = OnceLock::new();
    *STRICT.get_or_init(|| std::env::var_os("KFMAP_FUZZ_PANIC_ONLY").is_none_or(|v| v == "0"))
}

/// Bitwise equality of floats, any NaN equal to any NaN.
pub fn same_f32(a: f32, b: f32) -> bool {
    (a.is_nan() && b.is_nan()) || a.to_bits() == b.to_bits()
}

/// [`same_f32`] over slices of triplets.
pub fn same_points(a: &[[f32; 3]], b: &[[f32; 3]]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| (0..3).all(|i| same_f32(p[i], q[i])))
}

/// [`same_f32`] over optional slices.
pub fn same_opt<T, F: Fn(&T, &T) -> bool>(a: &Option<Vec<T>>, b: &Option<Vec<T>>, eq: F) -> bool {
    match (a, b) {
        (None, None) => true,
        (Some(a), Some(b)) => a.len() == b.len() && a.iter().zip(b).all(|(x, y)| eq(x, y)),
        _ => false,
    }
}

/// Every per-point attribute of `cloud` has one entry per point.
pub fn assert_attributes_match(cloud: &PointCloud) {
    let n = cloud.len();
    for (name, len) in [
        ("view_dirs", cloud.view_dirs.as_ref().map(Vec::len)),
        ("intensity", cloud.intensity.as_ref().map(Vec::len)),
        ("time", cloud.time.as_ref().map(Vec::len)),
    ] {
        assert!(
            len.is_none_or(|l| l == n),
            "{name} has {len:?} entries for {n} points"
        );
    }
}

/// `again` (written by a writer in `how`, read back) holds `cloud`'s values bit for bit.
pub fn assert_same_cloud(cloud: &PointCloud, again: &PointCloud, how: &str) {
    assert!(
        same_points(&cloud.points, &again.points),
        "{how}: points differ"
    );
    assert!(
        same_opt(&cloud.view_dirs, &again.view_dirs, |a, b| same_points(
            &[*a],
            &[*b]
        )),
        "{how}: view dirs differ"
    );
    assert!(
        same_opt(&cloud.intensity, &again.intensity, |a, b| same_f32(*a, *b)),
        "{how}: intensity differs"
    );
    assert!(
        same_opt(&cloud.time, &again.time, |a, b| same_f32(*a, *b)),
        "{how}: time differs"
    );
}
