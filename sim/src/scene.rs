//! A simulated site: terrain plus walls, boxes, poles, trunks and tunnels, built from
//! triangles and cylinders and indexed by a [`Bvh`]. Map frame, z up, metres.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::bvh::Bvh;
use super::shapes::{Ray, Shape};

/// The ground surface `z = height(x, y)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum Terrain {
    /// Level ground at height `z`.
    Flat {
        /// Ground height, metres.
        z: f64,
    },
    /// A plane rising `gx` metres per metre along x and `gy` along y.
    Sloped {
        /// Slope along x (m/m).
        gx: f64,
        /// Slope along y (m/m).
        gy: f64,
    },
    /// Gentle hills: `amplitude * sin(2 pi x / wavelength) * cos(2 pi y / wavelength)`.
    Rolling {
        /// Peak height, metres.
        amplitude: f64,
        /// Hill spacing, metres.
        wavelength: f64,
    },
}

impl Terrain {
    /// Ground height at (x, y), metres.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        match *self {
            Terrain::Flat { z } => z,
            Terrain::Sloped { gx, gy } => gx * x + gy * y,
            Terrain::Rolling {
                amplitude,
                wavelength,
            } => {
                let k = std::f64::consts::TAU / wavelength;
                amplitude * (k * x).sin() * (k * y).cos()
            }
        }
    }

    /// Unit upward normal at (x, y).
    pub fn normal(&self, x: f64, y: f64) -> Vector3<f64> {
        let (dx, dy) = match *self {
            Terrain::Flat { .. } => (0.0, 0.0),
            Terrain::Sloped { gx, gy } => (gx, gy),
            Terrain::Rolling {
                amplitude,
                wavelength,
            } => {
                let k = std::f64::consts::TAU / wavelength;
                (
                    amplitude * k * (k * x).cos() * (k * y).cos(),
                    -amplitude * k * (k * x).sin() * (k * y).sin(),
                )
            }
        };
        Vector3::new(-dx, -dy, 1.0).normalize()
    }
}

/// Collects shapes; [`SceneBuilder::build`] indexes them.
#[derive(Debug, Clone)]
pub struct SceneBuilder {
    terrain: Terrain,
    shapes: Vec<Shape>,
}

/// A built scene: ray casting against everything in it.
#[derive(Debug, Clone)]
pub struct Scene {
    terrain: Terrain,
    bvh: Bvh,
}

impl Scene {
    /// The ground surface.
    pub fn terrain(&self) -> &Terrain {
        &self.terrain
    }

    /// Number of primitives.
    pub fn shape_count(&self) -> usize {
        self.bvh.len()
    }

    /// Distance to the nearest surface along `ray`, below `max_range`.
    pub fn cast(&self, ray: &Ray, max_range: f64) -> Option<f64> {
        self.bvh.cast(ray, max_range).map(|(t, _)| t)
    }

    /// The nearest hit and the shape hit, for tests.
    pub fn cast_shape(&self, ray: &Ray, max_range: f64) -> Option<(f64, &Shape)> {
        self.bvh.cast(ray, max_range)
    }
}

fn v(x: f64, y: f64, z: f64) -> Vector3<f64> {
    Vector3::new(x, y, z)
}

impl SceneBuilder {
    /// An empty site on `terrain`.
    pub fn new(terrain: Terrain) -> Self {
        Self {
            terrain,
            shapes: Vec::new(),
        }
    }

    /// Indexes the shapes.
    pub fn build(self) -> Scene {
        Scene {
            terrain: self.terrain,
            bvh: Bvh::new(self.shapes),
        }
    }

    /// Adds a quad `a b c d` (in order around its edge) as two triangles.
    pub fn add_quad(&mut self, a: Vector3<f64>, b: Vector3<f64>, c: Vector3<f64>, d: Vector3<f64>) {
        self.shapes.push(Shape::Triangle { a, b, c });
        self.shapes.push(Shape::Triangle { a, b: c, c: d });
    }

