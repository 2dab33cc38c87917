//! Removal of invalid LiDAR returns: non-finite points, points at exactly the sensor
//! origin (how many drivers encode "no return"), and points closer than a minimum range.

use serde::{Deserialize, Serialize};

use super::PointCloud;
use crate::options::{InvalidOption, ensure};

/// Options of the invalid-return filter, applied on load by default.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct FilterOptions {
    /// Apply the filter when reading clouds.
    pub enabled: bool,
    /// Points closer than this to the sensor origin are dropped, metres (>= 0).
    pub min_range: f64,
}

impl FilterOptions {
    /// Checks `min-range`; the error names it.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let r = self.min_range;
        ensure(
            r.is_finite() && r >= 0.0,
            "min-range",
            r,
            "a finite distance >= 0 m",
        )
    }
}

impl Default for FilterOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            min_range: 0.1,
        }
    }
}

/// How many points the filter dropped, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FilterReport {
    /// Points kept.
    pub kept: usize,
    /// Dropped: a coordinate was NaN or infinite.
    pub non_finite: usize,
    /// Dropped: exactly (0, 0, 0).
    pub at_origin: usize,
    /// Dropped: closer than `min_range` (and not at the origin).
    pub too_close: usize,
}

impl FilterReport {
    /// Total points dropped.
    pub fn dropped(&self) -> usize {
        self.non_finite + self.at_origin + self.too_close
    }
}

impl PointCloud {
    /// Removes invalid returns in place, keeping attribute arrays aligned, and reports
    /// what was dropped. Point order is preserved.
    pub fn remove_invalid(&mut self, min_range: f64) -> FilterReport {
        let min_range_sq = min_range * min_range;
        let mut report = FilterReport::default();
        let keep: Vec<usize> = (0..self.points.len())
            .filter(|&i| {
                let p = self.points[i];
                if p.iter().any(|c| !c.is_finite()) {
                    report.non_finite += 1;
                    return false;
                }
                if p == [0.0, 0.0, 0.0] {
                    report.at_origin += 1;
                    return false;
                }
                let range_sq: f64 = p.iter().map(|&c| (c as f64) * (c as f64)).sum();
                if range_sq < min_range_sq {
                    report.too_close += 1;
                    return false;
                }
                true
            })
            .collect();
        report.kept = keep.len();
        if report.dropped() > 0 {
            *self = self.select(&keep);
        }
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_each_reason_and_keeps_attributes_aligned() {
        let mut cloud = PointCloud::from_points(vec![
            [0.0, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [f32::NAN, 1.0, 1.0],
            [0.05, 0.0, 0.0],
            [0.0, -3.0, 4.0],
        ]);
        cloud.intensity = Some(vec![10.0, 11.0, 12.0, 13.0, 14.0]);
        let report = cloud.remove_invalid(0.1);
        assert_eq!(
            report,
            FilterReport {
                kept: 2,
                non_finite: 1,
                at_origin: 1,
                too_close: 1
            }
        );
        assert_eq!(cloud.points, vec![[5.0, 0.0, 0.0], [0.0, -3.0, 4.0]]);
        assert_eq!(cloud.intensity, Some(vec![11.0, 14.0]));
    }

    #[test]
    fn zero_min_range_still_drops_origin_points() {
        let mut cloud = PointCloud::from_points(vec![[0.0; 3], [0.01, 0.0, 0.0]]);
        let report = cloud.remove_invalid(0.0);
        assert_eq!(report.at_origin, 1);
        assert_eq!(cloud.len(), 1);
    }
}
