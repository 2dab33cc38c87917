//! Fuzzes the headerless `.bin` reader (KITTI `x y z intensity` and raw `x y z`): any
//! bytes give a cloud or a named error (size not a multiple of the record), never a
//! panic; a cloud read writes back byte for byte.
//! Run: `cargo +nightly fuzz run read_bin`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_geometry::io::{BinLayout, read_bin, write_bin};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.bin");
    for layout in [BinLayout::Xyzi, BinLayout::Xyz] {
        let result = read_bin(path, data, layout);
        if common::strict() {
            assert_eq!(result.is_ok(), data.len() % layout.record_size() == 0);
        }
        if let Ok(cloud) = result {
            if common::strict() {
                assert_eq!(cloud.len(), data.len() / layout.record_size());
                assert_eq!(
                    write_bin(&cloud, layout),
                    data,
                    "{layout:?} does not write back"
                );
            }
        }
    }
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = BinLayout::parse(text);
    }
});
