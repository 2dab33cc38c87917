use super::*;
use proptest::prelude::*;

/// Oracle: two-pass statistics of a point list (mean first, then centred scatter).
fn batch_stats(points: &[Vector3<f64>]) -> (u32, Vector3<f64>, Matrix3<f64>) {
    let sum: Vector3<f64> = points.iter().sum();
    if points.is_empty() {
        return (0, sum, Matrix3::zeros());
    }
    let mean = sum / points.len() as f64;
    let scatter = points
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum();
    (points.len() as u32, sum, scatter)
}

fn packed_to_matrix(s: [f64; 6]) -> Matrix3<f64> {
    let [xx, xy, xz, yy, yz, zz] = s;
    Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
}

fn assert_agrees(surfel: &Surfel, points: &[Vector3<f64>], rel: f64) {
    let (n, sum, scatter) = batch_stats(points);
    assert_eq!(surfel.num_points(), n);
    let sum_scale = points.iter().map(|p| p.norm()).sum::<f64>().max(1.0);
    assert!(
        (surfel.sum() - sum).norm() <= rel * sum_scale,
        "sum differs"
    );
    let got = packed_to_matrix(surfel.scatter());
    // Floor of 1 m^2: a scatter that returns to zero keeps ~1e-13 of rounding.
    let scale = scatter.norm().max(1.0);
    assert!(
        (got - scatter).norm() <= rel * scale,
        "scatter differs: got {got}, want {scatter}"
    );
}

#[derive(Debug, Clone)]
enum Op {
    AddPoint([f64; 3]),
    RemovePoint(usize),
    MergeBatch(Vec<[f64; 3]>),
    RemoveBatch(usize),
}

fn point_strategy() -> impl Strategy<Value = [f64; 3]> {
    // Points up to ~10 m from a centre ~100 m away from the origin.
    prop::array::uniform3(-10.0f64..10.0).prop_map(|p| [p[0] + 100.0, p[1] - 80.0, p[2] + 60.0])
}

fn op_strategy() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => point_strategy().prop_map(Op::AddPoint),
        2 => any::<usize>().prop_map(Op::RemovePoint),
        1 => prop::collection::vec(point_strategy(), 1..40).prop_map(Op::MergeBatch),
        1 => any::<usize>().prop_map(Op::RemoveBatch),
    ]
}

proptest! {
    #[test]
    fn any_sequence_agrees_with_batch_statistics(ops in prop::collection::vec(op_strategy(), 1..120)) {
        let mut surfel = Surfel::new();
        let mut points: Vec<Vector3<f64>> = Vec::new();
        for op in ops {
            match op {
                Op::AddPoint(p) => {
                    surfel.add_point(p.into());
                    points.push(p.into());
                }
                Op::RemovePoint(i) if !points.is_empty() => {
                    let p = points.remove(i % points.len());
                    surfel.remove_point(p);
                }
                Op::MergeBatch(batch) => {
                    let batch: Vec<Vector3<f64>> = batch.into_iter().map(Into::into).collect();
                    surfel += Surfel::from_points(batch.iter().copied());
                    points.extend(batch);
                }
                Op::RemoveBatch(k) if !points.is_empty() => {
                    // Remove a tail of the current points as one surfel.
                    let take = 1 + k % points.len();
                    let removed = points.split_off(points.len() - take);
                    surfel -= Surfel::from_points(removed);
                }
                _ => {}
            }
            assert_agrees(&surfel, &points, 1e-6);
        }
    }

    #[test]
    fn removing_a_point_inverts_adding_it(
        base in prop::collection::vec(point_strategy(), 2..50),
        extra in point_strategy(),
    ) {
        let base: Vec<Vector3<f64>> = base.into_iter().map(Into::into).collect();
        let original = Surfel::from_points(base.iter().copied());
        let mut s = original;
        s.add_point(extra.into());
        s.remove_point(extra.into());
        prop_assert_eq!(s.num_points(), original.num_points());
        prop_assert!((s.sum() - original.sum()).norm() <= 1e-9 * original.sum().norm());
        let diff = packed_to_matrix(s.scatter()) - packed_to_matrix(original.scatter());
        prop_assert!(diff.norm() <= 1e-9 * packed_to_matrix(original.scatter()).norm().max(1e-9));
    }

    #[test]
    fn batch_add_equals_incremental_add(points in prop::collection::vec(point_strategy(), 1..80)) {
        let points: Vec<Vector3<f64>> = points.into_iter().map(Into::into).collect();
        let mut incremental = Surfel::new();
        for p in &points {
            incremental.add_point(*p);
        }
        assert_agrees(&incremental, &points, 1e-6);
        assert_agrees(&Surfel::from_points(points.iter().copied()), &points, 1e-6);
    }
}

