//! Pose-graph optimization of `../shared/data/g2o/parking-garage.g2o` (1661 poses, 6275
//! edges) against GTSAM 4.3 (`tools/anchors/gtsam_pose_graph.py`: with a tight prior on
//! pose 0, Gauss-Newton goes from 8363.601948 to 0.634192 in 4 iterations; GTSAM's
//! error is half the chi2, as kfmap's).

use kfmap_geometry::registration::Optimizer;
use kfmap_graph::pose_graph::{GraphParams, read_g2o};
use kfmap_testdata::require_test_data;

#[test]
fn parking_garage_reaches_gtsams_final_error() {
    let Some(path) = require_test_data("g2o/parking-garage.g2o", "pose_graph_real") else {
        return;
    };
    for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
        let (mut graph, fixed) = read_g2o(&path).unwrap();
        assert_eq!((graph.len(), graph.edges().len()), (1661, 6275));
        let report = graph
            .optimize(&GraphParams {
                optimizer,
                fixed,
                ..GraphParams::default()
            })
            .unwrap();
        println!(
            "{optimizer:?}: {:.6} -> {:.6} in {} iterations",
            report.initial_error, report.final_error, report.iterations
        );
        assert!((report.initial_error - 8363.601948).abs() < 1e-5);
        assert!(
            (report.final_error - 0.634192).abs() / 0.634192 < 1e-4,
            "{}",
            report.final_error
        );
        assert!(report.converged);
    }
}
