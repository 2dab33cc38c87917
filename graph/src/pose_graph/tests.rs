use nalgebra::{Matrix6, UnitQuaternion, Vector3, Vector6};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use kfmap_sim::noise::gaussian;

fn pose(x: f64, y: f64, z: f64, roll: f64, pitch: f64, yaw: f64) -> Pose {
    Pose::from_parts(
        Vector3::new(x, y, z).into(),
        UnitQuaternion::from_euler_angles(roll, pitch, yaw),
    )
}

/// A closed square of `side` poses per edge of the square, 1 m apart, turning 90 deg at
/// the corners; odometry edges between neighbours and a loop edge last -> first.
fn square(per_side: usize) -> Vec<Pose> {
    let mut poses = Vec::new();
    let mut current = Pose::identity();
    for k in 0..4 * per_side {
        poses.push(current);
        let turn = if (k + 1) % per_side == 0 {
            std::f64::consts::FRAC_PI_2
        } else {
            0.0
        };
        current *= pose(1.0, 0.0, 0.0, 0.0, 0.0, turn);
    }
    poses
}

fn graph_from(truth: &[Pose], start: &[Pose], loop_edge: bool) -> PoseGraph {
    let mut graph = PoseGraph::default();
    for (i, p) in start.iter().enumerate() {
        graph.add_pose(i as u64, *p).unwrap();
    }
    let info = Matrix6::from_diagonal(&Vector6::new(400.0, 400.0, 400.0, 100.0, 100.0, 100.0));
    for i in 1..truth.len() {
        let z = truth[i - 1].inverse() * truth[i];
        graph
            .add_edge(PoseEdge::new(i as u64 - 1, i as u64, z, info))
            .unwrap();
    }
    if loop_edge {
        let last = truth.len() - 1;
        let z = truth[last].inverse() * truth[0];
        graph
            .add_edge(PoseEdge::new(last as u64, 0, z, info))
            .unwrap();
    }
    graph
}

#[test]
fn se3_exp_and_log_are_inverse_and_match_closed_forms() {
    let mut rng = StdRng::seed_from_u64(1);
    for _ in 0..200 {
        let xi = Vector6::from_fn(|_, _| rng.random_range(-2.0..2.0));
        assert!((log(&exp(&xi)) - xi).norm() < 1e-9, "{xi:?}");
    }
    // Pure translation and pure rotation are exact.
    let t = exp(&Vector6::new(0.0, 0.0, 0.0, 1.0, 2.0, 3.0));
    assert!((t.translation.vector - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-15);
    // A quarter turn about z while moving 1 m along x in the body traces a quarter
    // circle of radius 2/pi: the chord is (2/pi, 2/pi).
    let arc = exp(&Vector6::new(
        0.0,
        0.0,
        std::f64::consts::FRAC_PI_2,
        1.0,
        0.0,
        0.0,
    ));
    let r = 2.0 / std::f64::consts::PI;
    assert!((arc.translation.vector - Vector3::new(r, r, 0.0)).norm() < 1e-12);
    // Ad(T) Exp(xi) = T Exp(xi) T^-1.
    let a = pose(1.0, -2.0, 0.5, 0.3, -0.2, 1.1);
    let xi = Vector6::new(0.1, 0.2, -0.3, 0.4, -0.5, 0.6);
    let lhs = exp(&(adjoint(&a) * xi));
    let rhs = a * exp(&xi) * a.inverse();
    assert!((log(&(lhs.inverse() * rhs))).norm() < 1e-12);
}

#[test]
fn a_noise_free_loop_returns_to_its_optimum() {
    let truth = square(5);
    let mut rng = StdRng::seed_from_u64(2);
    let start: Vec<Pose> = truth
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i == 0 {
                return *p;
            }
            let d = Vector6::from_fn(|_, _| gaussian(&mut rng) * 0.1);
            *p * exp(&d)
        })
        .collect();
    for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
        let mut graph = graph_from(&truth, &start, true);
        let report = graph
            .optimize(&GraphParams {
                optimizer,
                relative_error_tol: 1e-12,
                absolute_error_tol: 1e-20,
                ..GraphParams::default()
            })
            .unwrap();
        assert!(report.final_error < 1e-12, "{report:?}");
        for (i, t) in truth.iter().enumerate() {
            let off = log(&(t.inverse() * graph.pose(i as u64).unwrap())).norm();
            assert!(off < 1e-6, "{optimizer:?} pose {i}: {off}");
        }
    }
}

#[test]
fn with_noisy_edges_the_error_decreases_monotonically() {
    let truth = square(8);
    let mut rng = StdRng::seed_from_u64(3);
    let mut graph = graph_from(&truth, &truth, true);
    // Noisy measurements, and a start far from them.
    let noisy: Vec<PoseEdge> = graph
        .edges()
        .iter()
        .map(|e| PoseEdge {
            measurement: e.measurement * exp(&Vector6::from_fn(|_, _| gaussian(&mut rng) * 0.05)),
            ..*e
        })
        .collect();
    let mut noisy_graph = PoseGraph::default();
    for (i, t) in truth.iter().enumerate() {
        let d = Vector6::from_fn(|_, _| {
            if i == 0 {
                0.0
            } else {
                gaussian(&mut rng) * 0.2
            }
        });
        noisy_graph.add_pose(i as u64, *t * exp(&d)).unwrap();
    }
    for e in noisy {
        noisy_graph.add_edge(e).unwrap();
    }
    graph = noisy_graph;
    for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
        let mut g = graph.clone();
        let report = g
            .optimize(&GraphParams {
                optimizer,
                ..GraphParams::default()
            })
            .unwrap();
        let mut previous = report.initial_error;
        for &e in &report.errors {
            assert!(
                e <= previous * (1.0 + 1e-12),
                "{optimizer:?}: {:?}",
                report.errors
            );
            previous = e;
        }
        assert!(report.converged && report.final_error < report.initial_error / 10.0);
    }
}

