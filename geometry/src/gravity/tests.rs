use std::collections::BTreeMap;

use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::imu::ImuSample;
use kfmap_sim::gravity_in_map;
use kfmap_sim::noise::gaussian;

const G: f64 = 9.81;

/// Angle between two directions, degrees.
fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.angle(b).to_degrees()
}

/// The map-frame "up" a resting accelerometer reads in a world tilted by roll, pitch
/// (degrees) against the map.
fn true_up(roll_deg: f64, pitch_deg: f64) -> Vector3<f64> {
    -gravity_in_map(roll_deg.to_radians(), pitch_deg.to_radians())
}

/// `n` keyframes of a platform resting in varied attitudes in a tilted world: windows
/// of 100 samples with Gaussian noise `sigma` per axis.
fn tilted_pool(
    n: usize,
    roll_deg: f64,
    pitch_deg: f64,
    sigma: f64,
    seed: u64,
) -> (GravityAligner, BTreeMap<KeyframeId, Pose>) {
    biased_pool(n, [roll_deg, pitch_deg], sigma, Vector3::zeros(), 0.2, seed)
}

/// [`tilted_pool`] with a constant accelerometer `bias` (body frame) and attitudes
/// rolled and pitched up to `lean` radians (yaw anywhere).
fn biased_pool(
    n: usize,
    [roll_deg, pitch_deg]: [f64; 2],
    sigma: f64,
    bias: Vector3<f64>,
    lean: f64,
    seed: u64,
) -> (GravityAligner, BTreeMap<KeyframeId, Pose>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let up = true_up(roll_deg, pitch_deg);
    let mut aligner = GravityAligner::new(GravityParams::default()).unwrap();
    let mut poses = BTreeMap::new();
    for id in 0..n as u64 {
        let mut lean_angle = || {
            if lean > 0.0 {
                rng.random_range(-lean..lean)
            } else {
                0.0
            }
        };
        let (roll, pitch) = (lean_angle(), lean_angle());
        let yaw = if lean > 0.0 {
            rng.random_range(-3.1..3.1)
        } else {
            0.0
        };
        let rotation = UnitQuaternion::from_euler_angles(roll, pitch, yaw);
        let reading = rotation.inverse() * up + bias;
        let samples = (0..100)
            .map(|k| ImuSample {
                t: id as f64 + k as f64 * 0.01,
                acc: std::array::from_fn(|a| reading[a] + sigma * gaussian(&mut rng)),
                gyro: [0.0; 3],
            })
            .collect();
        assert!(aligner.on_new_keyframe(id, &ImuWindow::new(samples)));
        poses.insert(id, Pose::from_parts(Vector3::zeros().into(), rotation));
    }
    (aligner, poses)
}

#[test]
fn a_tilted_world_is_recovered_within_a_tenth_of_a_degree() {
    let (aligner, poses) = tilted_pool(30, 2.0, -3.0, 0.04, 1);
    let c = aligner.estimate_global_correction(&poses).unwrap();
    assert!((c.roll_deg() - 2.0).abs() < 0.1, "roll {}", c.roll_deg());
    assert!((c.pitch_deg() + 3.0).abs() < 0.1, "pitch {}", c.pitch_deg());
    assert_eq!(c.yaw(), 0.0);
    let up = c.rotation * c.estimate.g;
    assert!(angle_deg(&up, &Vector3::z()) < 1e-9);
    assert_eq!(c.estimate.health.members, 30);
    assert_eq!(c.estimate.health.inliers, 30);
    assert!(c.estimate.health.spread_deg < 0.1);
}

/// The bias is recovered with gravity when the attitudes vary; the oracle is the
/// bias and tilt the pool was drawn with. Without the bias term the tilt is off by
/// up to `atan(|b_horizontal| / g)` (less as yaw turns average it).
#[test]
fn an_accelerometer_bias_is_estimated_jointly_with_gravity() {
    let bias = Vector3::new(0.05, -0.03, 0.04);
    let (aligner, poses) = biased_pool(40, [2.0, -3.0], 0.04, bias, 0.2, 4);
    let up = true_up(2.0, -3.0);
    let e = aligner.estimate_gravity_vector(&poses).unwrap();
    let b = e.accel_bias;
    println!(
        "bias {:?} (true {bias:?}), sigma {:?}, tilt error {:.4} deg",
        b.mps2,
        b.sigma_mps2,
        angle_deg(&e.g, &up)
    );
    assert!((b.mps2 - bias).norm() < 0.005, "{:?}", b.mps2);
    assert!(b.observable);
    let sigma = b.sigma_mps2.unwrap();
    assert!(sigma.iter().all(|s| *s > 0.0 && *s < 0.01), "{sigma:?}");
    assert!(angle_deg(&e.g, &up) < 0.02, "{}", angle_deg(&e.g, &up));
    let plain = GravityAligner {
        params: GravityParams {
            estimate_accel_bias: false,
            ..GravityParams::default()
        },
        ..aligner.clone()
    };
    let unbiased = plain.estimate_gravity_vector(&poses).unwrap();
    // Measured: 0.006 deg with the bias term, 0.088 deg without.
    let (joint, plain) = (angle_deg(&e.g, &up), angle_deg(&unbiased.g, &up));
    assert!(plain > 5.0 * joint, "{plain} vs {joint}");

    // A platform that never turns cannot tell a bias from a tilt: not observable, and
    // the prior keeps the bias small.
    let (still, poses) = biased_pool(40, [2.0, -3.0], 0.04, bias, 0.0, 5);
    let e = still.estimate_gravity_vector(&poses).unwrap();
    assert!(!e.accel_bias.observable);
    assert!(e.accel_bias.mps2.norm() < 0.05, "{:?}", e.accel_bias.mps2);
}

