//! The table's pose-graph row: Gauss-Newton on parking-garage.g2o against GTSAM.

use std::path::Path;

use kfmap_graph::pose_graph::{GraphParams, read_g2o};

use super::anchors::GTSAM_PARKING_GARAGE_MS;
use super::fixtures::data_file;
use super::table::{Table, anchor};

/// Measures the pose-graph optimization on 1 and 2 threads (skipped without the file).
pub(super) fn measure(table: &mut Table, data: Option<&Path>) -> anyhow::Result<()> {
    table.stage("pose graph");
    let Some(path) = data_file(data, "g2o/parking-garage.g2o") else {
        table.skip("pose graph: needs g2o/parking-garage.g2o of the shared data");
        return Ok(());
    };
    let (graph, fixed) = read_g2o(&path)?;
    let params = GraphParams {
        fixed,
        ..GraphParams::default()
    };
    let label = format!("parking-garage.g2o, {} poses", graph.len());
    for threads in [1, 2] {
        let ms = table.time_ms(threads, || graph.clone().optimize(&params))?;
        table.push(
            "pose-graph optimization (Gauss-Newton)",
            &label,
            threads,
            ms,
            "ms",
        );
        table.anchored(anchor(
            "GTSAM 4.3",
            GTSAM_PARKING_GARAGE_MS,
            "tools/anchors/gtsam_pose_graph.py",
        ));
    }
    Ok(())
}
