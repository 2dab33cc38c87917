//! Harness of the multi-process tests: a `kfmap serve` child with its own iceoryx2
//! prefix, removed with its shared-memory files when dropped (also after a kill).

#![allow(dead_code)]

pub mod fixtures;
pub mod picture;

/// The libtest name of test `name` of the module at `module` (its `module_path!()`):
/// the path without the binary's crate name, as `--exact` matches it.
pub fn test_name(module: &str, name: &str) -> String {
    match module.split_once("::") {
        Some((_, path)) => format!("{path}::{name}"),
        None => name.to_string(),
    }
}

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{Pose, rotation_distance, translation_distance};
use kfmap_map::archive::save_map;
use kfmap_map::map::{Keyframe, KeyframeMap, KeyframeMapOptions};
use kfmap_protocol::transport::{iceoryx_config, remove_prefix_files};

/// A finished command's standard error as text.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A finished command's standard output as text.
pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `kfmap ARGS`, which must succeed; its standard output.
pub fn run_ok(args: &[&str]) -> String {
    let out = kfmap(args);
    assert!(
        out.status.success(),
        "kfmap {args:?} failed: {}",
        stderr(&out)
    );
    stdout(&out)
}

/// The kfmap binary.
pub fn kfmap_bin() -> &'static str {
    env!("CARGO_BIN_EXE_kfmap")
}

/// The JSON object a successful kfmap run printed (its stderr shown on failure).
pub fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "kfmap failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("stdout is one JSON object")
}

/// Runs kfmap to completion.
pub fn kfmap(args: &[&str]) -> Output {
    Command::new(kfmap_bin())
        .args(args)
        .output()
        .expect("run kfmap")
}

