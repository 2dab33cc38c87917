use std::collections::BTreeMap;

use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::imu::ImuSample;
use crate::sim::noise::gaussian;
use crate::sim::{ImuParams, SimConfig, Simulation, gravity_in_map};

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
    let mut rng = StdRng::seed_from_u64(seed);
    let up = true_up(roll_deg, pitch_deg);
    let mut aligner = GravityAligner::new(GravityParams::default()).unwrap();
    let mut poses = BTreeMap::new();
    for id in 0..n as u64 {
        let rotation = UnitQuaternion::from_euler_angles(
            rng.random_range(-0.2..0.2),
            rng.random_range(-0.2..0.2),
            rng.random_range(-3.1..3.1),
        );
        let reading = rotation.inverse() * up;
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
    let mut aligner = GravityAligner::new(GravityParams {
        irls_iterations: 0,
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
    assert!(model.mean_acceleration(-1.0, 1.0).is_none());
    assert!(model.mean_acceleration(2.0, 2.0).is_none());
    assert!(MotionModel::new([(0.0, Pose::identity())]).is_none());
}

/// Gravity-direction errors (degrees) on the simulated courtyard, tilted by (2, -3)
/// degrees, keyframes every second: the global estimate, and the RMS over per-keyframe
/// corrections (windows of 2 keyframes each side).
struct CourtyardErrors {
    global: f64,
    per_keyframe_rms: f64,
    health: PoolHealth,
}

fn courtyard_errors(seconds: f64, compensate: bool) -> CourtyardErrors {
    let config = SimConfig {
        seconds,
        tilt_deg: [2.0, -3.0],
        imu: ImuParams {
            acc_bias: 0.0,
            ..ImuParams::default()
        },
        ..SimConfig::default()
    };
    let sim = Simulation::new(config).unwrap();
    let imu = sim.imu();
    let trajectory = &sim.site().trajectory;
    let keyframes: Vec<KeyframeStamp> = (1..seconds as u64)
        .map(|id| KeyframeStamp {
            id,
            t: id as f64,
            pose: trajectory.pose(id as f64),
        })
        .collect();
    // The motion model sees only the 10 Hz LiDAR poses, as a bake would.
    let motion = MotionModel::new((0..(seconds * 10.0) as usize).map(|k| {
        let t = k as f64 * 0.1;
        (t, trajectory.pose(t))
    }))
    .unwrap();
    let poses: BTreeMap<KeyframeId, Pose> = keyframes.iter().map(|k| (k.id, k.pose)).collect();
    let up = true_up(2.0, -3.0);
    let mut aligner = GravityAligner::new(GravityParams {
        motion_compensation: compensate,
        ..GravityParams::default()
    })
    .unwrap();
    let fill = fill_pool(&mut aligner, &keyframes, &imu, Some(&motion));
    assert_eq!(fill.with_samples, keyframes.len());
    assert_eq!(
        fill.compensated,
        if compensate { keyframes.len() } else { 0 }
    );
    let e = aligner.estimate_gravity_vector(&poses).unwrap();
    let per_kf = aligner.estimate_per_kf_correction(&poses, 2, 3);
    let mean_sq = per_kf
        .values()
        .map(|c| angle_deg(&c.estimate.g, &up).powi(2))
        .sum::<f64>()
        / per_kf.len() as f64;
    CourtyardErrors {
        global: angle_deg(&e.g, &up),
        per_keyframe_rms: mean_sq.sqrt(),
        health: e.health,
    }
}

#[test]
fn motion_compensation_reduces_the_gravity_error_on_an_accelerating_run() {
    let raw = courtyard_errors(40.0, false);
    let compensated = courtyard_errors(40.0, true);
    println!(
        "courtyard 40 s, keyframes every 1 s: global gravity error {:.3} deg raw, {:.3} deg \
         motion-compensated; per-keyframe RMS {:.3} -> {:.3} deg; pool spread {:.2} -> {:.2} deg",
        raw.global,
        compensated.global,
        raw.per_keyframe_rms,
        compensated.per_keyframe_rms,
        raw.health.spread_deg,
        compensated.health.spread_deg
    );
    assert!(compensated.global < raw.global / 2.0);
    assert!(compensated.global < 0.05, "{}", compensated.global);
    assert!(compensated.per_keyframe_rms < raw.per_keyframe_rms / 2.0);
    assert!(compensated.health.spread_deg < raw.health.spread_deg / 2.0);
}
