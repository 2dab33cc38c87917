//! Test policy for every crate of the workspace (a dev-dependency only): where the real
//! LiDAR data beside the repository is (`../shared/data`), what a test does when data or
//! a capability of the machine is missing (skip with a printed reason locally, fail
//! under `CI=true`), and scratch directories.

use std::io::Write;
use std::path::{Path, PathBuf};

/// Environment variable that overrides where the shared data folder is.
pub const DATA_DIR_ENV: &str = "KFMAP_DATA_DIR";

/// The shared data folder: `$KFMAP_DATA_DIR`, else `../shared/data` beside this
/// checkout, else `../shared/data` relative to the working directory. `None` if
/// none exists.
pub fn shared_data_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os(DATA_DIR_ENV) {
        return Some(PathBuf::from(dir)).filter(|d| d.is_dir());
    }
    // This crate lives at <checkout>/testdata; the data at <checkout>/../shared/data.
    let beside_checkout = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    let beside_cwd = PathBuf::from("../shared/data");
    [beside_checkout, beside_cwd]
        .into_iter()
        .find(|d| d.join("PROVENANCE.txt").is_file())
        .map(|d| d.canonicalize().unwrap_or(d))
}

/// True when the tests run as CI runs them (`CI=true`): nothing may be skipped.
pub fn under_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// What a test does when something it needs is missing: under `CI=true` it panics with
/// `reason` (CI must run every test); elsewhere it prints `SKIPPED test: reason` and the
/// caller returns early.
pub fn skip_or_fail(test: &str, reason: &str) {
    if under_ci() {
        panic!("{test}: {reason}; CI=true requires it");
    }
    // Written to stderr directly: the test harness captures eprintln! of passing tests.
    let _ = writeln!(std::io::stderr(), "SKIPPED {test}: {reason}");
}

/// For tests and benchmarks: the path of `relative` inside the shared data folder.
/// When the data is missing it prints why the caller skips and returns `None`; under
/// `CI=true` it panics instead, because CI must run every data test.
pub fn require_test_data(relative: &str, test: &str) -> Option<PathBuf> {
    let found = shared_data_dir()
        .map(|d| d.join(relative))
        .filter(|p| p.exists());
    if found.is_none() {
        skip_or_fail(
            test,
            &format!(
                "shared data '{relative}' not found (looked in ${DATA_DIR_ENV} and ../shared/data)"
            ),
        );
    }
    found
}

/// For tests that need a capability of the machine (a namespace, a tool): `Some(())`
/// when `available`, else the skip-or-fail of [`skip_or_fail`] with `what` as reason.
pub fn require_capability(available: bool, what: &str, test: &str) -> Option<()> {
    if available {
        Some(())
    } else {
        skip_or_fail(test, what);
        None
    }
}

/// For the config tests: every `key = value` line of `serialized` (a default config
/// written by `toml`) has its key in the shipped `file`, so no option goes undocumented.
pub fn assert_lists_every_option(serialized: &str, file: &str) {
    for line in serialized.lines().filter(|l| l.contains(" = ")) {
        let key = line.split(" = ").next().unwrap_or(line);
        assert!(
            file.lines().any(|l| l.starts_with(&format!("{key} = "))),
            "{key} missing from the shipped file"
        );
    }
}

/// `$TMPDIR/kfmap-<name>-<pid>`, emptied on creation and removed on drop; unique per test
/// when `name` is.
pub struct Scratch(pub PathBuf);

impl Scratch {
    /// Creates (or empties) the directory.
    pub fn new(name: &str) -> Self {
        Self::under(&std::env::temp_dir(), name)
    }

    /// As [`Self::new`], under `parent` instead of $TMPDIR (e.g. /dev/shm, when a test
    /// is about a file's size or layout and not about the disk).
    pub fn under(parent: &Path, name: &str) -> Self {
        let dir = parent.join(format!("kfmap-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)
            .unwrap_or_else(|e| panic!("scratch directory {}: {e}", dir.display()));
        Self(dir)
    }

    /// A path inside the directory.
    pub fn file(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
