use nalgebra::{Matrix3, Matrix6, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::geometry::{Pose, rotation_distance, translation_distance};
use crate::registration::{
    Constraint, Correspondence, Fitness, RegistrationParams, RegistrationResult, RobustKernel,
    linearize, solve_pose,
};
use crate::tracking::health::{COVARIANCE_INFLATION, ROTATION_FLOOR_RAD2};

/// Point-to-point correspondences: `source` points and targets `source + noise`.
fn problem(rng: &mut StdRng, n: usize, sigma: f64) -> (Vec<Vector3<f64>>, Vec<Correspondence>) {
    let mut source: Vec<Vector3<f64>> = (0..n)
        .map(|_| {
            Vector3::new(
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect();
    // Centred, so the closed form below has no rotation-translation coupling.
    let mean = source.iter().sum::<Vector3<f64>>() / n as f64;
    source.iter_mut().for_each(|s| *s -= mean);
    let pairs = source
        .iter()
        .map(|s| Correspondence {
            source: *s,
            target: s + gaussian3(rng) * sigma,
            information: Matrix3::identity(),
        })
        .collect();
    (source, pairs)
}

fn gaussian3(rng: &mut StdRng) -> Vector3<f64> {
    // Box-Muller.
    let mut g = || {
        let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    Vector3::new(g(), g(), g())
}

fn result_at_identity(pairs: &[Correspondence]) -> RegistrationResult {
    let lin = linearize(pairs, &Pose::identity(), &RobustKernel::None);
    RegistrationResult {
        pose: Pose::identity(),
        hessian: lin.hessian,
        fitness: Fitness {
            inlier_ratio: 1.0,
            rmse: 0.0,
        },
        iterations: 1,
        converged: true,
        constraint: Constraint::of(&lin.hessian),
        unobservable: 0,
        degenerate: false,
        cost: lin.cost,
        pairs: pairs.len(),
        gradient_scatter: None,
    }
}

/// The registration of fixed `pairs` (the same at every pose) from the identity.
fn solved_from_identity(
    pairs: &[Correspondence],
    params: &RegistrationParams,
) -> RegistrationResult {
    solve_pose(&Pose::identity(), params, pairs.len(), |_| {
        Ok::<_, crate::registration::RegistrationError>(pairs.to_vec())
    })
    .unwrap()
}

/// The unbiased sample covariance of `draws`.
fn sample_covariance(draws: &[nalgebra::Vector6<f64>]) -> Matrix6<f64> {
    let mean = draws.iter().sum::<nalgebra::Vector6<f64>>() / draws.len() as f64;
    draws
        .iter()
        .map(|x| (x - mean) * (x - mean).transpose())
        .sum::<Matrix6<f64>>()
        / (draws.len() - 1) as f64
}

/// Point-to-point with unit information on a centred cloud: `H = diag(sum |s|^2 I - s
/// s^T, n I)` and `sigma^2 = sum |r|^2 / (3n - 6)`, so the covariance is `sigma^2 (sum
/// |s|^2 I - s s^T)^-1` for rotation, `sigma^2 / n I` for translation, zero between.
#[test]
fn covariance_equals_the_closed_form_of_point_to_point() {
    let mut rng = StdRng::seed_from_u64(1);
    let (source, pairs) = problem(&mut rng, 400, 0.05);
    let covariance = registration_covariance(&result_at_identity(&pairs)).unwrap();
    let n = pairs.len() as f64;
    let sigma2 = pairs
        .iter()
        .map(|c| (c.target - c.source).norm_squared())
        .sum::<f64>()
        / (3.0 * n - 6.0);
    let rotation_information: Matrix3<f64> = source
        .iter()
        .map(|s| Matrix3::identity() * s.norm_squared() - s * s.transpose())
        .sum();
    let mut expected = Matrix6::zeros();
    expected
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(rotation_information.try_inverse().unwrap() * sigma2));
    expected
        .fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(Matrix3::identity() * sigma2 / n));
    let gap = (covariance - expected).abs().max();
    assert!(
        gap < 1e-9 * expected.abs().max(),
        "{covariance}\n{expected}"
    );
}

/// The covariance predicts how the solved pose scatters under noise: over many noise
/// draws, the spread of the solution equals the covariance of one solve.
#[test]
fn covariance_predicts_the_scatter_of_the_solution() {
    let mut rng = StdRng::seed_from_u64(2);
    let sigma = 0.03;
    let draws = 300;
    let mut solutions = Vec::with_capacity(draws);
    let mut predicted = Matrix6::zeros();
    for _ in 0..draws {
        let (_, pairs) = problem(&mut rng, 200, sigma);
        let params = RegistrationParams {
            max_iterations: 10,
            ..RegistrationParams::default()
        };
        let result = solved_from_identity(&pairs, &params);
        predicted += registration_covariance(&result).unwrap() / draws as f64;
        solutions.push(crate::se3::log(&result.pose));
    }
    let empirical = sample_covariance(&solutions);
    for i in 0..6 {
        let ratio = empirical[(i, i)] / predicted[(i, i)];
        // 300 draws: the variance estimate is within about +-16 % (2 sigma).
        assert!((0.75..1.33).contains(&ratio), "axis {i}: {ratio}");
    }
}

/// Point-to-plane pairs on a box room (floor, ceiling, four walls) cut into 2 m panels,
/// the source at the identity: each panel's target is offset along its normal by one
/// draw shared by all its pairs (a wall mapped a little off), plus small noise per pair.
fn panel_problem(rng: &mut StdRng, shared: f64, own: f64) -> Vec<Correspondence> {
    let mut pairs = Vec::new();
    // (normal, the two in-plane axes, the plane's offset from the origin)
    let faces = [
        (Vector3::z(), Vector3::x(), Vector3::y(), -1.5),
        (Vector3::z(), Vector3::x(), Vector3::y(), 2.5),
        (Vector3::x(), Vector3::y(), Vector3::z(), -6.0),
        (Vector3::x(), Vector3::y(), Vector3::z(), 5.0),
        (Vector3::y(), Vector3::x(), Vector3::z(), -4.0),
        (Vector3::y(), Vector3::x(), Vector3::z(), 7.0),
    ];
    for (normal, a, b, offset) in faces {
        for pa in -3..3 {
            for pb in -1..1 {
                let shift = shared * gaussian3(rng).x;
                for _ in 0..12 {
                    let (u, v): (f64, f64) = (rng.random(), rng.random());
                    let source =
                        normal * offset + a * (2.0 * (pa as f64 + u)) + b * (2.0 * (pb as f64 + v));
                    let noise = own * gaussian3(rng).x;
                    pairs.push(Correspondence {
                        source,
                        target: source + normal * (shift + noise),
                        information: normal * normal.transpose() + Matrix3::identity() * 1e-3,
                    });
                }
            }
        }
    }
    pairs
}

/// When whole surfaces err together, the solution scatters far more than `sigma^2 H^-1`
/// (independent pairs) says; the cluster-robust sandwich over cubes of about a panel's
/// size predicts it. Oracle: the scatter of the solved pose over many draws.
#[test]
fn the_sandwich_predicts_the_scatter_when_surfaces_err_together() {
    let mut rng = StdRng::seed_from_u64(4);
    let draws = 300;
    let params = RegistrationParams {
        max_iterations: 10,
        gradient_cluster_m: Some(2.0),
        ..RegistrationParams::default()
    };
    let mut solutions = Vec::with_capacity(draws);
    let (mut sandwich, mut independent) = (Matrix6::zeros(), Matrix6::zeros());
    for _ in 0..draws {
        let pairs = panel_problem(&mut rng, 0.01, 0.002);
        let result = solved_from_identity(&pairs, &params);
        let both = registration_covariance(&result).unwrap();
        let alone = registration_covariance(&RegistrationResult {
            gradient_scatter: None,
            ..result
        })
        .unwrap();
        sandwich += (both - alone) / draws as f64;
        independent += alone / draws as f64;
        solutions.push(crate::se3::log(&result.pose));
    }
    let empirical = sample_covariance(&solutions);
    for i in 0..6 {
        let ratio = empirical[(i, i)] / sandwich[(i, i)];
        let under = empirical[(i, i)] / independent[(i, i)];
        println!("axis {i}: empirical / sandwich {ratio:.2}, / independent {under:.1}");
        // 72 panels, 300 draws: within about +-16 % (2 sigma); measured 0.92-1.11.
        assert!((0.75..1.33).contains(&ratio), "axis {i}: {ratio}");
        // Measured 25-39x: independent pairs alone would be badly overconfident.
        assert!(
            under > 10.0,
            "axis {i}: independent pairs only {under}x under"
        );
    }
}

/// The rotation floor lies about the map's horizontal axes, none about its vertical,
/// whatever way the sensor is turned: worked out by hand for a level sensor (the floor
/// on its roll and pitch) and for one pitched 90 deg (the map's up along its -x axis:
/// the floor on its y and z axes).
#[test]
fn the_rotation_floor_lies_about_the_maps_horizontal_axes() {
    let mut rng = StdRng::seed_from_u64(11);
    let (_, pairs) = problem(&mut rng, 200, 0.01);
    let mut result = result_at_identity(&pairs);
    let floor_of = |result: &RegistrationResult| -> Matrix3<f64> {
        let added = pose_covariance(result).unwrap()
            - registration_covariance(result).unwrap() * COVARIANCE_INFLATION;
        // Only the rotation block gains.
        assert!(added.fixed_view::<3, 3>(3, 3).abs().max() < 1e-18);
        assert!(added.fixed_view::<3, 3>(0, 3).abs().max() < 1e-18);
        added.fixed_view::<3, 3>(0, 0).into_owned() / ROTATION_FLOOR_RAD2
    };
    let level = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0));
    assert!(
        (floor_of(&result) - level).abs().max() < 1e-9,
        "{}",
        floor_of(&result)
    );
    result.pose = Pose::from_parts(
        nalgebra::Translation3::new(3.0, -2.0, 1.0),
        nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
    );
    let pitched = Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 1.0));
    assert!(
        (floor_of(&result) - pitched).abs().max() < 1e-9,
        "{}",
        floor_of(&result)
    );
}

