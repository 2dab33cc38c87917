//! Gravity estimated on simulated runs (tilted world) against the simulator's truth, at
//! the estimator's level: the pool filled from the simulator's trajectory, and a live
//! session against the offline pool. The runs as `kfmap gravity` and `kfmap bake` read
//! them (the dataset's files, the bias on) are in `bake/tests/gravity_sim.rs`.

use std::collections::BTreeMap;

use kfmap_geometry::KeyframeId;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::gravity::*;
use kfmap_geometry::imu::ImuSample;
use kfmap_sim::{ImuParams, Preset, SimConfig, Simulation, gravity_in_map};
use nalgebra::Vector3;

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

/// Gravity over a simulated run tilted roll 2, pitch -3 degrees, keyframes every
/// second: the global estimate's error and the RMS over per-keyframe corrections
/// (windows of 2 keyframes each side).
struct SimGravity {
    global: f64,
    per_keyframe_rms: f64,
    health: PoolHealth,
}

/// A simulated run to estimate gravity on, the accelerometer bias off.
#[derive(Clone, Copy)]
struct Run {
    preset: Preset,
    seconds: f64,
    seed: u64,
}

fn sim_gravity(run: Run, params: GravityParams) -> SimGravity {
    let imu = ImuParams {
        acc_bias: 0.0,
        ..ImuParams::default()
    };
    let config = SimConfig {
        preset: run.preset,
        seconds: run.seconds,
        seed: run.seed,
        tilt_deg: [2.0, -3.0],
        imu,
        ..SimConfig::default()
    };
    let sim = Simulation::new(config).unwrap();
    let samples = sim.imu();
    let trajectory = &sim.site().trajectory;
    let keyframes: Vec<KeyframeStamp> = (1..run.seconds as u64)
        .map(|id| KeyframeStamp {
            id,
            t: id as f64,
            pose: trajectory.pose(id as f64),
        })
        .collect();
    // The motion model sees only the 10 Hz LiDAR poses, as a bake would.
    let motion = MotionModel::new((0..(run.seconds * 10.0) as usize).map(|k| {
        let t = k as f64 * 0.1;
        (t, trajectory.pose(t))
    }))
    .unwrap();
    let poses: BTreeMap<KeyframeId, Pose> = keyframes.iter().map(|k| (k.id, k.pose)).collect();
    let up = true_up(2.0, -3.0);
    let mut aligner = GravityAligner::new(params).unwrap();
    let fill = fill_pool(&mut aligner, &keyframes, &samples, Some(&motion));
    assert_eq!(fill.with_samples, keyframes.len());
    assert_eq!(
        fill.compensated,
        if params.motion_compensation {
            keyframes.len()
        } else {
            0
        }
    );
    let e = aligner.estimate_gravity_vector(&poses).unwrap();
    let per_kf = aligner.estimate_per_kf_correction(&poses, 2, 3);
    let mean_sq = per_kf
        .values()
        .map(|c| angle_deg(&c.estimate.g, &up).powi(2))
        .sum::<f64>()
        / per_kf.len() as f64;
    SimGravity {
        global: angle_deg(&e.g, &up),
        per_keyframe_rms: mean_sq.sqrt(),
        health: e.health,
    }
}

