//! Fuzzes the PCD reader (`ascii`, `binary`, `binary_compressed` with LZF): any bytes
//! give a cloud or a named error, never a panic, and no allocation proportional to a
//! header value (POINTS, WIDTH x HEIGHT, COUNT, the LZF size prefix). A cloud read
//! must write back (`write_pcd`, each data mode) and read again to the same values.
//! Run: `cargo +nightly fuzz run read_pcd`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_geometry::io::{PcdData, read_pcd, write_pcd};
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
    common::assert_attributes_match(&cloud);
    let _ = cloud.validate();
    for out_mode in [
        mode,
        PcdData::Ascii,
        PcdData::Binary,
        PcdData::BinaryCompressed,
    ] {
        let bytes = write_pcd(&cloud, out_mode);
        let (again, again_mode, _) = read_pcd(path, &bytes)
            .unwrap_or_else(|e| panic!("write_pcd({out_mode:?}) output does not read back: {e}"));
        assert_eq!(again_mode, out_mode);
        common::assert_same_cloud(&cloud, &again, &format!("{out_mode:?}"));
    }
});
