//! Scene primitives and exact ray intersection: triangles (ground meshes, box faces,
//! walls) and vertical cylinders (poles, tree trunks), all in the map frame (metres).

use nalgebra::Vector3;

/// A ray `origin + t * dir`, `dir` of unit length, `t` in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Start point, map frame.
    pub origin: Vector3<f64>,
    /// Unit direction, map frame.
    pub dir: Vector3<f64>,
}

/// An axis-aligned box, map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// Minimum corner.
    pub min: Vector3<f64>,
    /// Maximum corner.
    pub max: Vector3<f64>,
}

impl Bounds {
    /// The empty box (grows from nothing).
    pub fn empty() -> Self {
        Self {
            min: Vector3::repeat(f64::INFINITY),
            max: Vector3::repeat(f64::NEG_INFINITY),
        }
    }

    /// Smallest box holding both.
    pub fn union(&self, other: &Bounds) -> Bounds {
        Bounds {
            min: self.min.inf(&other.min),
            max: self.max.sup(&other.max),
        }
    }

    /// Centre point.
    pub fn centre(&self) -> Vector3<f64> {
        (self.min + self.max) * 0.5
    }

    /// Entry distance of `ray` into the box if it enters before `t_max` (slab test).
    pub fn hit(&self, ray: &Ray, inv_dir: &Vector3<f64>, t_max: f64) -> Option<f64> {
        let mut t0 = 0.0f64;
        let mut t1 = t_max;
        for axis in 0..3 {
            let a = (self.min[axis] - ray.origin[axis]) * inv_dir[axis];
            let b = (self.max[axis] - ray.origin[axis]) * inv_dir[axis];
            let (near, far) = if a <= b { (a, b) } else { (b, a) };
            // NaN (0 * inf on a slab face) compares false and leaves the range as is.
            if near > t0 {
                t0 = near;
            }
            if far < t1 {
                t1 = far;
            }
            if t0 > t1 {
                return None;
            }
        }
        Some(t0)
    }
}

/// One scene primitive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A triangle with vertices `a`, `b`, `c`; both sides hit.
    Triangle {
        /// First vertex.
        a: Vector3<f64>,
        /// Second vertex.
        b: Vector3<f64>,
        /// Third vertex.
        c: Vector3<f64>,
    },
    /// A vertical cylinder (side and top cap) standing on `z0`, up to `z1`.
    Cylinder {
        /// Axis position (x, y).
        centre: [f64; 2],
        /// Radius, metres.
        radius: f64,
        /// Bottom height.
        z0: f64,
        /// Top height.
        z1: f64,
    },
}

impl Shape {
    /// Bounding box.
    pub fn bounds(&self) -> Bounds {
        match *self {
            Shape::Triangle { a, b, c } => Bounds {
                min: a.inf(&b).inf(&c),
                max: a.sup(&b).sup(&c),
            },
            Shape::Cylinder {
                centre,
                radius,
                z0,
                z1,
            } => Bounds {
                min: Vector3::new(centre[0] - radius, centre[1] - radius, z0),
                max: Vector3::new(centre[0] + radius, centre[1] + radius, z1),
            },
        }
    }

    /// Nearest hit distance in `(T_MIN, t_max)`, if any.
    pub fn hit(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        match *self {
            Shape::Triangle { a, b, c } => hit_triangle(ray, &a, &b, &c, t_max),
            Shape::Cylinder {
                centre,
                radius,
                z0,
                z1,
            } => hit_cylinder(ray, centre, radius, z0, z1, t_max),
        }
    }
}

/// Hits closer than this are ignored (a ray never hits its own start).
pub const T_MIN: f64 = 1e-6;

