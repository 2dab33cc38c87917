//! `sensor_msgs/PointCloud2` and `sensor_msgs/Imu` decoding checked against an
//! independent serializer: `tests/support/messages.py` writes messages with the Python
//! `rosbags` package (ROS 2 CDR and ROS 1) and the values a decoder must find.
//!
//! The Python is what `tests/support/bag_venv.sh` gives (`$KFMAP_BAG_PYTHON`, else a venv
//! it creates); without one these tests skip (fail under `CI=true`).
//! The hostile-input tests that need no Python run everywhere.

use std::alloc::{GlobalAlloc, Layout, System};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};

use kfmap_bag::Encoding;
use kfmap_bag::msg::{
    PointCloud2, Stamp, TimeUnit, datatype_name, decode_imu, decode_point_cloud2,
    encode_point_cloud2,
};
use proptest::prelude::*;
use serde_json::Value;

/// Records the largest single allocation, so a test can show a hostile length prefix
/// did not make the decoder reserve memory for it.
struct Tracking;

static LARGEST_ALLOCATION: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call forwards to the system allocator unchanged; the only addition is
// an atomic maximum, which neither allocates nor touches the memory handed out.
unsafe impl GlobalAlloc for Tracking {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST_ALLOCATION.fetch_max(layout.size(), Ordering::Relaxed);
        // SAFETY: the caller's contract for `alloc` is passed on as is.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` through `alloc` / `realloc` above.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST_ALLOCATION.fetch_max(new_size, Ordering::Relaxed);
        // SAFETY: the caller's contract for `realloc` is passed on as is.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Tracking = Tracking;

/// The messages the Python script wrote, read into memory, and its manifest.
struct Generated {
    manifest: Vec<Value>,
    files: HashMap<String, Vec<u8>>,
}

impl Generated {
    fn bytes(&self, file: &str) -> &[u8] {
        self.files
            .get(file)
            .unwrap_or_else(|| panic!("{file} not generated"))
    }

    /// Manifest entries of message type `ty` with key `key` (`expect` or `error`).
    fn entries<'a>(&'a self, ty: &'a str, key: &'a str) -> impl Iterator<Item = &'a Value> {
        self.manifest
            .iter()
            .filter(move |e| e["type"] == ty && e.get(key).is_some())
    }
}

/// The interpreter `tests/support/bag_venv.sh` (at the workspace root) gives:
/// `$KFMAP_BAG_PYTHON`, else its venv with rosbags, created from PyPI on first use.
fn python() -> Option<PathBuf> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/support/bag_venv.sh");
    let out = Command::new(script).output().ok()?;
    out.status
        .success()
        .then(|| PathBuf::from(String::from_utf8_lossy(&out.stdout).trim()))
}

/// Runs the script once per test process; `None` (after skip-or-fail) without Python.
fn generated(test: &str) -> Option<&'static Generated> {
    static GENERATED: OnceLock<Option<Generated>> = OnceLock::new();
    let generated = GENERATED.get_or_init(|| {
        let python = python()?;
        let dir = kfmap_testdata::Scratch::new("bag-messages");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/messages.py");
        let out = Command::new(&python)
            .arg(&script)
            .arg(&dir.0)
            .output()
            .unwrap_or_else(|e| panic!("running {}: {e}", python.display()));
        assert!(
            out.status.success(),
            "{} failed:\n{}",
            script.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        let manifest: Vec<Value> =
            serde_json::from_slice(&std::fs::read(dir.file("manifest.json")).unwrap()).unwrap();
        let files = manifest
            .iter()
            .map(|e| {
                let name = e["file"].as_str().unwrap().to_string();
                let bytes = std::fs::read(dir.file(&name)).unwrap();
                (name, bytes)
            })
            .collect();
        Some(Generated { manifest, files })
    });
    kfmap_testdata::require_capability(
        generated.is_some(),
        "python with rosbags (set KFMAP_BAG_PYTHON)",
        test,
    )?;
    generated.as_ref()
}