/// A bias that drifts along the pool (x from 0.02 to 0.08 m/s^2, what correlated errors
/// along a real trajectory look like) must show in the sigma: the two halves' estimates
/// differ by about 0.03, so the reported sigma on x may not claim a few thousandths as
/// the residuals alone would (the steady pool's sigma stays that small).
#[test]
fn a_drifting_bias_widens_the_reported_sigma() {
    let steady = Vector3::new(0.05, -0.03, 0.04);
    let (aligner, poses) = biased_pool(60, [2.0, -3.0], 0.04, steady, 0.2, 7);
    let calm = aligner.estimate_gravity_vector(&poses).unwrap().accel_bias;
    let mut drifting = aligner.clone();
    for (k, id) in poses.keys().enumerate() {
        let drift = Vector3::new(0.06 * (k as f64 / 59.0 - 0.5), 0.0, 0.0);
        let mut sample = drifting.samples()[id];
        sample.a_body += drift;
        drifting.on_new_keyframe_raw(*id, sample);
    }
    let drifted = drifting.estimate_gravity_vector(&poses).unwrap().accel_bias;
    let (calm_sigma, drift_sigma) = (calm.sigma_mps2.unwrap(), drifted.sigma_mps2.unwrap());
    println!("sigma steady {calm_sigma:?}, drifting {drift_sigma:?}");
    assert!(calm_sigma.max() < 0.005, "{calm_sigma:?}");
    // Measured: 0.0005 steady, 0.0087 drifting.
    assert!(drift_sigma.x > 0.006, "{drift_sigma:?}");
    assert!((drifted.mps2.x - steady.x).abs() < 3.0 * drift_sigma.x);
}

#[test]
fn twenty_percent_outliers_stay_within_a_fifth_of_a_degree() {
    let (mut aligner, poses) = tilted_pool(50, 2.0, -3.0, 0.04, 2);
    let mut rng = StdRng::seed_from_u64(3);
    // Every fifth keyframe reads a steady but wrong direction (a bump, a lever arm).
    for id in (0..50).step_by(5) {
        let off = Rotation3::from_euler_angles(
            rng.random_range(0.3..0.8),
            rng.random_range(-0.8..-0.3),
            0.0,
        );
        aligner.on_new_keyframe_raw(
            id,
            KfAccSample {
                a_body: off * Vector3::new(0.0, 0.0, G + rng.random_range(-2.0..2.0)),
                a_std: 0.05,
                n: 100,
            },
        );
    }
    let c = aligner.estimate_global_correction(&poses).unwrap();
    assert!((c.roll_deg() - 2.0).abs() < 0.2, "roll {}", c.roll_deg());
    assert!((c.pitch_deg() + 3.0).abs() < 0.2, "pitch {}", c.pitch_deg());
    assert_eq!(c.estimate.health.members, 50);
    assert!(c.estimate.health.inliers <= 40);
}

#[test]
fn too_few_keyframes_give_none_and_drops_update_the_pool() {
    let (mut aligner, poses) = tilted_pool(10, 1.0, 1.0, 0.04, 4);
    assert!(aligner.estimate_gravity_vector(&poses).is_some());
    aligner.on_keyframe_dropped(3);
    assert!(!aligner.has(3));
    assert_eq!(aligner.size(), 9);
    assert!(aligner.estimate_gravity_vector(&poses).is_none());
    assert!(aligner.estimate_global_correction(&poses).is_none());
    // Poses without samples and samples without poses do not count.
    let mut fewer = poses.clone();
    fewer.remove(&4);
    aligner.on_new_keyframe_raw(3, aligner.samples()[&5]);
    assert!(aligner.estimate_gravity_vector(&fewer).is_none());
    // An empty window adds nothing; a repeated id overwrites.
    assert!(!aligner.on_new_keyframe(99, &ImuWindow::default()));
    assert!(!aligner.has(99));
    let before = aligner.samples()[&5];
    aligner.on_new_keyframe_raw(5, KfAccSample { n: 7, ..before });
    assert_eq!(aligner.samples()[&5].n, 7);
    assert_eq!(aligner.size(), 10);
    aligner.clear();
    assert_eq!(aligner.size(), 0);
}

