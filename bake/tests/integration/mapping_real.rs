//! Map building on the real handheld sequence `balm_os0` (../shared/data; see
//! PROVENANCE.txt): 177 scans of an Ouster OS0-class LiDAR at 2 Hz along a 74.5 m loop
//! with fast turns, built from the raw scans alone and compared with the dataset's
//! reference poses (odometry-quality, consistent to a few cm locally).

use crate::TestError;
use kfmap_bake::mapping::{BuildParams, BuiltTrajectory, build_trajectory};
use kfmap_geometry::cloud::FilterOptions;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_geometry::trajectory_error::absolute_trajectory_error;
use kfmap_testdata::require_test_data;

struct Sequence {
    scans: Vec<std::path::PathBuf>,
    stamps: Vec<f64>,
    truth: Vec<Pose>,
}

fn balm() -> Option<Sequence> {
    let dir = require_test_data("balm_os0", "mapping_real")?;
    let mut scans: Vec<_> = std::fs::read_dir(dir.join("scans"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    scans.sort();
    let trajectory = read_trajectory(&dir.join("poses.txt")).unwrap();
    assert_eq!(scans.len(), trajectory.poses.len());
    Some(Sequence {
        scans,
        stamps: trajectory.stamps.unwrap(),
        truth: trajectory.poses,
    })
}

/// Builds the trajectory of the scans `pick` selects (indices into the sequence).
fn build(seq: &Sequence, pick: &[usize]) -> BuiltTrajectory {
    let options = ReadOptions {
        bin_layout: None,
        filter: FilterOptions::default(),
    };
    let stamps: Vec<f64> = pick.iter().map(|&i| seq.stamps[i]).collect();
    let started = std::time::Instant::now();
    let built = build_trajectory::<TestError>(
        &stamps,
        Vec::new(),
        |i| Ok(read_cloud(&seq.scans[pick[i]], &options)?.cloud),
        &BuildParams::default(),
        |_| {},
    )
    .unwrap();
    let truth: Vec<Pose> = pick.iter().map(|&i| seq.truth[i]).collect();
    // Steps whose motion odometry got wrong: (index, outcome, true turn deg, error m, deg).
    let bad_steps: Vec<String> = (1..pick.len())
        .filter_map(|i| {
            let e = built.odometry[i - 1].inverse() * built.odometry[i];
            let t = truth[i - 1].inverse() * truth[i];
            let d = e.inverse() * t;
            let (m, deg) = (d.translation.vector.norm(), d.rotation.angle().to_degrees());
            (m > 0.1 || deg > 1.0).then(|| {
                format!(
                    "{}:{:?} turn {:.0} -> {m:.2} m {deg:.1} deg",
                    pick[i],
                    built.outcomes[i],
                    t.rotation.angle().to_degrees()
                )
            })
        })
        .collect();
    println!("bad steps: {bad_steps:?}");
    for check in &built.loop_checks {
        let scan = |k: usize| pick[built.keyframe_scans[k]];
        println!(
            "loop scans {} - {}: {:?}",
            scan(check.older),
            scan(check.newer),
            check
                .verdict
                .map(|v| (v.accepted, v.converged, v.degenerate, v.fitness))
        );
    }
    println!(
        "{} scans in {:.1} s: ATE {:.3} m (odometry alone {:.3} m); {} keyframes, loops {} \
         found / {} accepted {:?}; outcomes {:?}",
        pick.len(),
        started.elapsed().as_secs_f64(),
        absolute_trajectory_error(&built.poses, &truth),
        absolute_trajectory_error(&built.odometry, &truth),
        built.keyframe_scans.len(),
        built.loops_found,
        built.loops_accepted().len(),
        built.loops_accepted(),
        built
            .outcomes
            .iter()
            .enumerate()
            .filter(|(_, o)| **o != kfmap_bake::mapping::OdometryOutcome::Tracked)
            .collect::<Vec<_>>(),
    );
    built
}

/// The README's results table (and DESIGN.md): ATE of every scan of balm_os0 built
/// from its raw scans, metres, at 2 Hz (all 177 scans) and at 1 Hz (every second one).
const CLAIMED_ATE_2HZ_M: f64 = 0.060;
const CLAIMED_ATE_1HZ_M: f64 = 0.061;

/// A claimed figure is asserted within this factor of itself: a regression of more
/// than half the figure fails.
const CLAIM_SLACK: f64 = 1.5;

/// `ate` within [`CLAIM_SLACK`] times `figure`, the ATE published (or measured) for it.
fn assert_near_claim(what: &str, ate: f64, figure: f64) {
    println!("{what}: ATE {ate:.4} m, figure {figure} m");
    assert!(
        ate <= CLAIM_SLACK * figure,
        "{what}: ATE {ate} m, more than {CLAIM_SLACK} x {figure} m"
    );
}

#[test]
fn balm_built_from_raw_scans_at_2hz() {
    let Some(seq) = balm() else { return };
    let all: Vec<usize> = (0..seq.scans.len()).collect();
    let built = build(&seq, &all);
    let ate = absolute_trajectory_error(&built.poses, &seq.truth);
    assert_near_claim("2 Hz", ate, CLAIMED_ATE_2HZ_M);
    // The revisit of the start area (scans 0-7 seen again from 116 on) is closed.
    let scan = |k: usize| built.keyframe_scans[k];
    assert!(
        built
            .loops_accepted()
            .iter()
            .any(|&(older, newer)| scan(older) <= 7 && scan(newer) >= 116),
        "{:?}",
        built.loops_accepted()
    );
}

#[test]
fn balm_built_from_every_second_scan_at_1hz() {
    let Some(seq) = balm() else { return };
    let pick: Vec<usize> = (0..seq.scans.len()).step_by(2).collect();
    let built = build(&seq, &pick);
    let truth: Vec<Pose> = pick.iter().map(|&i| seq.truth[i]).collect();
    let ate = absolute_trajectory_error(&built.poses, &truth);
    assert_near_claim("1 Hz", ate, CLAIMED_ATE_1HZ_M);
}

#[test]
fn balm_built_from_a_moving_start() {
    let Some(seq) = balm() else { return };
    let pick: Vec<usize> = (40..seq.scans.len()).collect();
    let built = build(&seq, &pick);
    let truth: Vec<Pose> = pick.iter().map(|&i| seq.truth[i]).collect();
    let ate = absolute_trajectory_error(&built.poses, &truth);
    // No figure published; measured 0.046 m, held to the same slack.
    assert_near_claim("moving start", ate, 0.046);
}

/// Another sensor: KITTI 00 frames 0-5 (Velodyne HDL-64E, 10 Hz, 0.86 m per frame, not
/// deskewed). Pairwise GICP and small_gicp recover only 81-83 % of each step's forward
/// motion on these frames (PROVENANCE.txt: 12-18 cm short per step), so odometry must
/// stay within that: aligned ATE under what a 15 cm-per-step shortfall leaves (0.26 m).
#[test]
fn kitti00_frames_built_from_raw_scans() {
    let Some(dir) = require_test_data("kitti00", "mapping_real") else {
        return;
    };
    let truth = read_trajectory(&dir.join("poses_velo_kitti.txt"))
        .unwrap()
        .poses;
    let stamps: Vec<f64> = (0..6).map(|i| i as f64 * 0.1).collect();
    let options = ReadOptions {
        bin_layout: None,
        filter: FilterOptions::default(),
    };
    let built = build_trajectory::<TestError>(
        &stamps,
        Vec::new(),
        |i| Ok(read_cloud(&dir.join(format!("{i:06}.bin")), &options)?.cloud),
        &BuildParams::default(),
        |_| {},
    )
    .unwrap();
    // Closed form of the shortfall: steps of 0.86 m estimated 0.15 m short each.
    let short: Vec<Pose> = (0..6)
        .map(|i| Pose::translation(0.71 * i as f64, 0.0, 0.0))
        .collect();
    let straight: Vec<Pose> = (0..6)
        .map(|i| Pose::translation(0.86 * i as f64, 0.0, 0.0))
        .collect();
    let bound = absolute_trajectory_error(&short, &straight);
    let ate = absolute_trajectory_error(&built.poses, &truth);
    println!("KITTI 00 frames 0-5: ATE {ate:.3} m (a 15 cm-per-step shortfall: {bound:.3} m)");
    assert!(ate < bound, "ATE {ate} m, bound {bound} m");
}

/// hku2_avia (PROVENANCE.txt): a solid-state LiDAR walk, 266 scans 0.2 m apart, baked
/// with built poses exactly as `kfmap bake --build-poses --trajectory-out` does. The
/// written trajectory is scored here against the dataset's FAST-LIO2 poses: scans 157
/// and 256 used to be built 1.2 m off their neighbours (aligned ATE 0.126 m) with no
/// word of it; each scan must now be within 0.3 m or listed as poor, in the summary
/// and in the trajectory's sidecar.
#[test]
fn hku2_scans_off_their_neighbours_are_reregistered_or_listed_poor() {
    use kfmap_bake::config::BakeConfig;
    use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake, scan_check_sidecar};
    use kfmap_geometry::trajectory_error::rigid_alignment;

    let Some(dir) = require_test_data("hku2_avia", "mapping_real") else {
        return;
    };
    let scratch = kfmap_testdata::Scratch::new("hku2-check");
    let output = BakeOutput {
        trajectory: Some(scratch.file("built.tum")),
        ..BakeOutput::map(scratch.file("hku2.kfmap"))
    };
    let input = BakeInput {
        build_poses: true,
        ..BakeInput::dataset(&dir)
    };
    let report = bake(&input, &BakeConfig::default(), &output, |_| {}).unwrap();
    let mapping = report.mapping.expect("poses built");
    let built = read_trajectory(output.trajectory.as_ref().unwrap()).unwrap();
    let truth = read_trajectory(&dir.join("poses.txt")).unwrap();
    assert_eq!(built.poses.len(), truth.poses.len());
    // The sidecar's poor scans, as the user sees them.
    let sidecar = std::fs::read_to_string(scan_check_sidecar(&scratch.file("built.tum"))).unwrap();
    let listed_poor: Vec<usize> = sidecar
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect::<Vec<_>>())
        .filter(|f| f[2] == "poor")
        .map(|f| f[0].parse().unwrap())
        .collect();
    assert_eq!(sidecar.lines().count(), 1 + truth.poses.len());
    assert_eq!(listed_poor, mapping.poor_scans);
    // Each scan's position error after the rigid fit of the whole trajectory.
    let fit = rigid_alignment(&built.poses, &truth.poses);
    let errors: Vec<f64> = built
        .poses
        .iter()
        .zip(&truth.poses)
        .map(|(b, t)| ((fit * b).translation.vector - t.translation.vector).norm())
        .collect();
    let ate = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    let (worst, max) = errors
        .iter()
        .enumerate()
        .fold((0, 0.0), |a, (i, &e)| if e > a.1 { (i, e) } else { a });
    println!(
        "hku2_avia built: ATE {ate:.4} m, worst scan {worst} {max:.3} m; re-registered {:?}, poor {:?}; {:.1} s",
        mapping.reregistered_scans, mapping.poor_scans, report.seconds
    );
    let off_and_unlisted: Vec<(usize, f64)> = errors
        .iter()
        .enumerate()
        .filter(|&(i, &e)| e > 0.3 && !listed_poor.contains(&i))
        .map(|(i, &e)| (i, e))
        .collect();
    assert!(off_and_unlisted.is_empty(), "{off_and_unlisted:?}");
    // The joint refinement ran and was kept; without it the same bake lands 0.059 m
    // (0.126 m before the scan check), with it 0.027 m (the target: 0.05 m).
    let refine = mapping.refine.as_ref().expect("refinement on by default");
    assert!(refine.accepted(), "{:?}", refine.refused);
    let mut config = BakeConfig::default();
    config.build.refine.enabled = false;
    let unrefined_out = BakeOutput {
        trajectory: Some(scratch.file("unrefined.tum")),
        ..BakeOutput::map(scratch.file("unrefined.kfmap"))
    };
    bake(&input, &config, &unrefined_out, |_| {}).unwrap();
    let unrefined = read_trajectory(&scratch.file("unrefined.tum")).unwrap();
    let ate_unrefined = absolute_trajectory_error(&unrefined.poses, &truth.poses);
    println!("hku2_avia: ATE {ate_unrefined:.4} m without the refinement, {ate:.4} m with it");
    assert!(
        ate_unrefined > 0.05,
        "ATE without refinement {ate_unrefined} m"
    );
    assert!(ate < 0.036, "ATE {ate} m");
}

