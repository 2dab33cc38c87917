//! Fuzzes `io::read_cloud`, the entry point bake and the CLI use: the first byte picks
//! the file name's extension (`.pcd`, `.ply`, `.bin`, none: sniffed from the content)
//! and the read options (bin layout, invalid-return filter and its range); the rest
//! is the file, written to a per-process temp path. Any content gives a cloud or a
//! named error, never a panic; a filtered cloud keeps its attributes aligned.
//! Run: `cargo +nightly fuzz run read_cloud`.
#![no_main]

#[path = "common.rs"]
mod common;

use kfmap_geometry::cloud::FilterOptions;
use kfmap_geometry::io::{BinLayout, ReadOptions, read_cloud};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&selector, content)) = data.split_first() else {
        return;
    };
    let ext = [".pcd", ".ply", ".bin", ".xyz"][(selector & 3) as usize];
    let bin_layout =
        [None, Some(BinLayout::Xyzi), Some(BinLayout::Xyz), None][((selector >> 2) & 3) as usize];
    let min_range = [0.0, 0.1, 1.0, 1e30][((selector >> 5) & 3) as usize];
    let options = ReadOptions {
        bin_layout,
        filter: FilterOptions {
            enabled: selector & 0x10 != 0,
            min_range,
        },
    };
    let path = common::temp_path("cloud", ext);
    if std::fs::write(&path, content).is_err() {
        return;
    }
    if let Ok(loaded) = read_cloud(&path, &options) {
        let _ = loaded.format.to_string();
        if common::strict() {
            let cloud = &loaded.cloud;
            let n = cloud.len();
            assert!(cloud.view_dirs.as_ref().is_none_or(|v| v.len() == n));
            assert!(cloud.intensity.as_ref().is_none_or(|v| v.len() == n));
            assert!(cloud.time.as_ref().is_none_or(|v| v.len() == n));
            match &loaded.filter {
                Some(report) => {
                    assert_eq!(report.kept, n);
                    assert_eq!(report.kept + report.dropped(), loaded.points_in_file);
                    // Filtered clouds are what bake validates: every point finite.
                    assert!(cloud.validate().is_ok(), "{:?}", cloud.validate());
                }
                None => assert_eq!(n, loaded.points_in_file),
            }
        }
    }
    let _ = std::fs::remove_file(&path);
});