/// Möller-Trumbore intersection, double-sided.
fn hit_triangle(
    ray: &Ray,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
    t_max: f64,
) -> Option<f64> {
    let e1 = b - a;
    let e2 = c - a;
    let p = ray.dir.cross(&e2);
    let det = e1.dot(&p);
    if det.abs() < 1e-15 {
        return None; // Parallel to the triangle's plane.
    }
    let inv = 1.0 / det;
    let s = ray.origin - a;
    let u = s.dot(&p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(&e1);
    let v = ray.dir.dot(&q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(&q) * inv;
    (t > T_MIN && t < t_max).then_some(t)
}

fn hit_cylinder(
    ray: &Ray,
    centre: [f64; 2],
    radius: f64,
    z0: f64,
    z1: f64,
    t_max: f64,
) -> Option<f64> {
    let mut best: Option<f64> = None;
    let mut keep = |t: f64| {
        if t > T_MIN && t < t_max && best.is_none_or(|b| t < b) {
            best = Some(t);
        }
    };
    // Side: |o_xy + t d_xy - c|^2 = r^2.
    let (ox, oy) = (ray.origin.x - centre[0], ray.origin.y - centre[1]);
    let (dx, dy) = (ray.dir.x, ray.dir.y);
    let a = dx * dx + dy * dy;
    if a > 1e-18 {
        let b = ox * dx + oy * dy;
        let c = ox * ox + oy * oy - radius * radius;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let root = disc.sqrt();
            for t in [(-b - root) / a, (-b + root) / a] {
                let z = ray.origin.z + t * ray.dir.z;
                if (z0..=z1).contains(&z) {
                    keep(t);
                }
            }
        }
    }
    // Top cap: the disc of radius r at z1.
    if ray.dir.z.abs() > 1e-15 {
        let t = (z1 - ray.origin.z) / ray.dir.z;
        let (x, y) = (ox + t * dx, oy + t * dy);
        if x * x + y * y <= radius * radius {
            keep(t);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(o: [f64; 3], d: [f64; 3]) -> Ray {
        Ray {
            origin: Vector3::from(o),
            dir: Vector3::from(d).normalize(),
        }
    }

    #[test]
    fn triangle_hit_is_exact_and_double_sided() {
        let tri = Shape::Triangle {
            a: Vector3::new(5.0, -10.0, -10.0),
            b: Vector3::new(5.0, 10.0, -10.0),
            c: Vector3::new(5.0, 0.0, 10.0),
        };
        assert_eq!(tri.hit(&ray([0.0; 3], [1.0, 0.0, 0.0]), 100.0), Some(5.0));
        assert_eq!(
            tri.hit(&ray([9.0, 0.0, 0.0], [-1.0, 0.0, 0.0]), 100.0),
            Some(4.0)
        );
        assert_eq!(tri.hit(&ray([0.0; 3], [1.0, 0.0, 0.0]), 4.0), None);
        assert_eq!(tri.hit(&ray([0.0; 3], [-1.0, 0.0, 0.0]), 100.0), None);
        assert_eq!(
            tri.hit(&ray([0.0, 0.0, 10.5], [1.0, 0.0, 0.0]), 100.0),
            None
        );
        assert_eq!(tri.hit(&ray([0.0, 0.2, 9.9], [1.0, 0.0, 0.0]), 100.0), None);
    }

    #[test]
    fn cylinder_side_and_cap() {
        let cyl = Shape::Cylinder {
            centre: [10.0, 0.0],
            radius: 0.5,
            z0: 0.0,
            z1: 3.0,
        };
        assert!(
            (cyl.hit(&ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]), 100.0)
                .unwrap()
                - 9.5)
                .abs()
                < 1e-12
        );
        assert!(
            (cyl.hit(&ray([10.0, 0.0, 10.0], [0.0, 0.0, -1.0]), 100.0)
                .unwrap()
                - 7.0)
                .abs()
                < 1e-12
        );
        assert_eq!(cyl.hit(&ray([0.0, 0.0, 5.0], [1.0, 0.0, 0.0]), 100.0), None);
        assert_eq!(cyl.hit(&ray([0.0, 2.0, 1.0], [1.0, 0.0, 0.0]), 100.0), None);
    }

    #[test]
    fn bounds_slab_test() {
        let b = Bounds {
            min: Vector3::new(1.0, -1.0, -1.0),
            max: Vector3::new(2.0, 1.0, 1.0),
        };
        let r = ray([0.0; 3], [1.0, 0.0, 0.0]);
        let inv = r.dir.map(|d| 1.0 / d);
        assert_eq!(b.hit(&r, &inv, 100.0), Some(1.0));
        assert_eq!(b.hit(&r, &inv, 0.5), None);
        let r = ray([0.0, 5.0, 0.0], [1.0, 0.0, 0.0]);
        assert_eq!(b.hit(&r, &r.dir.map(|d| 1.0 / d), 100.0), None);
    }
}
