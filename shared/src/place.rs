//! Place descriptors for global relocalization (issue 21, first piece): a Scan Context
//! (Kim and Kim, IROS 2018) of a scan, as its own code. Around the sensor, the plane is
//! cut into `rings` x `sectors` polar cells out to `max_range`; each cell keeps the
//! highest point above the sensor's floor. Turning the sensor about z shifts the
//! sectors, so two scans of one place compare by the best column shift, which is also
//! their yaw difference. A ring key (the share of occupied cells per ring) does not
//! change with yaw and ranks candidates before that comparison.

use std::f64::consts::TAU;

use crate::options::{InvalidOption, ensure};

/// The polar grid of a descriptor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanContextParams {
    /// Rings from the sensor out to `max_range`.
    pub rings: usize,
    /// Sectors around z (yaw resolution 360 deg / sectors).
    pub sectors: usize,
    /// Farthest point counted, metres (horizontal range).
    pub max_range: f64,
    /// Height of the sensor above the ground, metres: heights are kept from
    /// `-sensor_height` up, so the ground's cells are not empty.
    pub sensor_height: f64,
}

impl Default for ScanContextParams {
    /// The paper's grid: 20 rings to 80 m, 60 sectors of 6 deg.
    fn default() -> Self {
        Self {
            rings: 20,
            sectors: 60,
            max_range: 80.0,
            sensor_height: 2.0,
        }
    }
}

impl ScanContextParams {
    /// Checks the grid.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            (1..=256).contains(&self.rings),
            "rings",
            self.rings,
            "1 to 256",
        )?;
        ensure(
            (1..=720).contains(&self.sectors),
            "sectors",
            self.sectors,
            "1 to 720",
        )?;
        ensure(
            self.max_range.is_finite() && self.max_range > 0.0,
            "max-range",
            self.max_range,
            "a finite range > 0 m",
        )?;
        ensure(
            self.sensor_height.is_finite() && self.sensor_height >= 0.0,
            "sensor-height",
            self.sensor_height,
            "a finite height >= 0 m",
        )
    }

    /// Width of one sector, radians.
    pub fn sector_width(&self) -> f64 {
        TAU / self.sectors as f64
    }
}

/// The descriptor of one scan: `rings` x `sectors` heights, stored sector by sector
/// (a column per sector, what a comparison walks), with each column's norm.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanContext {
    params: ScanContextParams,
    columns: Vec<f32>,
    norms: Vec<f64>,
}

/// How well two descriptors match at their best yaw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaceMatch {
    /// 0 (same columns) to 1 (nothing alike): one minus the mean cosine similarity
    /// of the columns occupied in both.
    pub distance: f64,
    /// Rotation about z that takes the query's points onto the candidate's, radians
    /// in (-pi, pi], to within one sector width.
    pub yaw: f64,
}

impl ScanContext {
    /// The descriptor of `points` (sensor frame, z up). Points that are not finite or
    /// lie beyond `max_range` are left out.
    pub fn of_points(points: &[[f32; 3]], params: ScanContextParams) -> Self {
        let rings = params.rings;
        let mut columns = vec![0.0f32; rings * params.sectors];
        for p in points {
            let [x, y, z] = p.map(f64::from);
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                continue;
            }
            let range = x.hypot(y);
            if range >= params.max_range {
                continue;
            }
            let ring = ((range / params.max_range) * rings as f64) as usize;
            let azimuth = y.atan2(x).rem_euclid(TAU);
            let sector = ((azimuth / params.sector_width()) as usize).min(params.sectors - 1);
            // Height above the floor; a point below it still marks its cell occupied.
            let height = (z + params.sensor_height).max(f64::EPSILON) as f32;
            let cell = &mut columns[sector * rings + ring];
            *cell = cell.max(height);
        }
        let norms = columns
            .chunks(rings)
            .map(|c| c.iter().map(|&h| f64::from(h * h)).sum::<f64>().sqrt())
            .collect();
        Self {
            params,
            columns,
            norms,
        }
    }

    /// The grid it was made with.
    pub fn params(&self) -> &ScanContextParams {
        &self.params
    }

    /// Height kept in cell (`ring`, `sector`), metres above the floor (0: empty).
    pub fn cell(&self, ring: usize, sector: usize) -> f32 {
        self.columns[sector * self.params.rings + ring]
    }

    /// The share of occupied cells in each ring: the same whatever the yaw.
    pub fn ring_key(&self) -> Vec<f32> {
        let sectors = self.params.sectors;
        (0..self.params.rings)
            .map(|r| {
                let occupied = (0..sectors).filter(|&s| self.cell(r, s) > 0.0).count();
                occupied as f32 / sectors as f32
            })
            .collect()
    }

    /// The best column shift between `self` (query) and `candidate` (same grid), or
    /// `None` when the grids differ. Descriptors with no column occupied in both
    /// match at distance 1.
    pub fn compare(&self, candidate: &ScanContext) -> Option<PlaceMatch> {
        if self.params != candidate.params {
            return None;
        }
        let (rings, sectors) = (self.params.rings, self.params.sectors);
        let mut best = PlaceMatch {
            distance: 1.0,
            yaw: 0.0,
        };
        for shift in 0..sectors {
            let (mut similarity, mut shared) = (0.0, 0usize);
            for j in 0..sectors {
                let k = (j + shift) % sectors;
                let (norm_a, norm_b) = (self.norms[j], candidate.norms[k]);
                if norm_a == 0.0 || norm_b == 0.0 {
                    continue;
                }
                let a = &self.columns[j * rings..(j + 1) * rings];
                let b = &candidate.columns[k * rings..(k + 1) * rings];
                let dot: f64 = a.iter().zip(b).map(|(x, y)| f64::from(x * y)).sum();
                similarity += dot / (norm_a * norm_b);
                shared += 1;
            }
            if shared == 0 {
                continue;
            }
            let distance = 1.0 - similarity / shared as f64;
            if distance < best.distance {
                best = PlaceMatch {
                    distance,
                    yaw: wrap_angle(shift as f64 * self.params.sector_width()),
                };
            }
        }
        Some(best)
    }
}

