//! Per-point times of a spinning LiDAR's scan recovered from the points' azimuths, for
//! scans stored without them (KITTI's velodyne `.bin`): a sensor turning at a constant
//! rate fires each column at a time proportional to its azimuth angle along the sweep, so
//! `t(p) = seconds * (u(p) - u(stamp))` with `u` the share of the sweep from its start
//! azimuth to the point's, in the spin direction. With those times the motion model's
//! constant-velocity deskew ([`crate::motion::PosePredictor::mid_scan`]) applies unchanged;
//! it is what KISS-ICP 0.x did for KITTI (`t = 0.5 (-atan2(y, x) / pi + 1)`: a clockwise
//! sweep from behind the sensor, forward at mid-sweep).
//!
//! The assumption fails for sensors that do not sweep in azimuth (solid-state, Livox's
//! rosettes), for scans already deskewed by their source (times would deskew them twice),
//! and where the sensor's azimuth is not the scan frame's (a sensor mounted rotated about
//! its vertical axis needs `start-deg` and `stamp-deg` turned with it).

use serde::{Deserialize, Deserializer, Serialize};

use crate::cloud::PointCloud;
use crate::options::{InvalidOption, ensure};

/// Which scans the odometry deskews with its constant-velocity twist, and where their
/// per-point times come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum DeskewMode {
    /// Per-point times when the scans have them; otherwise times from the azimuth when the
    /// caller knows the scans are raw sweeps of a spinning sensor (`kfmap bake`: KITTI
    /// `x y z intensity` `.bin` files); otherwise none. Without that knowledge, as
    /// `per-point`.
    #[default]
    Auto,
    /// Only scans with per-point times (the setting's former `true`).
    PerPoint,
    /// Per-point times when present, else times from each point's azimuth
    /// ([`SweepParams`]) for every scan.
    Azimuth,
    /// Never (the former `false`).
    Off,
}

impl DeskewMode {
    /// The names accepted in configuration files and on the command line.
    pub const NAMES: &'static str = "auto, per-point, azimuth, off";

    /// Parses a name of [`DeskewMode::NAMES`].
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "per-point" => Some(Self::PerPoint),
            "azimuth" => Some(Self::Azimuth),
            "off" => Some(Self::Off),
            _ => None,
        }
    }

    /// True unless `off`: scans with per-point times are deskewed.
    pub fn uses_point_times(self) -> bool {
        self != Self::Off
    }

    /// `auto` settled for scans that are (`raw_sweeps`) or may not be raw spinning
    /// sweeps without times; other modes unchanged.
    pub fn resolve(self, raw_sweeps: bool) -> Self {
        match self {
            Self::Auto if raw_sweeps => Self::Azimuth,
            Self::Auto => Self::PerPoint,
            other => other,
        }
    }
}

impl std::fmt::Display for DeskewMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Auto => "auto",
            Self::PerPoint => "per-point",
            Self::Azimuth => "azimuth",
            Self::Off => "off",
        })
    }
}

impl<'de> Deserialize<'de> for DeskewMode {
    /// A name of [`DeskewMode::NAMES`], or the former booleans (`true` = `per-point`,
    /// `false` = `off`).
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Flag(bool),
            Name(String),
        }
        match Raw::deserialize(deserializer)? {
            Raw::Flag(true) => Ok(Self::PerPoint),
            Raw::Flag(false) => Ok(Self::Off),
            Raw::Name(name) => Self::parse(&name).ok_or_else(|| {
                serde::de::Error::custom(format!(
                    "deskew = \"{name}\" is not one of {} (or true / false)",
                    Self::NAMES
                ))
            }),
        }
    }
}

/// Which way the sensor turns, seen from above (+Z).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SpinDirection {
    /// Azimuth decreasing with time (Velodyne HDL / VLP, KITTI).
    Clockwise,
    /// Azimuth increasing with time (kfmap's simulator).
    CounterClockwise,
}

/// A spinning sensor's sweep, for per-point times from azimuth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct SweepParams {
    /// Seconds one sweep lasts (one turn: 0.1 s at 10 Hz). Where the scans have no
    /// timestamps (stamps are scan indices) `kfmap bake` takes one scan interval instead.
    pub seconds: f64,
    /// Which way the sensor turns.
    pub direction: SpinDirection,
    /// Azimuth where each sweep starts and ends, degrees from +X towards +Y (sensor frame).
    pub start_deg: f64,
    /// Azimuth the sensor points at at the scan's stamp (the time its pose is for),
    /// degrees from +X towards +Y.
    pub stamp_deg: f64,
}

impl Default for SweepParams {
    /// KITTI's HDL-64E: 10 Hz, clockwise, from behind the sensor, stamped (and its
    /// ground truth given) facing forward, at mid-sweep.
    fn default() -> Self {
        Self {
            seconds: 0.1,
            direction: SpinDirection::Clockwise,
            start_deg: 180.0,
            stamp_deg: 0.0,
        }
    }
}

