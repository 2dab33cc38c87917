//! Fuzzes the map loader: any bytes, opened as a `.kfmap` file, must give a named error
//! or a map that answers, never a crash. Run: `cargo +nightly fuzz run open_map`
//! (seed the corpus with a small baked map, e.g. from `kfmap bake`).
#![no_main]

use kfmap_map::archive::{OpenOptions, open_map};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("kfmap-fuzz-{}.kfmap", std::process::id()));
    if std::fs::write(&path, data).is_err() {
        return;
    }
    for trust in [false, true] {
        if let Ok(opened) = open_map(
            &path,
            OpenOptions {
                trust,
                ..OpenOptions::default()
            },
        ) {
            let _ = opened.verify_keyframes(|_| {});
            let mut map = opened.map;
            let ids: Vec<u64> = map.keyframes().map(|k| k.id).collect();
            for id in ids {
                if let Ok(active) = map.activate_ids(vec![id]) {
                    let _ = active.nearest_k(&[0.0, 0.0, 0.0], 3);
                }
            }
        }
    }
    let _ = std::fs::remove_file(&path);
});