/// Runs `command` (a `kfmap` invocation) and returns its output, failing the test with
/// its standard error when it does not succeed.
pub fn succeeded(command: &mut Command) -> Output {
    let out = command.output().expect("run kfmap");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A test's temporary directory, removed with everything in it when dropped.
pub struct TestDir(PathBuf);

impl std::ops::Deref for TestDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A fresh temporary directory for one test.
pub fn temp_dir(test: &str) -> TestDir {
    let dir = std::env::temp_dir().join(format!("kfmap-e2e-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    TestDir(dir)
}

/// An iceoryx2 prefix no other test (or test run) uses.
pub fn unique_prefix(test: &str) -> String {
    format!("kfmt_{test}_{}_", std::process::id())
}

/// Removes every iceoryx2 file of `prefix` (what a killed process leaves).
pub fn remove_shared_memory(prefix: &str) {
    let config = iceoryx_config(Some(prefix)).expect("valid prefix");
    remove_prefix_files(&config, prefix);
}

/// Owns one test's iceoryx2 prefix: its files are removed at drop.
pub struct Prefix(pub String);

impl Prefix {
    /// A new prefix for `test`, clean of leftovers (and, once per run, of every test
    /// prefix of an earlier test process that was killed before its drops ran).
    pub fn new(test: &str) -> Self {
        static SWEPT: std::sync::Once = std::sync::Once::new();
        SWEPT.call_once(remove_dead_runs_shared_memory);
        let p = unique_prefix(test);
        remove_shared_memory(&p);
        Self(p)
    }
}

/// Removes the iceoryx2 files of every `kfmt_<test>_<pid>_` prefix in /dev/shm whose
/// test process is gone: a killed `cargo test` never runs its `Prefix` drops.
pub fn remove_dead_runs_shared_memory() {
    let Ok(entries) = std::fs::read_dir("/dev/shm") else {
        return;
    };
    let mut dead = std::collections::BTreeSet::new();
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(prefix) = dead_test_prefix(&name) {
            dead.insert(prefix);
        }
    }
    for prefix in dead {
        remove_shared_memory(&prefix);
    }
}

/// `kfmt_<test>_<pid>_` of a file named by [`unique_prefix`] when process `pid` no
/// longer runs (test names hold no all-digit `_` segment).
fn dead_test_prefix(file: &str) -> Option<String> {
    let rest = file.strip_prefix("kfmt_")?;
    let segments: Vec<&str> = rest.split('_').collect();
    let at = (1..segments.len())
        .find(|&k| !segments[k].is_empty() && segments[k].bytes().all(|b| b.is_ascii_digit()))?;
    let pid = segments[at];
    let alive = Path::new("/proc").join(pid).exists();
    (!alive).then(|| format!("kfmt_{}_{pid}_", segments[..at].join("_")))
}

impl Drop for Prefix {
    fn drop(&mut self) {
        remove_shared_memory(&self.0);
    }
}

/// A running `kfmap serve`.
pub struct Server {
    pub child: Child,
    pub ready_line: String,
    stderr: Option<std::thread::JoinHandle<String>>,
}

impl Server {
    /// Starts `kfmap serve --map MAP --map-name NAME --iceoryx-prefix PREFIX [extra]` and
    /// waits for its ready line.
    pub fn start(map: &Path, name: &str, prefix: &str, extra: &[&str]) -> Self {
        let map = ["--map", map.to_str().unwrap()];
        Self::spawn(
            &[
                &map[..],
                &["--map-name", name, "--iceoryx-prefix", prefix],
                extra,
            ]
            .concat(),
        )
    }

    /// Starts `kfmap serve --tiles DIR --map-name NAME --iceoryx-prefix PREFIX --only
    /// IDS` and waits for its ready line (after every tile's).
    pub fn start_tiles(dir: &Path, name: &str, prefix: &str, only: &str) -> Self {
        let tiles = ["--tiles", dir.to_str().unwrap(), "--only", only];
        Self::spawn(
            &[
                &tiles[..],
                &["--map-name", name, "--iceoryx-prefix", prefix],
            ]
            .concat(),
        )
    }

    /// Starts `kfmap serve ARGS` and waits for the line starting "ready:".
    fn spawn(args: &[&str]) -> Self {
        let mut child = Command::new(kfmap_bin())
            .arg("serve")
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn kfmap serve");
        let stdout = child.stdout.take().unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let stderr = std::thread::spawn(move || {
            let mut all = String::new();
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                all.push_str(&line);
                all.push('\n');
            }
            all
        });
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        // A tile server prints a line per tile before its ready line.
        let ready = std::iter::from_fn(|| {
            rx.recv_timeout(deadline.saturating_duration_since(std::time::Instant::now()))
                .ok()
        })
        .find(|line| line.starts_with("ready:"));
        let ready_line = match ready {
            Some(line) => line,
            None => {
                let _ = child.kill();
                let _ = child.wait();
                panic!(
                    "server never got ready: {}",
                    stderr.join().unwrap_or_default()
                );
            }
        };
        assert!(ready_line.starts_with("ready:"), "{ready_line}");
        Self {
            child,
            ready_line,
            stderr: Some(stderr),
        }
    }

    /// Sends SIGTERM and returns the exit status and stderr.
    pub fn stop(mut self) -> (std::process::ExitStatus, String) {
        signal(&self.child, libc::SIGTERM);
        let status = self.child.wait().unwrap();
        let err = self.stderr.take().unwrap().join().unwrap_or_default();
        (status, err)
    }

    /// SIGKILL, no cleanup.
    pub fn kill(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Sends `sig` to `child`.
pub fn signal(child: &Child, sig: i32) {
    // SAFETY: plain kill(2) on our own child's pid.
    unsafe {
        libc::kill(child.id() as i32, sig);
    }
}

/// Bakes a map of `keyframes` (local clouds at `T_map_keyframe` poses), each
/// downsampled at `voxel` metres, with the shipped map options.
pub fn bake_map(path: &Path, keyframes: &[(PointCloud, Pose)], voxel: f64) {
    bake_map_with(path, keyframes, voxel, KeyframeMapOptions::default());
}

/// As [`bake_map`] with other map options. With `fuse_voxel_size` set, keyframes are
/// voxelized on the map's grid with their counts, as `kfmap bake` does when fusing
/// (the same `PointCloud::into_keyframe_points`).
pub fn bake_map_with(
    path: &Path,
    keyframes: &[(PointCloud, Pose)],
    voxel: f64,
    options: KeyframeMapOptions,
) {
    let mut map = KeyframeMap::new(options).unwrap();
    let fused = options.fuse_voxel_size > 0.0;
    for (i, (cloud, pose)) in keyframes.iter().enumerate() {
        let (cloud, weights) = cloud
            .clone()
            .into_keyframe_points(voxel, fused.then_some(pose))
            .unwrap();
        let id = i as u64;
        let keyframe =
            Keyframe::build_weighted(id, *pose, i as f64, cloud, weights, &options.covariance);
        map.insert_keyframe(keyframe.unwrap()).unwrap();
    }
    save_map(&map, &[], path).unwrap();
}

/// A simulated dataset written by `kfmap simulate`.
pub fn simulate(dir: &Path, preset: &str, seconds: &str, beams: &str, extra: &[&str]) {
    succeeded(
        Command::new(kfmap_bin())
            .args(["simulate", "--preset", preset, "--seconds", seconds])
            .args(["--beams", beams, "--out", dir.to_str().unwrap()])
            .args(extra),
    );
}

/// `kfmap bake --dataset DIR --out MAP` (poses from the dataset).
pub fn bake_dataset(dataset: &Path, map: &Path) {
    let out = kfmap(&[
        "bake",
        "--dataset",
        dataset.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
        "--force",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A dataset of links to `scans` (renumbered from 0) with `pose_lines` as its pose file.
pub fn linked_dataset(dir: &Path, scans: &[PathBuf], pose_lines: &[&str]) {
    std::fs::create_dir_all(dir.join("scans")).unwrap();
    for (i, scan) in scans.iter().enumerate() {
        let name = format!("{i:06}.{}", scan.extension().unwrap().to_str().unwrap());
        std::os::unix::fs::symlink(scan, dir.join("scans").join(name)).unwrap();
    }
    std::fs::write(dir.join("poses.txt"), pose_lines.join("\n") + "\n").unwrap();
}

/// `T_map_input` of the map `name` serves under `prefix`, as its `Status` reports it:
/// what moves a dataset's own poses into the (levelled) map frame.
pub fn map_from_input(name: &str, prefix: &str) -> Pose {
    let options = kfmap_client::ClientOptions {
        iceoryx_prefix: Some(prefix.to_string()),
        ..kfmap_client::ClientOptions::default()
    };
    kfmap_client::Client::connect(name, options)
        .expect("connect")
        .status()
        .expect("status")
        .map_from_input
}

/// Normalized estimation error squared of the `ok` scans' published covariances
/// against the truth: the mean of `d^T C^-1 d` per group, rotation and position
/// (3 each for a calibrated covariance), with `d` the right perturbation from the
/// reported pose to the truth (`T^-1 G`: rotation vector, then translation, sensor
/// frame), as the covariance is defined; `scans` are `--json-lines` objects, one per
/// pose of `truth`. Returns (rotation, position, scans counted).
pub fn mean_nees(scans: &[serde_json::Value], truth: &[Pose]) -> (f64, f64, usize) {
    assert_eq!(scans.len(), truth.len(), "one reference per scan");
    let (mut rotation, mut position, mut n) = (0.0, 0.0, 0);
    for (scan, truth) in scans.iter().zip(truth) {
        if scan["status"] != "ok" {
            continue;
        }
        let values: Vec<f64> = serde_json::from_value(scan["covariance"].clone()).unwrap();
        let covariance = nalgebra::Matrix6::from_row_slice(&values);
        let reported: Vec<f64> = serde_json::from_value(scan["pose"].clone()).unwrap();
        let reported =
            kfmap_geometry::geometry::pose_from_xyz_quat(reported.try_into().unwrap()).unwrap();
        let d = reported.inverse() * truth;
        let nees = |e: nalgebra::Vector3<f64>, at: usize| {
            let block = covariance.fixed_view::<3, 3>(at, at).into_owned();
            e.dot(&(block.try_inverse().expect("a full-rank covariance") * e))
        };
        rotation += nees(d.rotation.scaled_axis(), 0);
        position += nees(d.translation.vector, 3);
        n += 1;
    }
    (rotation / n as f64, position / n as f64, n)
}

/// Asserts [`mean_nees`] of `scans` against `truth` within the bounds, per group, over
/// at least `min_ok` scans `ok`, and prints the figures under `label`.
pub fn assert_nees(
    label: &str,
    scans: &[serde_json::Value],
    truth: &[Pose],
    min_ok: usize,
    rotation_within: std::ops::Range<f64>,
    position_within: std::ops::Range<f64>,
) {
    let (rotation, position, n) = mean_nees(scans, truth);
    println!(
        "{label}: mean NEES rotation {rotation:.2}, position {position:.2} (3 each when calibrated) over {n} ok scans"
    );
    assert!(n >= min_ok, "{label}: {n} ok scans");
    assert!(
        rotation_within.contains(&rotation),
        "{label}: rotation NEES {rotation}"
    );
    assert!(
        position_within.contains(&position),
        "{label}: position NEES {position}"
    );
}

/// Position (m) and rotation (deg) error of each pose against its reference, computed
/// here: the oracle of the localization tests, never the figures `kfmap localize`
/// prints about itself.
pub fn pose_errors(poses: &[Pose], reference: &[Pose]) -> Vec<(f64, f64)> {
    assert_eq!(poses.len(), reference.len(), "one reference per pose");
    poses
        .iter()
        .zip(reference)
        .map(|(p, r)| {
            (
                translation_distance(p, r),
                rotation_distance(p, r).to_degrees(),
            )
        })
        .collect()
}

/// RMS and largest of the position errors of [`pose_errors`], metres.
pub fn rms_and_max_m(errors: &[(f64, f64)]) -> (f64, f64) {
    let n = errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| e.0 * e.0).sum::<f64>() / n).sqrt();
    (rms, errors.iter().map(|e| e.0).fold(0.0, f64::max))
}