fn encoding(entry: &Value) -> Encoding {
    match entry["encoding"].as_str() {
        Some("cdr") => Encoding::Cdr,
        Some("ros1") => Encoding::Ros1,
        other => panic!("encoding {other:?}"),
    }
}

fn u64_of(v: &Value) -> u64 {
    v.as_u64()
        .unwrap_or_else(|| panic!("{v} is not an integer"))
}

fn stamp_of(v: &Value) -> Stamp {
    Stamp {
        sec: u64_of(&v[0]) as i64,
        nanosec: u64_of(&v[1]) as u32,
    }
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Expected f64 values, given as their bits.
fn f64_bits(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| f64::from_bits(u64_of(x)))
        .collect()
}

/// Expected f32 values, given as their bits.
fn f32s(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| f32::from_bits(u64_of(x) as u32))
        .collect()
}

/// Same value, or both NaN.
fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

fn unit_name(unit: TimeUnit) -> &'static str {
    match unit {
        TimeUnit::RelativeNanos => "RelativeNanos",
        TimeUnit::RelativeSeconds => "RelativeSeconds",
        TimeUnit::AbsoluteSeconds => "AbsoluteSeconds",
        TimeUnit::AbsoluteNanos => "AbsoluteNanos",
    }
}

/// Checks one decoded cloud against the manifest's expectations.
fn check_cloud(file: &str, msg: &PointCloud2<'_>, expect: &Value) {
    assert_eq!(msg.stamp, stamp_of(&expect["stamp"]), "{file}");
    assert_eq!(msg.frame_id, expect["frame_id"].as_str().unwrap(), "{file}");
    assert_eq!(u64::from(msg.height), u64_of(&expect["height"]), "{file}");
    assert_eq!(u64::from(msg.width), u64_of(&expect["width"]), "{file}");
    assert_eq!(
        u64::from(msg.point_step),
        u64_of(&expect["point_step"]),
        "{file}"
    );
    assert_eq!(
        u64::from(msg.row_step),
        u64_of(&expect["row_step"]),
        "{file}"
    );
    assert_eq!(
        Some(msg.is_bigendian),
        expect["is_bigendian"].as_bool(),
        "{file}"
    );
    assert_eq!(Some(msg.is_dense), expect["is_dense"].as_bool(), "{file}");
    assert_eq!(
        msg.data.len() as u64,
        u64::from(msg.height) * u64::from(msg.row_step),
        "{file}"
    );
    let fields: Vec<(String, u64, u64, u64)> = expect["fields"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let name = f[0].as_str().unwrap().to_string();
            (name, u64_of(&f[1]), u64_of(&f[2]), u64_of(&f[3]))
        })
        .collect();
    let got: Vec<(String, u64, u64, u64)> = msg
        .fields
        .iter()
        .map(|f| {
            let (offset, dt, count) = (f.offset.into(), f.datatype.into(), f.count.into());
            (f.name.clone(), offset, dt, count)
        })
        .collect();
    assert_eq!(got, fields, "{file}");

    let time_field = msg.time_field();
    match expect["time_field"].as_object() {
        None => assert_eq!(time_field, None, "{file}"),
        Some(tf) => {
            let time_field = time_field.unwrap_or_else(|| panic!("{file}: no time field"));
            assert_eq!(time_field.name, tf["name"].as_str().unwrap(), "{file}");
            assert_eq!(
                unit_name(time_field.unit),
                tf["unit"].as_str().unwrap(),
                "{file}"
            );
        }
    }
    assert_eq!(
        msg.ring_field().map(|f| f.name.as_str()),
        expect["ring_field"].as_str(),
        "{file}"
    );

    let cloud = msg.to_cloud().unwrap_or_else(|e| panic!("{file}: {e}"));
    assert_eq!(cloud.len(), msg.len(), "{file}");
    assert!(cloud.view_dirs.is_none());
    let (x, y, z) = (f32s(&expect["x"]), f32s(&expect["y"]), f32s(&expect["z"]));
    assert_eq!(x.len(), cloud.len(), "{file}");
    for (i, p) in cloud.points.iter().enumerate() {
        assert!(
            same(p[0], x[i]) && same(p[1], y[i]) && same(p[2], z[i]),
            "{file}: point {i} is {p:?}, expected {:?}",
            [x[i], y[i], z[i]]
        );
    }
    match expect["intensity"].is_null() {
        true => assert!(cloud.intensity.is_none(), "{file}"),
        false => {
            let want = f32s(&expect["intensity"]);
            let got = cloud.intensity.as_ref().unwrap();
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                assert!(same(*g, *w), "{file}: intensity {i} is {g}, expected {w}");
            }
            assert_eq!(got.len(), want.len());
        }
    }
    match expect["time"].is_null() {
        true => assert!(cloud.time.is_none(), "{file}"),
        false => {
            let want = f64s(&expect["time"]);
            let got = cloud.time.as_ref().unwrap();
            assert_eq!(got.len(), want.len());
            for (i, (&g, &w)) in got.iter().zip(&want).enumerate() {
                // f32 rounding of the exact value (+ a hair of f64 arithmetic); far from
                // the stamp (all-zero returns of absolute clocks) relative to the value.
                let tolerance = 1e-8 + w.abs() * 1.2e-7;
                assert!(
                    (g as f64 - w).abs() <= tolerance,
                    "{file}: time {i} is {g}, expected {w}"
                );
            }
        }
    }
}