fn grid_points(n: usize, offset: Vector3<f64>) -> Vec<Vector3<f64>> {
    (0..n)
        .map(|i| {
            let t = i as f64;
            offset
                + Vector3::new(
                    (t * 0.013).sin() * 5.0,
                    (t * 0.007).cos() * 3.0,
                    (t * 0.0031).sin(),
                )
        })
        .collect()
}

#[test]
fn merging_two_large_sets_does_not_overflow_the_count_product() {
    // 70 000 * 70 000 = 4.9e9 > u32::MAX: UFO once computed this product in u32.
    let a = grid_points(70_000, Vector3::new(0.0, 0.0, 0.0));
    let b = grid_points(70_000, Vector3::new(20.0, -5.0, 2.0));
    let merged = Surfel::from_points(a.iter().copied()) + Surfel::from_points(b.iter().copied());
    let all: Vec<_> = a.into_iter().chain(b).collect();
    assert_agrees(&merged, &all, 1e-9);
}

#[test]
fn removing_a_larger_surfel_clears() {
    let mut a = Surfel::from_points(grid_points(5, Vector3::zeros()));
    a -= Surfel::from_points(grid_points(7, Vector3::zeros()));
    assert!(a.is_empty());
    assert_eq!(a, Surfel::new());
}

#[test]
fn plane_has_normal_along_z_and_full_planarity() {
    // A square grid in the z = 2 plane: e0 = 0, e1 = e2, so planarity = 1.
    let points: Vec<_> = (0..11)
        .flat_map(|i| (0..11).map(move |j| Vector3::new(i as f64 * 0.1, j as f64 * 0.1, 2.0)))
        .collect();
    let s = Surfel::from_points(points.iter().copied());
    let normal = s.normal().unwrap();
    assert!((normal.z.abs() - 1.0).abs() < 1e-9);
    assert!((s.planarity().unwrap() - 1.0).abs() < 1e-9);
    let mean = s.mean().unwrap();
    assert!((mean - Vector3::new(0.5, 0.5, 2.0)).norm() < 1e-12);
    // Sample covariance along x: 11 x-values, each on 11 points, over n - 1 = 120.
    let xs: Vec<f64> = (0..11).map(|i| i as f64 * 0.1).collect();
    let mx = xs.iter().sum::<f64>() / 11.0;
    let expected = xs.iter().map(|x| (x - mx).powi(2)).sum::<f64>() * 11.0 / 120.0;
    assert!((s.covariance()[(0, 0)] - expected).abs() < 1e-12);
}

#[test]
fn empty_and_tiny_surfels_have_no_answers() {
    let empty = Surfel::new();
    assert!(empty.mean().is_none());
    assert!(empty.normal().is_none());
    assert!(empty.planarity().is_none());
    assert_eq!(empty.covariance(), Matrix3::zeros());
    let one = Surfel::from_point(Vector3::new(1.0, 2.0, 3.0));
    assert_eq!(one.covariance(), Matrix3::zeros());
    let mut s = one;
    s.remove_point(Vector3::new(1.0, 2.0, 3.0));
    assert!(s.is_empty());
}

#[test]
fn operators_match_methods() {
    let a = Surfel::from_points(grid_points(30, Vector3::zeros()));
    let b = Surfel::from_points(grid_points(12, Vector3::new(1.0, 1.0, 1.0)));
    let mut via_method = a;
    via_method.add_surfel(&b);
    assert_eq!(a + b, via_method);
    let back = (a + b) - b;
    assert_eq!(back.num_points(), a.num_points());
    let diff = packed_to_matrix(back.scatter()) - packed_to_matrix(a.scatter());
    assert!(diff.norm() < 1e-9 * packed_to_matrix(a.scatter()).norm());
}
