//! The ground-truth path: a closed cubic B-spline over the terrain, driven with a smooth
//! speed profile, the body frame following the path heading and the ground normal.
//! Velocity, acceleration and body rates come from central differences of the same
//! pose function, so the simulated IMU is consistent with the poses to ~1e-6.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};

use super::scene::Terrain;
use kfmap_geometry::geometry::Pose;

/// 8-point Gauss-Legendre nodes and weights on [-1, 1].
const GL_NODES: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (-0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
];

/// A closed uniform cubic B-spline in the plane, parameter `s` in `[0, n)`.
#[derive(Debug, Clone)]
pub struct ClosedSpline {
    control: Vec<Vector2<f64>>,
    /// Arc length from s = 0 to the start of each segment, and the total at the end.
    cumulative: Vec<f64>,
}

impl ClosedSpline {
    /// A spline rounding the closed polygon `control` (at least 4 points).
    pub fn new(control: &[[f64; 2]]) -> Self {
        assert!(
            control.len() >= 4,
            "a closed B-spline needs at least 4 control points"
        );
        let control: Vec<Vector2<f64>> = control.iter().map(|p| Vector2::new(p[0], p[1])).collect();
        let mut spline = Self {
            control,
            cumulative: vec![0.0],
        };
        for i in 0..spline.control.len() {
            let length = spline.length_within(i, 1.0);
            spline.cumulative.push(spline.cumulative[i] + length);
        }
        spline
    }

    fn points(&self, segment: usize) -> [Vector2<f64>; 4] {
        let n = self.control.len();
        std::array::from_fn(|k| self.control[(segment + k) % n])
    }

    /// Position and first derivative (per unit s) at `s`.
    pub fn eval(&self, s: f64) -> (Vector2<f64>, Vector2<f64>) {
        let n = self.control.len() as f64;
        let s = s.rem_euclid(n);
        let segment = (s.floor() as usize).min(self.control.len() - 1);
        let u = s - segment as f64;
        let [p0, p1, p2, p3] = self.points(segment);
        let (u2, u3, w) = (u * u, u * u * u, 1.0 - u);
        let pos = (p0 * w.powi(3)
            + p1 * (3.0 * u3 - 6.0 * u2 + 4.0)
            + p2 * (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0)
            + p3 * u3)
            / 6.0;
        let d = (p0 * (-3.0 * w * w)
            + p1 * (9.0 * u2 - 12.0 * u)
            + p2 * (-9.0 * u2 + 6.0 * u + 3.0)
            + p3 * (3.0 * u2))
            / 6.0;
        (pos, d)
    }

    /// Arc length from the start of `segment` to local parameter `u` in [0, 1].
    fn length_within(&self, segment: usize, u: f64) -> f64 {
        let half = u / 2.0;
        GL_NODES
            .iter()
            .map(|&(x, w)| w * half * self.eval(segment as f64 + half * (x + 1.0)).1.norm())
            .sum()
    }

    /// Total length of one lap, metres.
    pub fn total_length(&self) -> f64 {
        *self.cumulative.last().expect("at least one segment")
    }

    /// The parameter `s` at arc length `distance` (wrapped to one lap).
    pub fn param_at_distance(&self, distance: f64) -> f64 {
        let d = distance.rem_euclid(self.total_length());
        let segment = self
            .cumulative
            .partition_point(|&c| c <= d)
            .saturating_sub(1)
            .min(self.control.len() - 1);
        let (start, end) = (self.cumulative[segment], self.cumulative[segment + 1]);
        let mut u = ((d - start) / (end - start)).clamp(0.0, 1.0);
        // Newton on L(u) = d - start; dL/du = |p'|. Converges in a few steps.
        for _ in 0..30 {
            let f = self.length_within(segment, u) - (d - start);
            let speed = self.eval(segment as f64 + u).1.norm().max(1e-9);
            let step = f / speed;
            u = (u - step).clamp(0.0, 1.0);
            if step.abs() < 1e-14 {
                break;
            }
        }
        segment as f64 + u
    }
}

/// How fast the path is driven: a smooth start from rest to `cruise` m/s over `ramp`
/// seconds, then a gentle +-`swing` periodic speed change (so the IMU sees
/// accelerations all along).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedProfile {
    /// Cruise speed, m/s.
    pub cruise: f64,
    /// Duration of the start from rest, seconds.
    pub ramp: f64,
    /// Relative speed swing after the start, e.g. 0.2.
    pub swing: f64,
    /// Period of the swing, seconds.
    pub period: f64,
}

impl SpeedProfile {
    /// Distance travelled after `t` seconds (closed form of the speed integral).
    pub fn distance(&self, t: f64) -> f64 {
        let (v, r) = (self.cruise, self.ramp);
        if t <= 0.0 {
            return 0.0;
        }
        if t < r {
            let u = t / r;
            return v * r * (u.powi(3) - u.powi(4) / 2.0);
        }
        let tau = t - r;
        let w = std::f64::consts::TAU / self.period;
        v * r / 2.0 + v * (tau + self.swing / 2.0 * (tau - (w * tau).sin() / w))
    }
}

/// The vehicle path: where the body (= LiDAR = IMU) frame is at any time.
#[derive(Debug, Clone)]
pub struct Trajectory {
    spline: ClosedSpline,
    terrain: Terrain,
    speed: SpeedProfile,
    sensor_height: f64,
}