    /// Meshes the terrain over `[x0, x1] x [y0, y1]` with square cells of `cell` metres
    /// (one quad when the terrain is planar).
    pub fn add_ground(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, cell: f64) {
        let t = self.terrain;
        let at = |x: f64, y: f64| v(x, y, t.height(x, y));
        if !matches!(t, Terrain::Rolling { .. }) {
            self.add_quad(at(x0, y0), at(x1, y0), at(x1, y1), at(x0, y1));
            return;
        }
        let nx = ((x1 - x0) / cell).ceil().max(1.0) as usize;
        let ny = ((y1 - y0) / cell).ceil().max(1.0) as usize;
        let (dx, dy) = ((x1 - x0) / nx as f64, (y1 - y0) / ny as f64);
        for i in 0..nx {
            for j in 0..ny {
                let (xa, ya) = (x0 + i as f64 * dx, y0 + j as f64 * dy);
                self.add_quad(
                    at(xa, ya),
                    at(xa + dx, ya),
                    at(xa + dx, ya + dy),
                    at(xa, ya + dy),
                );
            }
        }
    }

    /// Adds a closed box with footprint centre (x, y), size `[lx, ly, lz]`, turned by
    /// `yaw` radians, standing on the terrain (its base sunk 0.5 m to leave no gap).
    pub fn add_box(&mut self, x: f64, y: f64, size: [f64; 3], yaw: f64) {
        let base = self.terrain.height(x, y) - 0.5;
        self.add_box_at(x, y, base, size[0], size[1], size[2] + 0.5, yaw);
    }

    #[allow(clippy::too_many_arguments)]
    fn add_box_at(&mut self, x: f64, y: f64, z0: f64, lx: f64, ly: f64, lz: f64, yaw: f64) {
        let (s, c) = yaw.sin_cos();
        let corner = |sx: f64, sy: f64, z: f64| {
            v(
                x + c * sx * lx / 2.0 - s * sy * ly / 2.0,
                y + s * sx * lx / 2.0 + c * sy * ly / 2.0,
                z,
            )
        };
        let z1 = z0 + lz;
        let bottom = [
            corner(-1.0, -1.0, z0),
            corner(1.0, -1.0, z0),
            corner(1.0, 1.0, z0),
            corner(-1.0, 1.0, z0),
        ];
        let top = [
            corner(-1.0, -1.0, z1),
            corner(1.0, -1.0, z1),
            corner(1.0, 1.0, z1),
            corner(-1.0, 1.0, z1),
        ];
        for k in 0..4 {
            let n = (k + 1) % 4;
            self.add_quad(bottom[k], bottom[n], top[n], top[k]);
        }
        self.add_quad(top[0], top[1], top[2], top[3]);
        self.add_quad(bottom[0], bottom[1], bottom[2], bottom[3]);
    }

    /// Adds a wall from `from` to `to` (x, y), `height` tall and `thickness` thick, with
    /// openings given as `(distance along the wall to its centre, width, height)`; an
    /// opening lower than the wall leaves a lintel above it (a door).
    pub fn add_wall(
        &mut self,
        from: [f64; 2],
        to: [f64; 2],
        height: f64,
        thickness: f64,
        openings: &[(f64, f64, f64)],
    ) {
        let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
        let length = dx.hypot(dy);
        if length <= 0.0 {
            return;
        }
        let yaw = dy.atan2(dx);
        let point = |along: f64| [from[0] + dx * along / length, from[1] + dy * along / length];
        let segment = |b: &mut Self, start: f64, end: f64, z_from: f64| {
            if end - start > 1e-6 {
                let mid = point((start + end) / 2.0);
                let base = b.terrain.height(mid[0], mid[1]);
                let z0 = if z_from > 0.0 {
                    base + z_from
                } else {
                    base - 0.5
                };
                b.add_box_at(
                    mid[0],
                    mid[1],
                    z0,
                    end - start,
                    thickness,
                    base + height - z0,
                    yaw,
                );
            }
        };
        let mut sorted: Vec<(f64, f64, f64)> = openings.to_vec();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut cursor = 0.0;
        for (centre, width, opening_height) in sorted {
            let (start, end) = (
                (centre - width / 2.0).max(cursor),
                (centre + width / 2.0).min(length),
            );
            segment(self, cursor, start, 0.0);
            if opening_height < height {
                segment(self, start, end, opening_height);
            }
            cursor = cursor.max(end);
        }
        segment(self, cursor, length, 0.0);
    }