#[test]
fn a_window_is_half_open_and_its_statistics_are_as_specified() {
    let stream: Vec<ImuSample> = (0..10)
        .map(|k| ImuSample {
            t: k as f64 * 0.1,
            acc: [0.0, 0.0, if k % 2 == 0 { 9.0 } else { 11.0 }],
            gyro: [0.0; 3],
        })
        .collect();
    // (0.2, 0.5] holds samples 3, 4 and 5 (t = 0.3, 0.4, 0.5), not 2.
    let w = ImuWindow::cut(&stream, stream[2].t, stream[5].t);
    assert_eq!(w.samples(), &stream[3..6]);
    assert!(ImuWindow::cut(&stream, 0.5, 0.5).is_empty());
    // Magnitudes 9 and 11 about a mean of 10: population std 1.
    let all = KfAccSample::from_window(&ImuWindow::new(stream.clone())).unwrap();
    assert_eq!(all.n, 10);
    assert!((all.a_body - Vector3::new(0.0, 0.0, 10.0)).norm() < 1e-12);
    assert!((all.a_std - 1.0).abs() < 1e-12);
    // A constant window's spread is floored.
    let quiet = KfAccSample::from_window(&ImuWindow::new(vec![stream[0]; 5])).unwrap();
    assert_eq!(quiet.a_std, MIN_ACC_STD);
    // Unsorted input is sorted.
    let mut reversed = stream.clone();
    reversed.reverse();
    assert_eq!(ImuWindow::new(reversed).samples(), &stream[..]);
}

#[test]
fn shaky_keyframes_keep_a_thousandth_of_their_weight() {
    // The plain weighted mean (no bias term) has the closed form below.
    let mut aligner = GravityAligner::new(GravityParams {
        irls_iterations: 0,
        estimate_accel_bias: false,
        ..GravityParams::default()
    })
    .unwrap();
    let mut poses = BTreeMap::new();
    for id in 0..12 {
        let (a, std) = match id {
            0 => (Vector3::new(1.0, 0.0, G), 2.0),
            _ => (Vector3::new(0.0, 0.0, G), 0.1),
        };
        aligner.on_new_keyframe_raw(
            id,
            KfAccSample {
                a_body: a,
                a_std: std,
                n: 10,
            },
        );
        poses.insert(id, Pose::identity());
    }
    let g = aligner.estimate_gravity_vector(&poses).unwrap().g;
    // Seeds: 1/0.01 = 100 for the quiet ones, 1e-3 / 4 for the shaky one.
    let shaky = 1e-3 / 4.0;
    let expected_x = shaky / (shaky + 11.0 * 100.0);
    assert!((g.x - expected_x).abs() < 1e-15, "{} vs {expected_x}", g.x);
}

#[test]
fn per_keyframe_corrections_have_zero_yaw_and_cover_the_pooled_keyframes() {
    let (mut aligner, mut poses) = tilted_pool(20, 2.0, -3.0, 0.04, 5);
    // Keyframe 20 has a pose but no samples.
    poses.insert(20, Pose::identity());
    aligner.on_keyframe_dropped(7);
    let per_kf = aligner.estimate_per_kf_correction(&poses, 3, 3);
    let pooled: Vec<KeyframeId> = aligner.samples().keys().copied().collect();
    assert_eq!(per_kf.keys().copied().collect::<Vec<_>>(), pooled);
    for c in per_kf.values() {
        assert_eq!(c.yaw(), 0.0);
        assert!((c.roll_deg() - 2.0).abs() < 0.3 && (c.pitch_deg() + 3.0).abs() < 0.3);
    }
    // Windows of one member are refused when two are needed.
    assert!(aligner.estimate_per_kf_correction(&poses, 0, 1).is_empty());
}