#[test]
fn clouds_match_the_independent_serializer() {
    let Some(generated) = generated("clouds_match_the_independent_serializer") else {
        return;
    };
    let (mut checked, mut encoded_le) = (0, 0);
    for entry in generated.entries("PointCloud2", "expect") {
        let file = entry["file"].as_str().unwrap();
        let bytes = generated.bytes(file);
        let msg =
            decode_point_cloud2(bytes, encoding(entry)).unwrap_or_else(|e| panic!("{file}: {e}"));
        check_cloud(file, &msg, &entry["expect"]);
        checked += 1;
        // The encoder writes what the independent serializer wrote (little-endian CDR,
        // the one the ROS 2 node publishes), up to the end padding it may add.
        if encoding(entry) == Encoding::Cdr && bytes.get(..2) == Some(&[0, 1]) {
            let encoded = encode_point_cloud2(&msg).unwrap();
            let (body, padding) = bytes.split_at(encoded.len().min(bytes.len()));
            assert_eq!(encoded, body, "{file}: encoded");
            assert!(
                padding.len() < 4 && padding.iter().all(|&b| b == 0),
                "{file}"
            );
            encoded_le += 1;
        }
    }
    assert!(checked >= 30, "only {checked} clouds generated");
    assert!(
        encoded_le >= 10,
        "only {encoded_le} little-endian CDR clouds"
    );
}

#[test]
fn imus_match_the_independent_serializer() {
    let Some(generated) = generated("imus_match_the_independent_serializer") else {
        return;
    };
    let mut checked = 0;
    for entry in generated.entries("Imu", "expect") {
        let file = entry["file"].as_str().unwrap();
        let expect = &entry["expect"];
        let m = decode_imu(generated.bytes(file), encoding(entry))
            .unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(m.stamp, stamp_of(&expect["stamp"]), "{file}");
        assert_eq!(m.frame_id, expect["frame_id"].as_str().unwrap(), "{file}");
        assert_eq!(
            m.orientation.to_vec(),
            f64_bits(&expect["orientation"]),
            "{file}"
        );
        assert_eq!(
            m.orientation_covariance.to_vec(),
            f64_bits(&expect["orientation_covariance"])
        );
        assert_eq!(
            m.angular_velocity.to_vec(),
            f64_bits(&expect["angular_velocity"])
        );
        assert_eq!(
            m.angular_velocity_covariance.to_vec(),
            f64_bits(&expect["angular_velocity_covariance"])
        );
        assert_eq!(
            m.linear_acceleration.to_vec(),
            f64_bits(&expect["linear_acceleration"])
        );
        assert_eq!(
            m.linear_acceleration_covariance.to_vec(),
            f64_bits(&expect["linear_acceleration_covariance"])
        );
        let finite = m
            .linear_acceleration
            .iter()
            .chain(&m.angular_velocity)
            .all(|x| x.is_finite());
        match m.sample() {
            Some(s) => {
                assert!(finite, "{file}");
                assert_eq!(s.acc, m.linear_acceleration);
                assert_eq!(s.gyro, m.angular_velocity);
                assert_eq!(s.t, m.stamp.seconds());
            }
            None => assert!(!finite, "{file}"),
        }
        checked += 1;
    }
    assert!(checked >= 5, "only {checked} Imu messages generated");
}