#[test]
fn a_singular_hessian_has_no_covariance() {
    let pairs = vec![Correspondence {
        source: Vector3::new(1.0, 0.0, 0.0),
        target: Vector3::new(1.0, 0.0, 0.0),
        information: Matrix3::identity(),
    }];
    assert!(pose_covariance(&result_at_identity(&pairs)).is_none());
    let mut rng = StdRng::seed_from_u64(3);
    let (_, mut pairs) = problem(&mut rng, 50, 0.0);
    // All on one line: rotation about it is unconstrained.
    for (i, c) in pairs.iter_mut().enumerate() {
        c.source = Vector3::new(i as f64, 0.0, 0.0);
        c.target = c.source;
    }
    let result = result_at_identity(&pairs);
    assert!(pose_covariance(&result).is_none());
    assert_eq!(result.constraint.rotation_ratio, 0.0);
}

#[test]
fn status_and_reasons_have_stable_codes_and_names() {
    for s in TrackingStatus::ALL {
        assert_eq!(TrackingStatus::from_code(s as u32), Some(s));
    }
    assert_eq!(TrackingStatus::from_code(7), None);
    assert_eq!(
        (Reasons::DEGENERATE | Reasons::RETRIED | Reasons(1 << 31)).names(),
        ["degenerate", "retried"]
    );
    assert_eq!(TrackingStatus::Degraded.name(), "degraded");
}