/// The joint refinement on balm_os0, through the bake a user runs: the map built from the raw scans
/// (refined by default) against the reference after the same refinement
/// (`--refine-only` on `poses.txt`). The raw reference is BALM's input odometry
/// (PROVENANCE.txt): the adjustment moves it 6 cm, while the built map, refined, lands
/// within 5 mm of the adjusted reference (2.5 mm measured; 12.5 mm without the
/// refinement). Both are measured here from the written trajectories.
#[test]
fn balm_built_and_refined_lands_on_the_adjusted_reference() {
    use kfmap_bake::config::BakeConfig;
    use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake};

    let Some(dir) = require_test_data("balm_os0", "mapping_real") else {
        return;
    };
    let scratch = kfmap_testdata::Scratch::new("balm-refine");
    let run = |name: &str, input: BakeInput, config: &BakeConfig| {
        let output = BakeOutput {
            trajectory: Some(scratch.file(&format!("{name}.tum"))),
            ..BakeOutput::map(scratch.file(&format!("{name}.kfmap")))
        };
        let report = bake(&input, config, &output, |_| {}).unwrap();
        let poses = read_trajectory(output.trajectory.as_ref().unwrap())
            .unwrap()
            .poses;
        (poses, report)
    };
    let built_input = BakeInput {
        build_poses: true,
        ..BakeInput::dataset(&dir)
    };
    let (built, report) = run("built", built_input.clone(), &BakeConfig::default());
    let refine = report.mapping.unwrap().refine.expect("on by default");
    assert!(refine.accepted(), "{:?}", refine.refused);
    let mut config = BakeConfig::default();
    config.build.refine.enabled = false;
    let (unrefined, _) = run("unrefined", built_input, &config);
    let adjusted_input = BakeInput {
        poses: Some(dir.join("poses.txt")),
        refine_only: true,
        ..BakeInput::dataset(&dir)
    };
    let (adjusted, _) = run("adjusted", adjusted_input, &BakeConfig::default());
    let reference = read_trajectory(&dir.join("poses.txt")).unwrap().poses;
    let ate = |a: &[Pose], b: &[Pose]| absolute_trajectory_error(a, b);
    let (built_raw, built_adjusted) = (ate(&built, &reference), ate(&built, &adjusted));
    let unrefined_adjusted = ate(&unrefined, &adjusted);
    let reference_moved = ate(&adjusted, &reference);
    println!(
        "balm_os0: built {built_raw:.4} m from the reference, {built_adjusted:.4} m from the adjusted \
         reference ({unrefined_adjusted:.4} m unrefined); the adjustment moved the reference {reference_moved:.4} m"
    );
    assert!(built_raw < 0.075, "{built_raw}");
    assert!(reference_moved > 0.05, "{reference_moved}");
    assert!(built_adjusted < 0.005, "{built_adjusted}");
    assert!(
        built_adjusted < 0.6 * unrefined_adjusted,
        "{built_adjusted} {unrefined_adjusted}"
    );
}