#[test]
fn bad_layouts_are_refused_by_name() {
    let Some(generated) = generated("bad_layouts_are_refused_by_name") else {
        return;
    };
    let mut checked = 0;
    for entry in generated.entries("PointCloud2", "error") {
        let file = entry["file"].as_str().unwrap();
        let want = entry["error"].as_str().unwrap();
        match decode_point_cloud2(generated.bytes(file), encoding(entry)) {
            Ok(msg) => panic!("{file} decoded: {msg:?}"),
            Err(e) => assert!(e.to_string().contains(want), "{file}: '{e}' lacks '{want}'"),
        }
        checked += 1;
    }
    assert!(checked >= 16, "only {checked} bad clouds generated");
}

#[test]
fn every_truncation_is_an_error() {
    let Some(generated) = generated("every_truncation_is_an_error") else {
        return;
    };
    for file in [
        "seed_small.cdr",
        "seed_small.ros1",
        "ouster_bigendian_cdr.cdr",
    ] {
        let bytes = generated.bytes(file);
        let encoding = if file.ends_with(".cdr") {
            Encoding::Cdr
        } else {
            Encoding::Ros1
        };
        assert!(decode_point_cloud2(bytes, encoding).is_ok());
        for n in 0..bytes.len() {
            assert!(
                decode_point_cloud2(&bytes[..n], encoding).is_err(),
                "{file} cut at {n} decoded"
            );
        }
    }
    for (file, encoding) in [
        ("imu_0.cdr", Encoding::Cdr),
        ("imu_2_be.cdr", Encoding::Cdr),
        ("imu_3.ros1", Encoding::Ros1),
    ] {
        let bytes = generated.bytes(file);
        assert!(decode_imu(bytes, encoding).is_ok());
        for n in 0..bytes.len() {
            assert!(
                decode_imu(&bytes[..n], encoding).is_err(),
                "{file} cut at {n}"
            );
        }
    }
}

/// Where the frame_id length, the fields count and the data length lie in a
/// little-endian message (CDR offsets include the 4-byte encapsulation header).
fn length_offsets(bytes: &[u8], encoding: Encoding) -> [usize; 3] {
    let msg = decode_point_cloud2(bytes, encoding).unwrap();
    let data_len = msg.data.as_ptr() as usize - bytes.as_ptr() as usize - 4;
    let (frame_len, fields_count) = match encoding {
        Encoding::Cdr => {
            let frame_len = 4 + 8;
            let end = frame_len + 4 + msg.frame_id.len() + 1;
            // height and width after padding to 4 (counted from the body start).
            (frame_len, 4 + (end - 4).next_multiple_of(4) + 8)
        }
        Encoding::Ros1 => (12, 12 + 4 + msg.frame_id.len() + 8),
    };
    [frame_len, fields_count, data_len]
}