#[test]
fn a_robust_kernel_ignores_a_wrong_loop_edge() {
    let truth = square(6);
    let mut graph = graph_from(&truth, &truth, true);
    // A false loop closure claiming vertex 12 sits on vertex 3.
    let mut wrong = PoseEdge::new(3, 12, Pose::identity(), Matrix6::identity() * 100.0);
    wrong.kernel = RobustKernel::Cauchy { delta: 1.0 };
    graph.add_edge(wrong).unwrap();
    graph.optimize(&GraphParams::default()).unwrap();
    let moved = (0..truth.len())
        .map(|i| log(&(truth[i].inverse() * graph.pose(i as u64).unwrap())).norm())
        .fold(0.0, f64::max);
    assert!(moved < 0.1, "{moved}");
}

#[test]
fn g2o_round_trip_and_errors_name_the_line() {
    let truth = square(3);
    let graph = graph_from(&truth, &truth, true);
    let dir = std::env::temp_dir().join(format!("kfmap-g2o-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("square.g2o");
    write_g2o(&path, &graph, Some(0)).unwrap();
    let (back, fixed) = read_g2o(&path).unwrap();
    assert_eq!(fixed, Some(0));
    assert_eq!(back.ids(), graph.ids());
    assert_eq!(back.edges().len(), graph.edges().len());
    for (a, b) in back.edges().iter().zip(graph.edges()) {
        assert!((a.information - b.information).abs().max() < 1e-6);
        assert!(log(&(a.measurement.inverse() * b.measurement)).norm() < 1e-8);
    }
    let cases = [
        (
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 0 1 0 0 0 0 0 1\n",
            "line 2",
        ),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 1\n", "needs 8 values"),
        ("VERTEX_SE3:QUAT 0 0 0 nan 0 0 0 1\n", "not a finite number"),
        ("VERTEX_SE2 0 0 0 0\n", "unsupported element"),
        (
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 7 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n",
            "vertex 7",
        ),
    ];
    for (text, expect) in cases {
        std::fs::write(&path, text).unwrap();
        let err = read_g2o(&path).unwrap_err().to_string();
        assert!(err.contains(expect), "{err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn elch_distributes_the_loop_error_by_graph_distance() {
    // A square of 4 x 4 steps whose odometry drifts: every step turns 1 deg too much.
    let truth = square(4);
    let mut drifted = vec![Pose::identity()];
    for i in 1..truth.len() {
        let step = truth[i - 1].inverse() * truth[i];
        let last = *drifted.last().unwrap();
        drifted.push(last * step * pose(0.0, 0.0, 0.0, 0.0, 0.0, 1f64.to_radians()));
    }
    // Odometry edges agree with the drifted poses; only the loop edge disagrees.
    let mut graph = graph_from(&drifted, &drifted, false);
    let last = truth.len() - 1;
    let loop_edge = PoseEdge::new(
        0,
        last as u64,
        truth[0].inverse() * truth[last],
        Matrix6::identity(),
    );
    let before = log(&(drifted[last].inverse() * truth[last])).norm();
    let shares = elch(&mut graph, &loop_edge).unwrap();
    // Shares grow with hops from the start: vertex k of the chain 0..last has k / last.
    for (k, w) in shares.iter().enumerate() {
        assert!((w - k as f64 / last as f64).abs() < 1e-12, "{k}: {w}");
    }
    // The end lands where the loop edge says; the start does not move.
    let end = graph.pose(last as u64).unwrap();
    assert!(log(&(end.inverse() * truth[last])).norm() < 1e-9);
    assert!(log(&graph.pose(0).unwrap().inverse()).norm() < 1e-12);
    // In between the error shrinks, and the optimizer starts nearer its optimum.
    let mid = last / 2;
    let mid_before = log(&(drifted[mid].inverse() * truth[mid])).norm();
    let mid_after = log(&(graph.pose(mid as u64).unwrap().inverse() * truth[mid])).norm();
    assert!(
        mid_after < mid_before,
        "{mid_before} -> {mid_after}, end {before}"
    );
    let mean_error = |poses: &dyn Fn(usize) -> Pose| {
        (0..truth.len())
            .map(|i| (poses(i).translation.vector - truth[i].translation.vector).norm())
            .sum::<f64>()
            / truth.len() as f64
    };
    let drift = mean_error(&|i| drifted[i]);
    let closed = mean_error(&|i| *graph.pose(i as u64).unwrap());
    assert!(
        closed < 0.7 * drift,
        "mean position error {drift} -> {closed}"
    );
    assert!(matches!(
        elch(
            &mut graph,
            &PoseEdge::new(0, 99, Pose::identity(), Matrix6::identity())
        ),
        Err(ElchError::UnknownVertex { missing: 99, .. })
    ));
}
