//! Inputs several tests share, made once per test run instead of once per test: each
//! is read only (a map is memory-mapped by every server that serves it).
//!
//! They live in `kfmap-fixtures-<pid>` under the temporary directory, removed when the
//! test process exits; a run killed before that leaves its directory, which the next
//! run removes (its process is gone). A child test process (the network-namespace
//! scenarios) is given its parent's directory through [`FIXTURES_ENV`] and reuses what
//! the parent made before starting it.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use super::{bake_dataset, linked_dataset};

/// The fixture directory a parent test process hands to the test processes it starts.
pub const FIXTURES_ENV: &str = "KFMAP_TEST_FIXTURES";

/// This run's fixture directory (the parent's, in a child test process).
pub fn dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        if let Some(inherited) = std::env::var_os(FIXTURES_ENV) {
            return PathBuf::from(inherited);
        }
        remove_dead_runs_fixtures();
        let dir = own_dir();
        std::fs::create_dir_all(&dir).unwrap();
        // SAFETY: `remove_own_fixtures` is an `extern "C" fn()` that touches only
        // `own_dir()`; registering it has no other precondition.
        let registered = unsafe { libc::atexit(remove_own_fixtures) };
        assert_eq!(registered, 0, "atexit refused the fixtures' clean-up");
        dir
    })
}

/// The fixture directory of this process, when it is not a child given its parent's.
fn own_dir() -> PathBuf {
    std::env::temp_dir().join(format!("kfmap-fixtures-{}", std::process::id()))
}

/// Removes this process's fixture directory at exit (libtest has no end-of-run hook).
extern "C" fn remove_own_fixtures() {
    let _ = std::fs::remove_dir_all(own_dir());
}

/// Removes every `kfmap-fixtures-<pid>` directory whose process no longer runs.
fn remove_dead_runs_fixtures() {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix("kfmap-fixtures-") else {
            continue;
        };
        if pid.bytes().all(|b| b.is_ascii_digit()) && !Path::new("/proc").join(pid).exists() {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// balm_os0's first pass, scans 0-115 at their reference poses (`poses.txt`), baked
/// with the defaults (`kfmap bake --dataset`): the map five tests serve to relocalize
/// and track the revisit (scans 116-176) against.
pub fn balm_first_pass_map(balm: &Path) -> PathBuf {
    static MAP: OnceLock<PathBuf> = OnceLock::new();
    MAP.get_or_init(|| {
        let map = dir().join("balm-0-115.kfmap");
        if map.is_file() {
            println!(
                "fixture: {} (made by the parent test process)",
                map.display()
            );
            return map;
        }
        let scans = kfmap_bake::dataset::find_scans(balm).unwrap();
        let pose_text = std::fs::read_to_string(balm.join("poses.txt")).unwrap();
        let pose_lines: Vec<&str> = pose_text.lines().collect();
        assert_eq!((scans.len(), pose_lines.len()), (177, 177));
        let making = dir().join(format!("balm-0-115-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&making);
        let mapped = making.join("mapped");
        linked_dataset(&mapped, &scans[..116], &pose_lines[..116]);
        let baked = making.join("balm.kfmap");
        bake_dataset(&mapped, &baked);
        // Whole or absent: another process never sees a map half written.
        std::fs::rename(&baked, &map).unwrap();
        let _ = std::fs::remove_dir_all(&making);
        println!("fixture: {} baked for this run", map.display());
        map
    })
    .clone()
}