#[test]
fn motion_compensation_reduces_the_gravity_error_on_an_accelerating_run() {
    let run = Run {
        preset: Preset::Courtyard,
        seconds: 40.0,
        seed: SimConfig::default().seed,
    };
    let params = |motion_compensation| GravityParams {
        motion_compensation,
        ..GravityParams::default()
    };
    let raw = sim_gravity(run, params(false));
    let compensated = sim_gravity(run, params(true));
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

/// A pool fed window by window (a server session) against the offline pool over the
/// same windows and poses. Live, scan windows (10 Hz) are joined into half-second ones;
/// the first scan's window has no start and the first joined one no two poses before it
/// (a velocity by central differences needs them): both are left out; the last waits
/// for a pose after it. The offline pool over the same joined windows must give the
/// same correction. Oracle for both: the simulator's tilt, with the 0.05 m/s^2 bias on.
#[test]
fn a_pool_fed_live_agrees_with_the_offline_pool() {
    let config = SimConfig {
        preset: Preset::Campus,
        seconds: 30.0,
        seed: 11,
        tilt_deg: [2.0, -3.0],
        ..SimConfig::default()
    };
    let sim = Simulation::new(config).unwrap();
    let imu = sim.imu();
    let trajectory = &sim.site().trajectory;
    let scans: Vec<KeyframeStamp> = (1..292u64)
        .map(|id| KeyframeStamp {
            id,
            t: id as f64 * 0.1,
            pose: trajectory.pose(id as f64 * 0.1),
        })
        .collect();
    let mut live = LiveGravity::new(GravityParams::default()).unwrap();
    let mut t_prev = 0.0;
    for k in &scans {
        live.add_window(k.id, ImuWindow::cut(&imu, t_prev, k.t), k.pose, Some(k.t));
        t_prev = k.t;
    }
    let answer = live.answer();
    // Joined windows end at scans 6, 11, ..., 286, 291: 58 of them.
    assert_eq!(
        answer.skipped, 2,
        "the first scan window and the first joined one"
    );
    assert_eq!(
        answer.pending, 1,
        "the last joined window waits for a later pose"
    );
    assert_eq!(answer.members, 58 - 2);
    assert_eq!(answer.compensated, answer.members);
    let served = answer.correction.unwrap();

    let members: Vec<KeyframeStamp> = scans
        .iter()
        .filter(|k| k.id >= 11 && k.id <= 286 && (k.id - 1) % 5 == 0)
        .copied()
        .collect();
    assert_eq!(members.len(), answer.members);
    let motion = MotionModel::new(scans.iter().map(|k| (k.t, k.pose))).unwrap();
    let mut offline = GravityAligner::new(GravityParams::default()).unwrap();
    let fill = fill_pool(&mut offline, &members, &imu, Some(&motion));
    assert_eq!(fill.compensated, members.len());
    let poses: BTreeMap<KeyframeId, Pose> = members.iter().map(|k| (k.id, k.pose)).collect();
    let offline = offline.estimate_global_correction(&poses).unwrap();
    let up = true_up(2.0, -3.0);
    let apart = angle_deg(&served.estimate.g, &offline.estimate.g);
    println!(
        "live vs offline: {apart:.6} deg apart; against the truth {:.4} / {:.4} deg; bias {:?} / {:?}",
        angle_deg(&served.estimate.g, &up),
        angle_deg(&offline.estimate.g, &up),
        served.estimate.accel_bias.mps2,
        offline.estimate.accel_bias.mps2,
    );
    assert!(apart < 1e-4, "{apart}");
    assert!(angle_deg(&served.estimate.g, &up) < 0.05);

    // Unstamped windows are pooled at once as raw means, and say so.
    let mut raw = LiveGravity::new(GravityParams::default()).unwrap();
    let mut t_prev = 0.0;
    for k in &scans {
        raw.add_window(k.id, ImuWindow::cut(&imu, t_prev, k.t), k.pose, None);
        t_prev = k.t;
    }
    let answer = raw.answer();
    assert_eq!(
        (
            answer.members,
            answer.compensated,
            answer.pending,
            answer.skipped
        ),
        (scans.len(), 0, 0, 0)
    );
}

/// A session streaming windows forever keeps the newest [`MAX_MEMBERS`]: the oracle is
/// a pool fed only those.
#[test]
fn a_live_pool_keeps_the_newest_members_only() {
    let window = |id: u64| {
        let tilt = 0.01 * (id % 7) as f64;
        ImuWindow::new(
            (0..10)
                .map(|k| ImuSample {
                    t: id as f64 + k as f64 * 0.01,
                    acc: [tilt, 0.0, G],
                    gyro: [0.0; 3],
                })
                .collect(),
        )
    };
    let extra = 50;
    let mut streamed = LiveGravity::new(GravityParams::default()).unwrap();
    let mut newest = LiveGravity::new(GravityParams::default()).unwrap();
    for id in 0..(MAX_MEMBERS + extra) as u64 {
        streamed.add_window(id, window(id), Pose::identity(), None);
        if id >= extra as u64 {
            newest.add_window(id, window(id), Pose::identity(), None);
        }
    }
    let (a, b) = (streamed.answer(), newest.answer());
    assert_eq!(a.members, MAX_MEMBERS);
    assert_eq!(b.members, MAX_MEMBERS);
    let (ga, gb) = (
        a.correction.unwrap().estimate.g,
        b.correction.unwrap().estimate.g,
    );
    assert!((ga - gb).norm() < 1e-12, "{ga:?} vs {gb:?}");
}