impl SweepParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            self.seconds.is_finite() && self.seconds > 0.0,
            "seconds",
            self.seconds,
            "a finite duration > 0 s",
        )?;
        ensure(
            self.start_deg.is_finite(),
            "start-deg",
            self.start_deg,
            "a finite angle",
        )?;
        ensure(
            self.stamp_deg.is_finite(),
            "stamp-deg",
            self.stamp_deg,
            "a finite angle",
        )
    }

    /// Share of the sweep (0 to 1) elapsed when the sensor points at azimuth `az`
    /// (radians from +X towards +Y).
    fn share(&self, az: f64) -> f64 {
        let turned = match self.direction {
            SpinDirection::CounterClockwise => az - self.start_deg.to_radians(),
            SpinDirection::Clockwise => self.start_deg.to_radians() - az,
        };
        turned.rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU
    }

    /// Each point's time, seconds after the scan's stamp, from its azimuth.
    pub fn point_times(&self, points: &[[f32; 3]]) -> Vec<f32> {
        let stamp = self.share(self.stamp_deg.to_radians());
        points
            .iter()
            .map(|p| {
                let az = f64::from(p[1]).atan2(f64::from(p[0]));
                (self.seconds * (self.share(az) - stamp)) as f32
            })
            .collect()
    }

    /// Gives `scan` per-point times from the azimuth unless it has its own; true when it
    /// got them.
    pub fn time_scan(&self, scan: &mut PointCloud) -> bool {
        if scan.time.is_some() {
            return false;
        }
        scan.time = Some(self.point_times(&scan.points));
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(deg: f64) -> [f32; 3] {
        let (s, c) = deg.to_radians().sin_cos();
        [10.0 * c as f32, 10.0 * s as f32, -1.0]
    }

    #[test]
    fn kitti_sweeps_clockwise_from_behind_with_the_stamp_forward() {
        let sweep = SweepParams::default();
        let t = sweep.point_times(&[at(179.0), at(90.0), at(0.0), at(-90.0), at(-179.0)]);
        let want = [-0.0497, -0.025, 0.0, 0.025, 0.0497];
        for (got, want) in t.iter().zip(want) {
            assert!((f64::from(*got) - want).abs() < 1e-4, "{t:?}");
        }
        // KISS-ICP 0.x's KITTI times, 0.5 (-atan2 / pi + 1), are the same up to the
        // mid-sweep offset and the sweep's duration.
        let kiss = |deg: f64| 0.5 * (-deg.to_radians() / std::f64::consts::PI + 1.0);
        for deg in [170.0, 45.0, -30.0] {
            let got = f64::from(sweep.point_times(&[at(deg)])[0]);
            assert!((got - 0.1 * (kiss(deg) - 0.5)).abs() < 1e-6);
        }
    }

    #[test]
    fn a_counter_clockwise_sweep_stamped_at_its_start() {
        let sweep = SweepParams {
            seconds: 0.2,
            direction: SpinDirection::CounterClockwise,
            start_deg: 0.0,
            stamp_deg: 0.0,
        };
        let t = sweep.point_times(&[at(0.0), at(90.0), at(270.0)]);
        assert!(t[0].abs() < 1e-6 && (t[1] - 0.05).abs() < 1e-6 && (t[2] - 0.15).abs() < 1e-6);
        let mut scan = PointCloud::from_points(vec![at(90.0)]);
        assert!(sweep.time_scan(&mut scan));
        scan.time = Some(vec![0.01]);
        assert!(!sweep.time_scan(&mut scan));
        assert_eq!(scan.time, Some(vec![0.01]));
    }

    #[test]
    fn modes_parse_names_and_the_former_booleans() {
        #[derive(Deserialize)]
        struct Doc {
            deskew: DeskewMode,
        }
        let parse = |text: &str| toml::from_str::<Doc>(text).map(|d| d.deskew);
        assert_eq!(parse("deskew = true").unwrap(), DeskewMode::PerPoint);
        assert_eq!(parse("deskew = false").unwrap(), DeskewMode::Off);
        assert_eq!(parse("deskew = \"azimuth\"").unwrap(), DeskewMode::Azimuth);
        let err = parse("deskew = \"kiss\"").unwrap_err().to_string();
        assert!(err.contains("auto, per-point, azimuth, off"), "{err}");
        assert_eq!(DeskewMode::Auto.resolve(true), DeskewMode::Azimuth);
        assert_eq!(DeskewMode::Auto.resolve(false), DeskewMode::PerPoint);
        assert_eq!(DeskewMode::Off.resolve(true), DeskewMode::Off);
        assert!(
            SweepParams {
                seconds: 0.0,
                ..SweepParams::default()
            }
            .validate()
            .is_err()
        );
    }
}