// The ladder's decisions, on a scripted registration: a yaw-only world where starts
// within `basin` degrees of the true yaw converge to the truth with a good fit, and
// others to a wrong minimum near their start with a poor one.

/// A scripted scene.
struct World {
    truth: Pose,
    basin_deg: f64,
    good_fit: f64,
    wrong_fit: f64,
    /// Where starts outside the basin end: the start moved by this.
    wrong_offset: Pose,
    calls: Vec<(Pose, Stage)>,
}

impl World {
    fn new(truth: Pose) -> Self {
        Self {
            truth,
            basin_deg: 20.0,
            good_fit: 0.9,
            wrong_fit: 0.6,
            wrong_offset: Pose::translation(0.4, 0.0, 0.0),
            calls: Vec::new(),
        }
    }

    fn register(&mut self, start: &Pose, stage: &Stage) -> Option<RegistrationResult> {
        self.calls.push((*start, *stage));
        let near = rotation_distance(start, &self.truth).to_degrees() < self.basin_deg
            && translation_distance(start, &self.truth) < 2.0;
        let (pose, fit) = match (stage.max_iterations, near) {
            // One linearization scores the start itself.
            (1, true) => (*start, self.good_fit - 0.1),
            (1, false) => (*start, self.wrong_fit - 0.1),
            (_, true) => (self.truth, self.good_fit),
            (_, false) => (start * self.wrong_offset, self.wrong_fit),
        };
        let mut result = result_at_identity(&problem(&mut StdRng::seed_from_u64(9), 60, 0.01).1);
        result.pose = pose;
        result.fitness.inlier_ratio = fit;
        Some(result)
    }
}

fn run(world: &mut World, prediction: &Pose, expected: Expectation) -> Localization {
    let fine = Stage {
        coarse: false,
        max_pair_dist: 1.0,
        max_iterations: 30,
    };
    localize_scan(
        prediction,
        &expected,
        fine,
        &TrackingParams::default(),
        |start, stage| Ok::<_, ()>(world.register(start, stage)),
    )
    .unwrap()
}

