use super::*;
use crate::sim::{LidarParams, Preset, SimConfig, Simulation};

/// Translation error of the first-to-last relative pose, metres.
fn end_to_start_drift(estimate: &[Pose], truth: &[Pose]) -> f64 {
    let (n, m) = (estimate.len() - 1, truth.len() - 1);
    let e = estimate[0].inverse() * estimate[n];
    let t = truth[0].inverse() * truth[m];
    (e.inverse() * t).translation.vector.norm()
}

#[derive(Debug, thiserror::Error)]
enum TestError {
    #[error(transparent)]
    Registration(#[from] RegistrationError),
    #[error(transparent)]
    Global(#[from] GlobalError),
}

struct LapFigures {
    ate: f64,
    ate_odometry: f64,
    drift: f64,
    drift_odometry: f64,
    loops: usize,
}

/// Builds the trajectory of a simulated run from its raw scans alone and compares it
/// with the simulator's ground truth.
fn lap(preset: Preset, seconds: f64, beams: u32) -> LapFigures {
    let sim = Simulation::new(SimConfig {
        preset,
        seconds,
        lidar: LidarParams {
            beams,
            horizontal_resolution_deg: 0.4,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    })
    .unwrap();
    let count = sim.config().scan_count();
    let started = std::time::Instant::now();
    let built = build_trajectory::<TestError>(
        count,
        |i| Ok(sim.scan(i).cloud),
        &BuildParams::default(),
        |_| {},
    )
    .unwrap();
    let truth: Vec<Pose> = (0..count).map(|i| sim.scan_pose(i)).collect();
    let kf =
        |poses: &[Pose]| -> Vec<Pose> { built.keyframe_scans.iter().map(|&i| poses[i]).collect() };
    let figures = LapFigures {
        ate: absolute_trajectory_error(&kf(&built.poses), &kf(&truth)),
        ate_odometry: absolute_trajectory_error(&kf(&built.odometry), &kf(&truth)),
        drift: end_to_start_drift(&built.poses, &truth),
        drift_odometry: end_to_start_drift(&built.odometry, &truth),
        loops: built.loops_accepted.len(),
    };
    println!(
        "{preset:?} {seconds} s, {beams} beams, {count} scans, {} keyframes in {:.1} s: loops {} \
         found / {} accepted; graph error {:.3} -> {:.3}; keyframe ATE {:.3} m (odometry alone \
         {:.3} m); end-to-start drift {:.3} m (odometry alone {:.3} m)",
        built.keyframe_scans.len(),
        started.elapsed().as_secs_f64(),
        built.loops_found,
        figures.loops,
        built.graph.initial_error,
        built.graph.final_error,
        figures.ate,
        figures.ate_odometry,
        figures.drift,
        figures.drift_odometry
    );
    figures
}

/// A full lap of the simulated campus (778 m, 32 beams) and a little more, built from
/// the raw scans alone. ARCHITECTURE / issue target: keyframe ATE under 10 cm (NOT
/// reached: 11.7 cm measured, 43.5 cm from odometry alone) and loop closure cutting the
/// end-to-start drift at least 5x (met: 1.55 m -> 0.11 m). The bounds below guard the
/// measured figures.
#[test]
fn campus_lap_from_raw_scans() {
    let f = lap(Preset::Campus, 165.0, 32);
    assert!(f.loops > 0);
    assert!(
        f.ate < 0.15 && f.ate < f.ate_odometry / 2.0,
        "ATE {} (odometry {})",
        f.ate,
        f.ate_odometry
    );
    assert!(
        f.drift * 5.0 <= f.drift_odometry,
        "{} vs {}",
        f.drift,
        f.drift_odometry
    );
}