/// `angle` in (-pi, pi].
fn wrap_angle(angle: f64) -> f64 {
    let a = angle.rem_euclid(TAU);
    if a > std::f64::consts::PI { a - TAU } else { a }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::SmallRng;
    use rand::{Rng, SeedableRng};

    /// A site of boxes of random heights scattered around the origin, sampled on
    /// their outlines, plus a ground ring: structure that differs with direction.
    fn site(seed: u64) -> Vec<[f32; 3]> {
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut points = Vec::new();
        for _ in 0..40 {
            let (cx, cy) = (rng.random_range(-60.0..60.0), rng.random_range(-60.0..60.0));
            let height: f32 = rng.random_range(0.5..12.0);
            for k in 0..200 {
                let t = k as f32 / 200.0 * std::f32::consts::TAU;
                let z = rng.random_range(-2.0..height - 2.0);
                points.push([cx + 1.5 * t.cos(), cy + 1.5 * t.sin(), z]);
            }
        }
        for k in 0..720 {
            let t = k as f32 / 720.0 * std::f32::consts::TAU;
            points.push([5.0 * t.cos(), 5.0 * t.sin(), -2.0]);
        }
        points
    }

    fn turned(points: &[[f32; 3]], yaw: f64) -> Vec<[f32; 3]> {
        let (s, c) = yaw.sin_cos();
        points
            .iter()
            .map(|p| {
                let (x, y) = (f64::from(p[0]), f64::from(p[1]));
                [(c * x - s * y) as f32, (s * x + c * y) as f32, p[2]]
            })
            .collect()
    }

    #[test]
    fn turning_by_whole_sectors_shifts_the_columns_and_gives_the_yaw() {
        let params = ScanContextParams::default();
        let points = site(1);
        let query = ScanContext::of_points(&points, params);
        for sectors in [1usize, 7, 30, 45] {
            let yaw = (sectors as f64) * params.sector_width();
            let candidate = ScanContext::of_points(&turned(&points, yaw), params);
            let m = query.compare(&candidate).unwrap();
            assert!(m.distance < 0.02, "{sectors} sectors: {m:?}");
            assert!(
                (wrap_angle(m.yaw - yaw)).abs() < 1e-9,
                "{sectors} sectors: yaw {} for {}",
                m.yaw,
                wrap_angle(yaw)
            );
            assert_eq!(query.ring_key(), candidate.ring_key());
        }
    }

    #[test]
    fn any_yaw_is_found_to_within_a_sector() {
        let params = ScanContextParams::default();
        let points = site(2);
        let query = ScanContext::of_points(&points, params);
        // Between sector borders the cells' highest points differ, but the same place
        // stays closer than any other.
        let elsewhere = (10..20)
            .map(|seed| {
                let other = ScanContext::of_points(&site(seed), params);
                query.compare(&other).unwrap().distance
            })
            .fold(f64::INFINITY, f64::min);
        let mut rng = SmallRng::seed_from_u64(3);
        for _ in 0..20 {
            let yaw = rng.random_range(-3.1..3.1);
            let candidate = ScanContext::of_points(&turned(&points, yaw), params);
            let m = query.compare(&candidate).unwrap();
            assert!(
                wrap_angle(m.yaw - yaw).abs() <= params.sector_width(),
                "yaw {} for {yaw}",
                m.yaw
            );
            assert!(m.distance < elsewhere, "{m:?}, elsewhere {elsewhere}");
        }
    }

    #[test]
    fn another_place_is_farther_than_the_same_place_turned() {
        let params = ScanContextParams::default();
        let here = ScanContext::of_points(&site(4), params);
        let same = ScanContext::of_points(&turned(&site(4), 1.0), params);
        for seed in 5..15 {
            let elsewhere = ScanContext::of_points(&site(seed), params);
            let (d_same, d_other) = (
                here.compare(&same).unwrap().distance,
                here.compare(&elsewhere).unwrap().distance,
            );
            assert!(d_other > d_same + 0.1, "seed {seed}: {d_other} vs {d_same}");
        }
    }

    #[test]
    fn bad_points_and_empty_scans_are_handled() {
        let params = ScanContextParams::default();
        let empty = ScanContext::of_points(&[], params);
        assert!(empty.ring_key().iter().all(|&k| k == 0.0));
        let junk = [
            [f32::NAN, 0.0, 0.0],
            [f32::INFINITY, 1.0, 0.0],
            [100.0, 0.0, 0.0], // beyond max_range
        ];
        assert_eq!(ScanContext::of_points(&junk, params), empty);
        let some = ScanContext::of_points(&site(1), params);
        let m = empty.compare(&some).unwrap();
        assert_eq!(m.distance, 1.0);
        // A point on the ground below the floor still marks its cell.
        let low = ScanContext::of_points(&[[1.0, 0.0, -5.0]], params);
        assert!(low.cell(0, 0) > 0.0);
        // Grids that differ do not compare.
        let other = ScanContextParams {
            sectors: 30,
            ..params
        };
        assert!(
            some.compare(&ScanContext::of_points(&site(1), other))
                .is_none()
        );
        assert!(ScanContextParams { rings: 0, ..params }.validate().is_err());
    }
}
