//! Fuzzes the PLY reader (`ascii`, `binary_little_endian`, any elements, list
//! properties): any bytes give a cloud or a named error, never a panic, and no
//! allocation proportional to an element count. A cloud read must write back
//! (`write_ply`, both encodings) and read again to the same values.
//! Run: `cargo +nightly fuzz run read_ply`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_geometry::io::{PlyEncoding, read_ply, write_ply};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.ply");
    let Ok((cloud, encoding, _names)) = read_ply(path, data) else {
        return;
    };
    if !common::strict() {
        return;
    }
    common::assert_attributes_match(&cloud);
    for out in [
        encoding,
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
    ] {
        let bytes = write_ply(&cloud, out);
        let (again, again_encoding, _) = read_ply(path, &bytes)
            .unwrap_or_else(|e| panic!("write_ply({out:?}) output does not read back: {e}"));
        assert_eq!(again_encoding, out);
        common::assert_same_cloud(&cloud, &again, &format!("{out:?}"));
    }
});