#[test]
fn rotation_from_gravity_sends_g_to_plus_z() {
    let mut rng = StdRng::seed_from_u64(6);
    for _ in 0..1000 {
        let g = Vector3::new(
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
        );
        let r = rotation_from_gravity(&g, 1e-9);
        let sent = r * g;
        assert!(
            angle_deg(&sent, &Vector3::z()).to_radians() < 1e-9,
            "{g:?} -> {sent:?}"
        );
        assert!((sent.norm() - g.norm()).abs() < 1e-9);
        assert_eq!(r.matrix()[(1, 0)], 0.0, "yaw entry");
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
    }
    assert_eq!(
        rotation_from_gravity(&Vector3::new(0.0, 0.0, 9.81), 1e-9),
        Rotation3::identity()
    );
    assert_eq!(
        rotation_from_gravity(&Vector3::new(1e-12, 0.0, 9.81), 1e-9),
        Rotation3::identity()
    );
    assert_eq!(
        rotation_from_gravity(&Vector3::new(1e-10, 0.0, 0.0), 1e-9),
        Rotation3::identity()
    );
    // Closed form: g = Rx(-0.2) z needs Rx(+0.2) to come back, so roll = 0.2.
    let g = Rotation3::from_euler_angles(-0.2, 0.0, 0.0) * Vector3::z();
    let (roll, pitch) = roll_pitch_from_gravity(&g, 1e-9);
    assert!(
        (roll - 0.2).abs() < 1e-12 && pitch.abs() < 1e-12,
        "{roll} {pitch}"
    );
}

#[test]
fn invalid_parameters_are_named() {
    let bad = GravityParams {
        huber_threshold_mps2: -1.0,
        ..GravityParams::default()
    };
    assert_eq!(
        GravityAligner::new(bad).unwrap_err().option,
        "huber-threshold-mps2"
    );
    let bad = GravityParams {
        min_keyframes: 1,
        ..GravityParams::default()
    };
    assert_eq!(bad.validate().unwrap_err().option, "min-keyframes");
}

#[test]
fn motion_model_recovers_a_constant_acceleration() {
    // x = 0.5 a t^2 sampled at 10 Hz: the mean acceleration over any interval is a.
    let a = Vector3::new(0.7, -0.3, 0.1);
    let poses = (0..50).map(|k| {
        let t = k as f64 * 0.1;
        (
            t,
            Pose::from_parts((a * 0.5 * t * t).into(), UnitQuaternion::identity()),
        )
    });
    let model = MotionModel::new(poses).unwrap();
    let got = model.mean_acceleration(1.05, 3.3).unwrap();
    assert!((got - a).norm() < 1e-9, "{got:?}");
    // Up to the ends too (second-order differences there).
    for (t0, t1) in [(0.0, 1.0), (3.9, 4.9)] {
        let got = model.mean_acceleration(t0, t1).unwrap();
        assert!((got - a).norm() < 1e-9, "{t0}..{t1}: {got:?}");
    }
    assert!(model.mean_acceleration(-1.0, 1.0).is_none());
    assert!(model.mean_acceleration(2.0, 2.0).is_none());
    assert!(MotionModel::new([(0.0, Pose::identity())]).is_none());
}

/// Keyframes at the poses' own times from 0 s, as `kfmap gravity` picks them: the first
/// one's window ends at the first pose, so no platform acceleration can be removed from
/// it. Compensated, it is left out and counted (its one raw sample, spread floored at
/// [`MIN_ACC_STD`], would weigh in heavily); raw, it is pooled.
#[test]
fn a_window_the_trajectory_does_not_cover_is_left_out_when_compensating() {
    let level = Pose::identity();
    let imu: Vec<ImuSample> = (0..=400)
        .map(|k| ImuSample {
            t: k as f64 * 0.005,
            acc: [0.0, 0.0, G],
            gyro: [0.0; 3],
        })
        .collect();
    let keyframes: Vec<KeyframeStamp> = (0..=2)
        .map(|id| KeyframeStamp {
            id,
            t: id as f64,
            pose: level,
        })
        .collect();
    let motion = MotionModel::new((0..=20).map(|k| (k as f64 * 0.1, level))).unwrap();
    let fill = |compensate: bool| {
        let params = GravityParams {
            motion_compensation: compensate,
            ..GravityParams::default()
        };
        let mut aligner = GravityAligner::new(params).unwrap();
        let fill = fill_pool(&mut aligner, &keyframes, &imu, Some(&motion));
        (fill, aligner.has(0))
    };
    let (compensated, first_pooled) = fill(true);
    assert!(!first_pooled);
    assert_eq!(
        (
            compensated.with_samples,
            compensated.compensated,
            compensated.skipped
        ),
        (2, 2, 1)
    );
    assert_eq!(compensated.samples_used, 400);
    let (raw, first_pooled) = fill(false);
    assert!(first_pooled);
    assert_eq!((raw.with_samples, raw.compensated, raw.skipped), (3, 0, 0));
}
