use super::oracle::brute_force;
use super::*;
use crate::geometry::unpack_sym3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn random_cloud(seed: u64, n: usize) -> Vec<[f32; 3]> {
    // Mixture of noisy planes and clutter, the shapes a LiDAR scan holds.
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let (u, v): (f32, f32) = (rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0));
            let noise: f32 = rng.random_range(-0.02..0.02);
            match i % 3 {
                0 => [u, v, noise],
                1 => [u, 3.0 + noise, v],
                _ => [u, v, rng.random_range(-4.0..4.0)],
            }
        })
        .collect()
}

fn assert_matches_brute_force(points: &[[f32; 3]], options: &CovOptions) {
    let got = estimate_covariances(points, options);
    let want = brute_force(points, options);
    assert_eq!(got.values.len(), want.len());
    for (i, (g, w)) in got.values.iter().zip(&want).enumerate() {
        for j in 0..6 {
            assert!(
                (g[j] - w[j]).abs() <= 1e-5,
                "point {i} entry {j}: got {g:?}, want {w:?}"
            );
        }
    }
}

#[test]
fn matches_brute_force_with_default_options() {
    assert_matches_brute_force(&random_cloud(1, 3000), &CovOptions::default());
}

#[test]
fn matches_brute_force_with_query_centre_and_eigenvalue_floor() {
    let options = CovOptions {
        cov_center: CovCenter::Query,
        lambda: -0.01,
        k_correspondences_for_cov: 12,
        min_correspondences_for_cov: 4,
        max_distance_for_cov: 0.7,
        ..CovOptions::default()
    };
    assert_matches_brute_force(&random_cloud(2, 3000), &options);
}

#[test]
fn matches_brute_force_with_plane_deviation_gate() {
    let options = CovOptions {
        max_plane_deviation_for_cov: 0.05,
        ..CovOptions::default()
    };
    let tree_points = random_cloud(3, 3000);
    assert_matches_brute_force(&tree_points, &options);
    // The clutter third of the cloud must actually trip the gate.
    assert!(estimate_covariances(&tree_points, &options).fallback_count > 100);
}

#[test]
fn regularized_plane_has_eigenvalues_one_one_lambda() {
    // A tilted planar grid: every covariance is exactly U diag(lambda, 1, 1) U^T with the
    // plane normal as the lambda eigenvector.
    let normal = Vector3::new(0.3, -0.2, 1.0).normalize();
    let u = normal.cross(&Vector3::x()).normalize();
    let v = normal.cross(&u);
    let points: Vec<[f32; 3]> = (0..40)
        .flat_map(|i| (0..40).map(move |j| (i, j)))
        .map(|(i, j)| {
            let p = u * (i as f64 * 0.1) + v * (j as f64 * 0.1);
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect();
    let options = CovOptions::default();
    let covs = estimate_covariances(&points, &options);
    assert_eq!(covs.fallback_count, 0);
    for c in &covs.values {
        let m = unpack_sym3(c);
        let e = sorted_symmetric_eigen(&m);
        assert!((e.values.x - options.lambda).abs() < 1e-5, "{:?}", e.values);
        assert!((e.values.y - 1.0).abs() < 1e-5 && (e.values.z - 1.0).abs() < 1e-5);
        assert!(e.vectors.column(0).dot(&normal).abs() > 1.0 - 1e-4);
    }
}

#[test]
fn eigenvalue_floor_lifts_a_line_neighbourhood() {
    // Points on a line: two zero eigenvalues, floored at |lambda| * s_max.
    let points: Vec<[f32; 3]> = (0..30).map(|i| [i as f32 * 0.05, 0.0, 0.0]).collect();
    let options = CovOptions {
        lambda: -0.1,
        ..CovOptions::default()
    };
    let covs = estimate_covariances(&points, &options);
    for c in &covs.values {
        let e = sorted_symmetric_eigen(&unpack_sym3(c)).values;
        assert!(e.x > 0.0);
        assert!((e.x - 0.1 * e.z).abs() < 1e-6 && (e.y - 0.1 * e.z).abs() < 1e-6);
    }
}

#[test]
fn isotropic_fallback_when_too_few_neighbours_or_points() {
    let options = CovOptions::default();
    // N < 3: identity, never zeros (MOLA wrote zeros here).
    for n in 1..3 {
        let points: Vec<[f32; 3]> = (0..n).map(|i| [i as f32 * 0.1, 0.0, 0.0]).collect();
        let covs = estimate_covariances(&points, &options);
        assert!(covs.values.iter().all(|c| *c == ISOTROPIC));
    }
    // Isolated points (2 m apart, r = 1 m): only the point itself is a neighbour.
    let sparse: Vec<[f32; 3]> = (0..20).map(|i| [i as f32 * 2.0, 0.0, 0.0]).collect();
    let covs = estimate_covariances(&sparse, &options);
    assert_eq!(covs.fallback_count, 20);
    assert!(covs.values.iter().all(|c| *c == ISOTROPIC));
    // All neighbours identical: zero scatter, fallback rather than a singular matrix.
    let same = vec![[1.0f32, 2.0, 3.0]; 10];
    assert!(
        estimate_covariances(&same, &options)
            .values
            .iter()
            .all(|c| *c == ISOTROPIC)
    );
}

#[test]
fn output_does_not_depend_on_thread_count() {
    let points = random_cloud(4, 5000);
    let options = CovOptions::default();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let serial = one.install(|| estimate_covariances(&points, &options));
    let parallel = estimate_covariances(&points, &options);
    assert_eq!(serial, parallel);
}

#[test]
fn validation_names_the_bad_option() {
    let bad_min = CovOptions {
        min_correspondences_for_cov: 30,
        ..CovOptions::default()
    };
    assert_eq!(
        bad_min.validate().unwrap_err().option,
        "min-correspondences-for-cov"
    );
    let bad_r = CovOptions {
        max_distance_for_cov: -1.0,
        ..CovOptions::default()
    };
    assert_eq!(bad_r.validate().unwrap_err().option, "max-distance-for-cov");
    let bad_lambda = CovOptions {
        lambda: 0.0,
        ..CovOptions::default()
    };
    assert_eq!(bad_lambda.validate().unwrap_err().option, "lambda");
    assert!(CovOptions::default().validate().is_ok());
}