fn yaw(deg: f64) -> Pose {
    Pose::new(Vector3::zeros(), Vector3::new(0.0, 0.0, deg.to_radians()))
}

#[test]
fn a_prediction_in_the_basin_is_ok_after_one_coarse_and_one_fine_registration() {
    let mut world = World::new(yaw(10.0));
    let expected = Expectation {
        max_correction: Some(3.0),
        inlier_ratio: Some(0.9),
    };
    let found = run(&mut world, &yaw(0.0), expected);
    assert_eq!(found.health.status, TrackingStatus::Ok);
    assert_eq!(found.pose, world.truth);
    assert_eq!(found.health.registrations, 2);
    assert!(world.calls[0].1.coarse && !world.calls[1].1.coarse);
    // 10 degrees at 10 m: a chord of 1.74 m.
    assert!((found.health.correction - 20.0 * 5f64.to_radians().sin()).abs() < 1e-9);
    assert!(found.health.covariance.is_some());
}

#[test]
fn a_fitness_drop_sends_the_scan_up_the_ladder_to_a_yaw_hypothesis() {
    // 35 degrees off: outside the basin; the 30 degree hypothesis is inside.
    let mut world = World::new(yaw(35.0));
    let expected = Expectation {
        max_correction: Some(8.0),
        inlier_ratio: Some(0.9),
    };
    let found = run(&mut world, &yaw(0.0), expected);
    assert_eq!(found.pose, world.truth);
    assert_eq!(found.health.status, TrackingStatus::Ok);
    assert!(found.health.reasons.contains(Reasons::RETRIED));
    // Coarse + fine, six yaw scores, coarse + fine from the best.
    assert_eq!(found.health.registrations, 10);
    let scored: Vec<f64> = world
        .calls
        .iter()
        .filter(|(_, s)| s.max_iterations == 1)
        .map(|(p, _)| p.rotation.euler_angles().2.to_degrees().round())
        .collect();
    assert_eq!(scored, [15.0, -15.0, 30.0, -30.0, 45.0, -45.0]);
}

#[test]
fn a_correction_beyond_the_bound_is_lost_without_an_expectation_to_confirm_it() {
    let mut world = World::new(yaw(35.0));
    // The wrong minimum is beyond the bound too, so the ladder runs.
    world.wrong_offset = Pose::translation(3.0, 0.0, 0.0);
    let bound = Expectation {
        max_correction: Some(2.0),
        inlier_ratio: None,
    };
    let found = run(&mut world, &yaw(0.0), bound);
    assert_eq!(found.health.status, TrackingStatus::Lost);
    assert_eq!(found.pose, yaw(0.0), "a lost scan reports the prediction");
    assert!(found.health.reasons.contains(Reasons::IMPLAUSIBLE));
    // The same correction, confirmed by a fit as good as the scans before: degraded.
    let mut world = World::new(yaw(35.0));
    world.wrong_offset = Pose::translation(3.0, 0.0, 0.0);
    let confirmed = Expectation {
        max_correction: Some(2.0),
        inlier_ratio: Some(0.9),
    };
    let found = run(&mut world, &yaw(0.0), confirmed);
    assert_eq!(found.health.status, TrackingStatus::Degraded);
    assert_eq!(found.pose, world.truth);
    assert!(found.health.reasons.contains(Reasons::IMPLAUSIBLE));
}

#[test]
fn a_scan_that_fits_nowhere_as_well_as_expected_is_lost() {
    // The truth is 90 degrees away: beyond every hypothesis.
    let mut world = World::new(yaw(90.0));
    let expected = Expectation {
        max_correction: Some(10.0),
        inlier_ratio: Some(0.9),
    };
    let found = run(&mut world, &yaw(0.0), expected);
    assert_eq!(found.health.status, TrackingStatus::Lost);
    assert!(found.health.reasons.contains(Reasons::FITNESS_DROP));
    assert_eq!(found.pose, yaw(0.0));
    // Without an expectation only the absolute levels apply: a fit below the lost
    // level is lost.
    let mut world = World::new(yaw(90.0));
    world.wrong_fit = 0.2;
    let found = run(&mut world, &yaw(0.0), Expectation::default());
    assert_eq!(found.health.status, TrackingStatus::Lost);
    assert!(found.health.reasons.contains(Reasons::NO_FIT));
}

