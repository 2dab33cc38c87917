//! Fuzzes the g2o reader (`VERTEX_SE3:QUAT`, `EDGE_SE3:QUAT`, `FIX`) as
//! `kfmap optimize-graph` uses it: any file gives a graph or a named error, never a
//! panic. Poses read are finite unit rotations; a graph read writes back
//! (`write_g2o`) and reads again to as many vertices and edges; small graphs are
//! optimized a few iterations (both optimizers), which must return Ok or an error.
//! Run: `cargo +nightly fuzz run g2o`.
#![no_main]

#[path = "common.rs"]
mod common;

use kfmap_geometry::registration::Optimizer;
use kfmap_graph::pose_graph::{GraphParams, read_g2o, write_g2o};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = common::temp_path("graph", ".g2o");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let result = read_g2o(&path);
    let _ = std::fs::remove_file(&path);
    let Ok((graph, fixed)) = result else {
        return;
    };
    let strict = common::strict();
    if strict {
        for &id in graph.ids() {
            let pose = graph.pose(id).expect("listed id has a pose");
            let q = pose.rotation.quaternion();
            assert!(
                pose.translation
                    .vector
                    .iter()
                    .chain(q.coords.iter())
                    .all(|v| v.is_finite()),
                "vertex {id} is not finite: {pose:?}"
            );
            assert!(
                (q.norm() - 1.0).abs() < 1e-6,
                "vertex {id}: quaternion {q:?} is not unit"
            );
        }
        for e in graph.edges() {
            let q = e.measurement.rotation.quaternion();
            assert!(
                (q.norm() - 1.0).abs() < 1e-6,
                "edge {} -> {}: quaternion {q:?} is not unit",
                e.from,
                e.to
            );
        }
        let out = common::temp_path("graph-out", ".g2o");
        write_g2o(&out, &graph, fixed).unwrap_or_else(|e| panic!("write_g2o failed: {e}"));
        let again = read_g2o(&out);
        let _ = std::fs::remove_file(&out);
        let (again, again_fixed) =
            again.unwrap_or_else(|e| panic!("write_g2o output does not read back: {e}"));
        assert_eq!(again.ids(), graph.ids());
        assert_eq!(again.edges().len(), graph.edges().len());
        assert_eq!(again_fixed, fixed);
    }
    let _ = graph.error();
    if graph.len() <= 32 && graph.edges().len() <= 64 {
        for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
            let params = GraphParams {
                optimizer,
                max_iterations: 5,
                fixed,
                ..GraphParams::default()
            };
            let mut g = graph.clone();
            let _ = g.optimize(&params);
        }
    }
});