impl Trajectory {
    /// A path along `spline` over `terrain`, the sensor `sensor_height` m above ground.
    pub fn new(
        spline: ClosedSpline,
        terrain: Terrain,
        speed: SpeedProfile,
        sensor_height: f64,
    ) -> Self {
        Self {
            spline,
            terrain,
            speed,
            sensor_height,
        }
    }

    /// The path's plan-view spline.
    pub fn spline(&self) -> &ClosedSpline {
        &self.spline
    }

    /// How fast the path is driven.
    pub fn speed(&self) -> &SpeedProfile {
        &self.speed
    }

    /// The same path driven at `cruise` m/s (same start from rest and relative swing).
    pub fn with_cruise(mut self, cruise: f64) -> Self {
        self.speed.cruise = cruise;
        self
    }

    /// Seconds to drive one lap.
    pub fn lap_time(&self) -> f64 {
        // Distance is monotone in t: bisect.
        let lap = self.spline.total_length();
        let (mut lo, mut hi) = (0.0, 1.0);
        while self.speed.distance(hi) < lap {
            hi *= 2.0;
        }
        for _ in 0..100 {
            let mid = (lo + hi) / 2.0;
            if self.speed.distance(mid) < lap {
                lo = mid
            } else {
                hi = mid
            }
        }
        hi
    }

    /// `T_map_body` at time `t` seconds.
    pub fn pose(&self, t: f64) -> Pose {
        let s = self.spline.param_at_distance(self.speed.distance(t));
        let (p, d) = self.spline.eval(s);
        let n = self.terrain.normal(p.x, p.y);
        let h = 1e-4;
        let slope = (self.terrain.height(p.x + h * d.x, p.y + h * d.y)
            - self.terrain.height(p.x - h * d.x, p.y - h * d.y))
            / (2.0 * h);
        let tangent = Vector3::new(d.x, d.y, slope);
        let x = (tangent - n * tangent.dot(&n)).normalize();
        let y = n.cross(&x);
        let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, n]));
        let position = Vector3::new(p.x, p.y, self.terrain.height(p.x, p.y) + self.sensor_height);
        Pose::from_parts(
            position.into(),
            UnitQuaternion::from_rotation_matrix(&rotation),
        )
    }

    /// Velocity in the map frame, m/s.
    pub fn velocity(&self, t: f64) -> Vector3<f64> {
        let h = 1e-3;
        (self.pose(t + h).translation.vector - self.pose(t - h).translation.vector) / (2.0 * h)
    }

    /// Acceleration in the map frame, m/s^2.
    pub fn acceleration(&self, t: f64) -> Vector3<f64> {
        let h = 1e-3;
        let p = |t: f64| self.pose(t).translation.vector;
        (p(t + h) - p(t) * 2.0 + p(t - h)) / (h * h)
    }

    /// Angular velocity in the body frame, rad/s.
    pub fn body_rate(&self, t: f64) -> Vector3<f64> {
        let h = 1e-4;
        let delta = self.pose(t - h).rotation.inverse() * self.pose(t + h).rotation;
        delta.scaled_axis() / (2.0 * h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> ClosedSpline {
        ClosedSpline::new(&[[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0]])
    }

    #[test]
    fn arc_length_inverse_is_consistent() {
        let spline = square();
        let lap = spline.total_length();
        // The spline rounds a 20 m square: shorter than 80 m, longer than its inscribed circle.
        assert!(lap < 80.0 && lap > std::f64::consts::PI * 10.0, "{lap}");
        // Chord sums over fine steps approach the arc length.
        let steps = 20_000;
        let mut chord = 0.0;
        let mut prev = spline.eval(spline.param_at_distance(0.0)).0;
        for k in 1..=steps {
            let p = spline
                .eval(spline.param_at_distance(lap * k as f64 / steps as f64))
                .0;
            chord += (p - prev).norm();
            prev = p;
        }
        assert!((chord - lap).abs() < 1e-4, "{chord} vs {lap}");
    }

    #[test]
    fn speed_profile_is_continuous_and_starts_at_rest() {
        let sp = SpeedProfile {
            cruise: 3.0,
            ramp: 4.0,
            swing: 0.2,
            period: 15.0,
        };
        let speed = |t: f64| (sp.distance(t + 1e-6) - sp.distance(t - 1e-6)) / 2e-6;
        assert!(sp.distance(1e-3) < 1e-6);
        for t in [3.999999, 4.0, 4.000001] {
            assert!((speed(t) - 3.0).abs() < 1e-3, "{t}: {}", speed(t));
        }
        assert!((speed(4.0 + 7.5) - 3.0 * 1.2).abs() < 1e-6);
    }

    #[test]
    fn a_lap_returns_to_the_start() {
        let traj = Trajectory::new(
            square(),
            Terrain::Rolling {
                amplitude: 1.0,
                wavelength: 40.0,
            },
            SpeedProfile {
                cruise: 2.0,
                ramp: 3.0,
                swing: 0.1,
                period: 10.0,
            },
            1.8,
        );
        let lap = traj.lap_time();
        let (a, b) = (traj.pose(0.0), traj.pose(lap));
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-6);
        assert!(a.rotation.angle_to(&b.rotation) < 1e-6);
        // The body z axis is the ground normal.
        let p = traj.pose(5.0);
        let up = p.rotation * Vector3::z();
        let t = p.translation.vector;
        assert!(
            (up - Terrain::Rolling {
                amplitude: 1.0,
                wavelength: 40.0
            }
            .normal(t.x, t.y))
            .norm()
                < 1e-9
        );
    }
}
