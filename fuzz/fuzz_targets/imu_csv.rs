//! Fuzzes the `imu.csv` reader (`t,ax,ay,az,gx,gy,gz`, or whitespace-separated logs):
//! any text gives samples or a named error, never a panic; samples are finite, and
//! what is read writes back (`format_imu_csv`) and reads again with as many samples.
//! Run: `cargo +nightly fuzz run imu_csv`.
#![no_main]

#[path = "common.rs"]
mod common;

use std::path::Path;

use kfmap_geometry::imu::{format_imu_csv, parse_imu_csv};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let path = Path::new("imu.csv");
    let Ok(samples) = parse_imu_csv(path, &text) else {
        return;
    };
    if !common::strict() {
        return;
    }
    for s in &samples {
        assert!(
            s.t.is_finite() && s.acc.iter().chain(&s.gyro).all(|v| v.is_finite()),
            "{s:?}"
        );
    }
    let again = parse_imu_csv(path, &format_imu_csv(&samples))
        .unwrap_or_else(|e| panic!("format_imu_csv output does not parse: {e}"));
    assert_eq!(again.len(), samples.len());
});
