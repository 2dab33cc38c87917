//! Incremental sufficient statistics of a point set, as UFO's `Surfel`
//! (docs/DESIGN.md#surfels): count, sum and scatter matrix, with exact add, remove and
//! merge, all in f64.

use std::ops::{Add, AddAssign, Sub, SubAssign};

use nalgebra::{Matrix3, Vector3};

use crate::eigen::{SortedEigen3, sorted_symmetric_eigen};

/// Sufficient statistics of a point set: `n`, `sum` and the scatter matrix
/// `S = Σ (p - mean)(p - mean)^T` stored as its upper triangle `[xx, xy, xz, yy, yz, zz]`.
/// Coordinates are in whatever frame the points are given (metres).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Surfel {
    n: u32,
    sum: Vector3<f64>,
    scatter: [f64; 6],
}

/// `S += d d^T * w` on the packed upper triangle.
fn add_outer(s: &mut [f64; 6], d: &Vector3<f64>, w: f64) {
    s[0] += d.x * d.x * w;
    s[1] += d.x * d.y * w;
    s[2] += d.x * d.z * w;
    s[3] += d.y * d.y * w;
    s[4] += d.y * d.z * w;
    s[5] += d.z * d.z * w;
}

fn add_packed(a: &[f64; 6], b: &[f64; 6], sign: f64) -> [f64; 6] {
    std::array::from_fn(|i| a[i] + sign * b[i])
}

impl Surfel {
    /// An empty surfel.
    pub fn new() -> Self {
        Self::default()
    }

    /// A surfel of one point.
    pub fn from_point(p: Vector3<f64>) -> Self {
        Self {
            n: 1,
            sum: p,
            scatter: [0.0; 6],
        }
    }

    /// A surfel of many points, computed in one pass (see [`Surfel::add_points`]).
    pub fn from_points<I: IntoIterator<Item = Vector3<f64>>>(points: I) -> Self {
        let mut s = Self::new();
        s.add_points(points);
        s
    }

    /// A surfel from raw statistics: count, sum (metres) and packed scatter matrix (m^2).
    pub fn from_raw(n: u32, sum: Vector3<f64>, scatter: [f64; 6]) -> Self {
        Self { n, sum, scatter }
    }

    /// Number of points.
    pub fn num_points(&self) -> u32 {
        self.n
    }

    /// Sum of the points (metres).
    pub fn sum(&self) -> Vector3<f64> {
        self.sum
    }

    /// Packed scatter matrix `[xx, xy, xz, yy, yz, zz]` (m^2).
    pub fn scatter(&self) -> [f64; 6] {
        self.scatter
    }

    /// True when the surfel holds no points.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Removes every point.
    pub fn clear(&mut self) {
        *self = Self::default();
    }

    /// Adds one point.
    pub fn add_point(&mut self, p: Vector3<f64>) {
        if self.n == 0 {
            *self = Self::from_point(p);
            return;
        }
        let n = self.n as f64;
        let d = p - self.sum / n;
        add_outer(&mut self.scatter, &d, n / (n + 1.0));
        self.sum += p;
        self.n += 1;
    }

    /// Adds many points: one pass of raw moments (taken about the first point, which
    /// keeps precision far from the origin), then a merge.
    pub fn add_points<I: IntoIterator<Item = Vector3<f64>>>(&mut self, points: I) {
        let mut iter = points.into_iter();
        let Some(origin) = iter.next() else { return };
        let mut n = 1u32;
        let mut shifted_sum = Vector3::zeros();
        let mut moments = [0.0f64; 6];
        for p in iter {
            let q = p - origin;
            shifted_sum += q;
            add_outer(&mut moments, &q, 1.0);
            n += 1;
        }
        // Centring correction S_ij = Σ q_i q_j - s_i s_j / n; S is shift-invariant.
        let mut correction = [0.0f64; 6];
        add_outer(&mut correction, &shifted_sum, 1.0 / n as f64);
        let batch = Self {
            n,
            sum: shifted_sum + origin * n as f64,
            scatter: add_packed(&moments, &correction, -1.0),
        };
        self.add_surfel(&batch);
    }

    /// Removes one point that was added before. Removing from a surfel of at most one
    /// point empties it.
    pub fn remove_point(&mut self, p: Vector3<f64>) {
        if self.n <= 1 {
            self.clear();
            return;
        }
        let n = self.n as f64;
        let n_after = n - 1.0;
        let sum_after = self.sum - p;
        let d = p - sum_after / n_after;
        add_outer(&mut self.scatter, &d, -n_after / n);
        self.sum = sum_after;
        self.n -= 1;
    }

