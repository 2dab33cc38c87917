//! IMU samples and the `imu.csv` file (`t,ax,ay,az,gx,gy,gz`: seconds, m/s^2, rad/s;
//! whitespace-separated logs with the same columns read too).

use std::fmt::Write as _;
use std::path::Path;

use crate::io::{IoError, Location};

/// One IMU measurement in the body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSample {
    /// Time, seconds.
    pub t: f64,
    /// Specific force (accelerometer), m/s^2, body frame.
    pub acc: [f64; 3],
    /// Angular velocity (gyroscope), rad/s, body frame.
    pub gyro: [f64; 3],
}

/// Header line of `imu.csv`.
pub const IMU_CSV_HEADER: &str = "t,ax,ay,az,gx,gy,gz";

/// Formats samples as `imu.csv`, with the header line.
pub fn format_imu_csv(samples: &[ImuSample]) -> String {
    let mut out = String::with_capacity(samples.len() * 100 + 32);
    out.push_str(IMU_CSV_HEADER);
    out.push('\n');
    for s in samples {
        let [ax, ay, az] = s.acc;
        let [gx, gy, gz] = s.gyro;
        let _ = writeln!(
            out,
            "{:.6},{ax:.9},{ay:.9},{az:.9},{gx:.9},{gy:.9},{gz:.9}",
            s.t
        );
    }
    out
}

/// Parses `imu.csv` (header optional); the error names the file and line.
pub fn parse_imu_csv(path: &Path, text: &str) -> Result<Vec<ImuSample>, IoError> {
    let mut samples = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with('t') {
            continue;
        }
        let bad = |reason: String| IoError::malformed(path, Location::Line(k + 1), reason);
        // `imu.csv` is comma-separated; plain-text logs (t ax ay az wx wy wz) use spaces.
        let words: Vec<&str> = if line.contains(',') {
            line.split(',').collect()
        } else {
            line.split_whitespace().collect()
        };
        let v: Vec<f64> = words
            .iter()
            .map(|w| {
                w.trim()
                    .parse::<f64>()
                    .map_err(|_| bad(format!("'{}' is not a number", w.trim())))
            })
            .collect::<Result<_, _>>()?;
        if v.len() != 7 {
            return Err(bad(format!(
                "expected 7 comma-separated values ({IMU_CSV_HEADER}), found {}",
                v.len()
            )));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(bad("a value is not finite".into()));
        }
        samples.push(ImuSample {
            t: v[0],
            acc: [v[1], v[2], v[3]],
            gyro: [v[4], v[5], v[6]],
        });
    }
    Ok(samples)
}

/// Reads `imu.csv`.
pub fn read_imu_csv(path: &Path) -> Result<Vec<ImuSample>, IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::os(path, e))?;
    parse_imu_csv(path, &text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let samples: Vec<ImuSample> = (0..5)
            .map(|i| ImuSample {
                t: i as f64 * 0.005,
                acc: [0.1, -0.2, 9.81],
                gyro: [0.001 * i as f64, 0.0, -0.5],
            })
            .collect();
        let back = parse_imu_csv(Path::new("imu.csv"), &format_imu_csv(&samples)).unwrap();
        assert_eq!(back, samples);
        let err = parse_imu_csv(Path::new("imu.csv"), "t,ax,ay,az,gx,gy,gz\n0,1,2,3,4,5\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("line 2") && err.contains("expected 7"),
            "{err}"
        );
        let spaced = "0.5 0.1 -0.2 9.81 0.0 0.0 -0.5\n";
        let back = parse_imu_csv(Path::new("imu.txt"), spaced).unwrap();
        assert_eq!(back[0].acc, [0.1, -0.2, 9.81]);
        let err = parse_imu_csv(Path::new("imu.txt"), "0 1 2 nan 4 5 6\n").unwrap_err();
        assert!(err.to_string().contains("not finite"), "{err}");
    }
}
