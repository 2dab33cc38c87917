//! The table's per-scan kernels on one real scan: covariances, then the voxel grid
//! every scan pays first.

use std::path::Path;

use kfmap_geometry::cov::{CovOptions, estimate_covariances};

use super::anchors::{SMALL_GICP_COV, SMALL_GICP_COV_SCRIPT, SMALL_GICP_VOXEL};
use super::fixtures::{data_file, read, synthetic_cloud};
use super::table::{Table, anchor};

/// Measures the covariance and voxel-grid rows, on 1 and 2 threads.
pub(super) fn measure(table: &mut Table, data: Option<&Path>) -> anyhow::Result<()> {
    table.stage("covariances and voxel grid");
    let real = data_file(data, "small_gicp/target.ply");
    let (cloud, name) = match &real {
        Some(p) => (read(p)?, "small_gicp/target.ply"),
        None => (synthetic_cloud(1, 64_000), "synthetic scan"),
    };
    let label = format!("{name}, {} points", cloud.len());
    let options = CovOptions::default();
    for threads in [1, 2] {
        let ms = table.time_ms(threads, || estimate_covariances(&cloud.points, &options))?;
        table.push(
            "covariances, k = 20 (index included)",
            &label,
            threads,
            ms,
            "ms",
        );
        table.anchored(real.as_ref().and_then(|_| {
            anchor(
                "small_gicp",
                SMALL_GICP_COV[threads - 1],
                SMALL_GICP_COV_SCRIPT,
            )
        }));
    }
    for threads in [1, 2] {
        let ms = table.time_ms(threads, || cloud.voxel_downsample(0.25))?;
        table.push("voxel grid, 0.25 m", &label, threads, ms, "ms");
        table.anchored(real.as_ref().and_then(|_| {
            anchor(
                "small_gicp",
                SMALL_GICP_VOXEL[threads - 1],
                SMALL_GICP_COV_SCRIPT,
            )
        }));
    }
    Ok(())
}
