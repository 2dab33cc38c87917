//! A spinning LiDAR's vertical-angle calibration error corrected on load: every return
//! raised (or lowered) by the same elevation, its range and azimuth kept. A sensor whose
//! beams sit slightly off their nominal angles sees flat ground as a shallow cone, which
//! scan-to-map registration reads as pitch and accumulates while driving (KITTI's HDL-64E:
//! 0.205 deg, the correction KISS-ICP applies to KITTI scans).

use super::PointCloud;
use crate::options::{InvalidOption, ensure};

/// Checks a vertical-angle offset (degrees) as every configuration that takes one does:
/// finite and within 5 degrees either way; the error names `vertical-angle-offset-deg`.
pub fn ensure_vertical_angle_offset(offset_deg: f64) -> Result<(), InvalidOption> {
    ensure(
        offset_deg.is_finite() && offset_deg.abs() <= 5.0,
        "vertical-angle-offset-deg",
        offset_deg,
        "-5 to 5 degrees",
    )
}

impl PointCloud {
    /// Raises every point's elevation (sensor frame, z up) by `offset_deg` about the
    /// sensor origin, keeping its range and azimuth. Points on the z axis (no azimuth)
    /// are left as they are. Other fields stay with their points.
    pub fn raise_elevation(&mut self, offset_deg: f64) {
        if offset_deg == 0.0 {
            return;
        }
        let (sin, cos) = offset_deg.to_radians().sin_cos();
        for p in &mut self.points {
            let [x, y, z] = p.map(f64::from);
            let horizontal = x.hypot(y);
            if horizontal <= f64::EPSILON {
                continue;
            }
            // Rotating (horizontal, z) in the vertical plane of the point's azimuth.
            let raised_horizontal = horizontal * cos - z * sin;
            let raised_z = horizontal * sin + z * cos;
            let scale = raised_horizontal / horizontal;
            *p = [(x * scale) as f32, (y * scale) as f32, raised_z as f32];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn elevation_rises_by_the_offset_with_range_and_azimuth_kept() {
        // Points built from spherical coordinates: the oracle is the same construction
        // at the raised elevation.
        let at = |range: f64, azimuth_deg: f64, elevation_deg: f64| {
            let (a, e) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
            [
                range * e.cos() * a.cos(),
                range * e.cos() * a.sin(),
                range * e.sin(),
            ]
        };
        let samples = [
            (10.0, 0.0, -24.8),
            (35.0, 97.0, -8.0),
            (60.0, -150.0, 2.0),
            (5.0, 181.0, 0.0),
        ];
        let mut cloud = PointCloud::from_points(
            samples
                .map(|(r, a, e)| at(r, a, e).map(|v| v as f32))
                .to_vec(),
        );
        cloud.points.push([0.0, 0.0, 3.0]);
        cloud.raise_elevation(0.205);
        for (p, (r, a, e)) in cloud.points.iter().zip(samples) {
            let want = at(r, a, e + 0.205);
            for k in 0..3 {
                assert!(
                    (f64::from(p[k]) - want[k]).abs() < 1e-5 * r,
                    "{p:?} vs {want:?}"
                );
            }
        }
        assert_eq!(cloud.points[4], [0.0, 0.0, 3.0]);
        let before = cloud.points.clone();
        cloud.raise_elevation(0.0);
        assert_eq!(cloud.points, before);
    }
}
