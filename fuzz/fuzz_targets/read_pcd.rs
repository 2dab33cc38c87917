//! Fuzzes the PCD reader (`ascii`, `binary`, `binary_compressed` with LZF): any bytes
//! give a cloud or a named error, never a panic, and no allocation proportional to a
//! header value (POINTS, WIDTH x HEIGHT, COUNT, the LZF size prefix). A cloud read
//! must write back (`write_pcd`, each data mode) and read again to the same values.
//! Run: `cargo +nightly fuzz run read_pcd`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_shared::io::{PcdData, read_pcd, write_pcd};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.pcd");
    let Ok((cloud, mode, fields)) = read_pcd(path, data) else {
        return;
    };
    if !common::strict() {
        return;
    }
    assert!(fields.len() >= 3, "fields {fields:?}");
    let n = cloud.len();
    for (name, len) in [
        ("view_dirs", cloud.view_dirs.as_ref().map(Vec::len)),
        ("intensity", cloud.intensity.as_ref().map(Vec::len)),
        ("time", cloud.time.as_ref().map(Vec::len)),
    ] {
        assert!(len.is_none_or(|l| l == n), "{name} has {len:?} entries for {n} points");
    }
    let _ = cloud.validate();
    for out_mode in [mode, PcdData::Ascii, PcdData::Binary, PcdData::BinaryCompressed] {
        let bytes = write_pcd(&cloud, out_mode);
        let (again, again_mode, _) = read_pcd(path, &bytes)
            .unwrap_or_else(|e| panic!("write_pcd({out_mode:?}) output does not read back: {e}"));
        assert_eq!(again_mode, out_mode);
        assert!(common::same_points(&cloud.points, &again.points), "{out_mode:?}: points differ");
        assert!(common::same_opt(&cloud.view_dirs, &again.view_dirs, |a, b| common::same_points(&[*a], &[*b])));
        assert!(common::same_opt(&cloud.intensity, &again.intensity, |a, b| common::same_f32(*a, *b)));
        assert!(common::same_opt(&cloud.time, &again.time, |a, b| common::same_f32(*a, *b)));
    }
});