#[test]
fn hostile_lengths_are_errors_without_huge_allocations() {
    let Some(generated) = generated("hostile_lengths_are_errors_without_huge_allocations") else {
        return;
    };
    for (file, encoding) in [
        ("ouster_organized.cdr", Encoding::Cdr),
        ("ouster_organized.ros1", Encoding::Ros1),
    ] {
        let bytes = generated.bytes(file);
        for at in length_offsets(bytes, encoding) {
            for value in [u32::MAX, 0x7FFF_FFFF, bytes.len() as u32] {
                let mut patched = bytes.to_vec();
                patched[at..at + 4].copy_from_slice(&value.to_le_bytes());
                let err = decode_point_cloud2(&patched, encoding)
                    .expect_err(&format!("{file} with {value:#x} at byte {at}"));
                assert!(!err.to_string().is_empty());
            }
        }
    }
    let mut imu = generated.bytes("imu_0.cdr").to_vec();
    imu[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(decode_imu(&imu, Encoding::Cdr).is_err());
    // Other tests run alongside, but none allocates anywhere near this.
    let largest = LARGEST_ALLOCATION.load(Ordering::Relaxed);
    assert!(largest < 256 << 20, "an allocation of {largest} bytes");
}

#[test]
fn datatype_names_read_as_ros_writes_them() {
    let names: Vec<&str> = (0..=9).map(datatype_name).collect();
    assert_eq!(
        names,
        [
            "unknown", "INT8", "UINT8", "INT16", "UINT16", "INT32", "UINT32", "FLOAT32", "FLOAT64",
            "unknown"
        ]
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    /// Random bytes never panic either decoder, in either serialization; a plain CDR
    /// header is prepended half the time so the decoders get past it.
    #[test]
    fn random_bytes_never_panic(
        mut bytes in proptest::collection::vec(any::<u8>(), 0..400),
        cdr_header in any::<bool>(),
    ) {
        if cdr_header {
            bytes.splice(0..0, [0, 1, 0, 0]);
        }
        for encoding in [Encoding::Cdr, Encoding::Ros1] {
            if let Ok(msg) = decode_point_cloud2(&bytes, encoding) {
                let cloud = msg.to_cloud().expect("a decoded cloud converts");
                prop_assert_eq!(cloud.len(), msg.len());
            }
            let _ = decode_imu(&bytes, encoding);
        }
    }
}

/// Single-thread throughput of `to_cloud` on a 128 x 1024 Ouster-layout cloud (48-byte
/// points with x y z, intensity and `t`). Run in release:
/// `cargo test --release -p kfmap-bag --test integration messages:: -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement, not a check; run in release"]
fn to_cloud_throughput() {
    let (height, width, step) = (128u32, 1024u32, 48usize);
    let n = (height * width) as usize;
    let mut data = vec![0u8; n * step];
    for (i, p) in data.chunks_exact_mut(step).enumerate() {
        let f = i as f32;
        p[0..4].copy_from_slice(&f.sin().to_le_bytes());
        p[4..8].copy_from_slice(&f.cos().to_le_bytes());
        p[8..12].copy_from_slice(&(f * 1e-3).to_le_bytes());
        p[16..20].copy_from_slice(&(f % 100.0).to_le_bytes());
        p[20..24].copy_from_slice(&((i as u32 % 1024) * 97_000).to_le_bytes());
    }
    let field = |name: &str, offset, datatype| kfmap_bag::msg::PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    let msg = PointCloud2 {
        stamp: Stamp {
            sec: 1_700_000_000,
            nanosec: 0,
        },
        frame_id: "os_lidar".into(),
        height,
        width,
        fields: vec![
            field("x", 0, 7),
            field("y", 4, 7),
            field("z", 8, 7),
            field("intensity", 16, 7),
            field("t", 20, 6),
            field("reflectivity", 24, 4),
            field("ring", 26, 4),
            field("ambient", 28, 4),
            field("range", 32, 6),
        ],
        is_bigendian: false,
        point_step: step as u32,
        row_step: width * step as u32,
        data: &data,
        is_dense: true,
    };
    let rounds = 50;
    let start = std::time::Instant::now();
    let mut points = 0;
    for _ in 0..rounds {
        points += std::hint::black_box(msg.to_cloud().unwrap()).len();
    }
    let secs = start.elapsed().as_secs_f64();
    let bytes = (rounds * data.len()) as f64;
    println!(
        "to_cloud: {n} points x {rounds}: {:.2} ms per cloud, {:.2} GB/s of point bytes, \
         {:.1} Mpoints/s",
        secs / rounds as f64 * 1e3,
        bytes / secs / 1e9,
        points as f64 / secs / 1e6
    );
}