    /// Adds a zero-thickness wall (a fence or a sign) visible from both sides.
    pub fn add_thin_wall(&mut self, from: [f64; 2], to: [f64; 2], height: f64) {
        let (h0, h1) = (
            self.terrain.height(from[0], from[1]),
            self.terrain.height(to[0], to[1]),
        );
        self.add_quad(
            v(from[0], from[1], h0 - 0.2),
            v(to[0], to[1], h1 - 0.2),
            v(to[0], to[1], h1 + height),
            v(from[0], from[1], h0 + height),
        );
    }

    /// Adds a vertical cylinder (pole, tree trunk) standing on the terrain.
    pub fn add_cylinder(&mut self, x: f64, y: f64, radius: f64, height: f64) {
        let base = self.terrain.height(x, y);
        self.shapes.push(Shape::Cylinder {
            centre: [x, y],
            radius,
            z0: base - 0.5,
            z1: base + height,
        });
    }

    /// Adds a straight tunnel along the segment `from -> to`: two side walls and a roof,
    /// `width` apart and `height` tall (inner surfaces), on flat ground.
    pub fn add_tunnel(&mut self, from: [f64; 2], to: [f64; 2], width: f64, height: f64) {
        let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
        let length = dx.hypot(dy);
        let (nx, ny) = (-dy / length * width / 2.0, dx / length * width / 2.0);
        let z0 = self.terrain.height(from[0], from[1]) - 0.2;
        let z1 = z0 + 0.2 + height;
        let p = |x: f64, y: f64, z: f64| v(x, y, z);
        for side in [-1.0, 1.0] {
            let (ox, oy) = (nx * side, ny * side);
            self.add_quad(
                p(from[0] + ox, from[1] + oy, z0),
                p(to[0] + ox, to[1] + oy, z0),
                p(to[0] + ox, to[1] + oy, z1),
                p(from[0] + ox, from[1] + oy, z1),
            );
        }
        self.add_quad(
            p(from[0] - nx, from[1] - ny, z1),
            p(to[0] - nx, to[1] - ny, z1),
            p(to[0] + nx, to[1] + ny, z1),
            p(from[0] + nx, from[1] + ny, z1),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terrain_normals_match_numerical_gradient() {
        let t = Terrain::Rolling {
            amplitude: 1.5,
            wavelength: 80.0,
        };
        for (x, y) in [(3.0, 7.0), (-20.0, 11.0), (55.5, -31.0)] {
            let h = 1e-5;
            let gx = (t.height(x + h, y) - t.height(x - h, y)) / (2.0 * h);
            let gy = (t.height(x, y + h) - t.height(x, y - h)) / (2.0 * h);
            let want = Vector3::new(-gx, -gy, 1.0).normalize();
            assert!((t.normal(x, y) - want).norm() < 1e-8);
        }
    }

    #[test]
    fn door_opening_lets_a_ray_through_and_lintel_stops_another() {
        let mut b = SceneBuilder::new(Terrain::Flat { z: 0.0 });
        b.add_wall([0.0, 5.0], [10.0, 5.0], 3.0, 0.3, &[(5.0, 1.0, 2.0)]);
        let scene = b.build();
        let through_door = Ray {
            origin: Vector3::new(5.0, 0.0, 1.0),
            dir: Vector3::y(),
        };
        assert_eq!(scene.cast(&through_door, 100.0), None);
        let lintel = Ray {
            origin: Vector3::new(5.0, 0.0, 2.5),
            dir: Vector3::y(),
        };
        assert!((scene.cast(&lintel, 100.0).unwrap() - 4.85).abs() < 1e-9);
        let wall = Ray {
            origin: Vector3::new(2.0, 0.0, 1.0),
            dir: Vector3::y(),
        };
        assert!((scene.cast(&wall, 100.0).unwrap() - 4.85).abs() < 1e-9);
    }

    #[test]
    fn thin_wall_is_seen_from_both_sides() {
        let mut b = SceneBuilder::new(Terrain::Flat { z: 0.0 });
        b.add_thin_wall([-5.0, 0.0], [5.0, 0.0], 2.0);
        let scene = b.build();
        for (y, dir) in [(-3.0, 1.0), (3.0, -1.0)] {
            let ray = Ray {
                origin: Vector3::new(0.0, y, 1.0),
                dir: Vector3::new(0.0, dir, 0.0),
            };
            assert!((scene.cast(&ray, 100.0).unwrap() - 3.0).abs() < 1e-12);
        }
    }
}