#[test]
fn two_distinct_poses_fitting_alike_are_ambiguous() {
    // The truth is 10 degrees off (a plausible correction) but outside a narrow basin;
    // from the prediction, registration ends in a wrong minimum beyond the bound that
    // fits as well as the truth (a symmetric room).
    let mut world = World::new(yaw(10.0));
    world.basin_deg = 6.0;
    world.wrong_fit = 0.89;
    world.wrong_offset = Pose::translation(3.0, 0.0, 0.0);
    let expected = Expectation {
        max_correction: Some(2.5),
        inlier_ratio: Some(0.9),
    };
    let found = run(&mut world, &yaw(0.0), expected);
    assert_eq!(found.health.status, TrackingStatus::Lost);
    assert!(found.health.reasons.contains(Reasons::AMBIGUOUS));
}

#[test]
fn no_correspondences_anywhere_is_lost_with_no_fit() {
    let found = localize_scan(
        &Pose::identity(),
        &Expectation::default(),
        Stage {
            coarse: false,
            max_pair_dist: 1.0,
            max_iterations: 10,
        },
        &TrackingParams::default(),
        |_, _| Ok::<_, ()>(None),
    )
    .unwrap();
    assert_eq!(found.health.status, TrackingStatus::Lost);
    assert_eq!(found.health.reasons, Reasons::NO_FIT);
    assert!(found.health.covariance.is_none());
}

#[test]
fn shipped_tracking_parameters_are_valid_and_checked() {
    TrackingParams::default().validate().unwrap();
    let bad = TrackingParams {
        lost_inlier_ratio: 0.9,
        ..TrackingParams::default()
    };
    let e = bad.validate().unwrap_err();
    assert_eq!(e.option, "lost-inlier-ratio");
}

/// A preparation resumed from another one's parts equals a fresh one on the same scan
/// and options, and drops parts built for other points or another coarse voxel.
#[test]
fn a_resumed_preparation_equals_a_fresh_one_and_drops_a_foreign_scans_parts() {
    let mut rng = StdRng::seed_from_u64(5);
    let scan: Vec<[f32; 3]> = (0..3000)
        .map(|_| {
            [
                rng.random_range(-20.0..20.0),
                rng.random_range(-20.0..20.0),
                rng.random_range(-2.0..2.0),
            ]
        })
        .collect();
    let other: Vec<[f32; 3]> = scan.iter().map(|p| [p[0] + 0.5, p[1], p[2]]).collect();
    let options = crate::cov::CovOptions::default();
    let tracking = TrackingParams::default();
    let built = |points: &[[f32; 3]], tracking: TrackingParams| {
        let mut fresh = PreparedScan::new(points, None, None, options, tracking);
        let fine = fresh.fine().1.to_vec();
        let (cloud, covs) = fresh.coarse().unwrap();
        let coarse = (cloud.points.clone(), covs.to_vec());
        (fine, coarse, fresh.into_parts())
    };
    let (fine, coarse, parts) = built(&scan, tracking);
    let mut resumed = PreparedScan::resume(&scan, None, None, options, tracking, parts.clone());
    assert_eq!(resumed.fine().1, fine.as_slice());
    let (cloud, covs) = resumed.coarse().unwrap();
    assert_eq!((&cloud.points, covs), (&coarse.0, coarse.1.as_slice()));
    // Parts of a preparation that built only the coarse copy: the fine covariances are
    // estimated on first use, as fresh.
    let mut coarse_only = PreparedScan::new(&scan, None, None, options, tracking);
    coarse_only.coarse().unwrap();
    let mut resumed = PreparedScan::resume(
        &scan,
        None,
        None,
        options,
        tracking,
        coarse_only.into_parts(),
    );
    assert_eq!(resumed.coarse().unwrap().1, coarse.1.as_slice());
    assert_eq!(resumed.fine().1, fine.as_slice());
    // The parts of this scan offered for another scan, or with another coarse voxel,
    // are dropped: each gives what a fresh preparation gives.
    let (other_fine, _, _) = built(&other, tracking);
    let mut foreign = PreparedScan::resume(&other, None, None, options, tracking, parts.clone());
    assert_eq!(foreign.fine().1, other_fine.as_slice());
    let wider = TrackingParams {
        coarse_voxel: 2.0,
        ..tracking
    };
    let (_, wider_coarse, _) = built(&scan, wider);
    let mut revoxelled = PreparedScan::resume(&scan, None, None, options, wider, parts);
    assert_eq!(revoxelled.coarse().unwrap().0.points, wider_coarse.0);
    assert_ne!(wider_coarse.0.len(), coarse.0.len());
}