    /// Removes many points that were added before.
    pub fn remove_points<I: IntoIterator<Item = Vector3<f64>>>(&mut self, points: I) {
        self.remove_surfel(&Self::from_points(points));
    }

    /// Merges `other` into `self`.
    pub fn add_surfel(&mut self, other: &Surfel) {
        if other.n == 0 {
            return;
        }
        if self.n == 0 {
            *self = *other;
            return;
        }
        // Products in f64: nA * nB overflows u32 beyond 65 536 points each.
        let (na, nb) = (self.n as f64, other.n as f64);
        let d = other.sum / nb - self.sum / na;
        let mut s = add_packed(&self.scatter, &other.scatter, 1.0);
        add_outer(&mut s, &d, na * nb / (na + nb));
        self.scatter = s;
        self.sum += other.sum;
        self.n += other.n;
    }

    /// Removes the points of `other`, which must have been merged in before. Removing
    /// as many points as `self` holds, or more, empties it.
    pub fn remove_surfel(&mut self, other: &Surfel) {
        if other.n == 0 {
            return;
        }
        if other.n >= self.n {
            self.clear();
            return;
        }
        let (na, nb) = (self.n as f64, other.n as f64);
        let n_after = na - nb;
        let sum_after = self.sum - other.sum;
        let d = other.sum / nb - sum_after / n_after;
        let mut s = add_packed(&self.scatter, &other.scatter, -1.0);
        add_outer(&mut s, &d, -n_after * nb / na);
        self.scatter = s;
        self.sum = sum_after;
        self.n -= other.n;
    }

    /// Mean of the points (metres); `None` when empty.
    pub fn mean(&self) -> Option<Vector3<f64>> {
        (self.n > 0).then(|| self.sum / self.n as f64)
    }

    /// Sample covariance `S / (n - 1)` (m^2); zero for fewer than two points.
    pub fn covariance(&self) -> Matrix3<f64> {
        if self.n < 2 {
            return Matrix3::zeros();
        }
        let [xx, xy, xz, yy, yz, zz] = self.scatter.map(|v| v / (self.n - 1) as f64);
        Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
    }

    /// Eigen-decomposition of the covariance, eigenvalues ascending.
    pub fn eigen(&self) -> SortedEigen3 {
        sorted_symmetric_eigen(&self.covariance())
    }

    /// Eigenvalues `e0 <= e1 <= e2` of the covariance (m^2).
    pub fn eigenvalues(&self) -> Vector3<f64> {
        self.eigen().values
    }

    /// Unit normal: the eigenvector of the smallest eigenvalue. `None` with fewer than
    /// three points, where no plane is defined.
    pub fn normal(&self) -> Option<Vector3<f64>> {
        (self.n >= 3).then(|| self.eigen().vectors.column(0).into_owned())
    }

    /// Planarity `2 (e1 - e0) / (e0 + e1 + e2)` in `[0, 1]`; `None` when the
    /// covariance is zero.
    pub fn planarity(&self) -> Option<f64> {
        let e = self.eigenvalues();
        let total = e.x + e.y + e.z;
        (total > 0.0).then(|| (2.0 * (e.y - e.x) / total).clamp(0.0, 1.0))
    }
}

impl AddAssign<&Surfel> for Surfel {
    fn add_assign(&mut self, rhs: &Surfel) {
        self.add_surfel(rhs);
    }
}

impl AddAssign for Surfel {
    fn add_assign(&mut self, rhs: Surfel) {
        self.add_surfel(&rhs);
    }
}

impl SubAssign<&Surfel> for Surfel {
    fn sub_assign(&mut self, rhs: &Surfel) {
        self.remove_surfel(rhs);
    }
}

impl SubAssign for Surfel {
    fn sub_assign(&mut self, rhs: Surfel) {
        self.remove_surfel(&rhs);
    }
}

impl Add for Surfel {
    type Output = Surfel;
    fn add(mut self, rhs: Surfel) -> Surfel {
        self += rhs;
        self
    }
}

impl Sub for Surfel {
    type Output = Surfel;
    fn sub(mut self, rhs: Surfel) -> Surfel {
        self -= rhs;
        self
    }
}

#[cfg(test)]
mod tests;
