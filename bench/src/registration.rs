//! The table's GICP rows: one scan pair registered from raw clouds, and aligned once
//! both are preprocessed.

use std::path::Path;

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::{PreparedCloud, RegistrationParams, align, register};

use super::anchors::{SMALL_GICP_ALIGN, SMALL_GICP_REGISTER};
use super::fixtures::{data_file, read, synthetic_cloud};
use super::table::{Table, anchor};

/// Measures the GICP rows on small_gicp's scan pair (two synthetic scans without it),
/// on 1 and 2 threads.
pub(super) fn measure(table: &mut Table, data: Option<&Path>) -> anyhow::Result<()> {
    table.stage("GICP per scan pair");
    let real = data_file(data, "small_gicp");
    let (target, source, label) = match &real {
        Some(dir) => (
            read(&dir.join("target.ply"))?,
            read(&dir.join("source.ply"))?,
            "small_gicp/{target,source}.ply".to_string(),
        ),
        None => (
            synthetic_cloud(1, 64_000),
            synthetic_cloud(2, 64_000),
            "two synthetic scans of one site".to_string(),
        ),
    };
    let params = RegistrationParams::default();
    let identity = Pose::identity();
    for threads in [1, 2] {
        let ms = table.time_ms(threads, || register(&target, &source, &identity, &params))?;
        table.push(
            "GICP from raw clouds (voxels, covariances, trees, solve)",
            &label,
            threads,
            ms,
            "ms",
        );
        let script = "tools/anchors/small_gicp_reg.py";
        table.anchored(
            real.as_ref()
                .and_then(|_| anchor("small_gicp", SMALL_GICP_REGISTER[threads - 1], script)),
        );
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        let (t, s) = pool.install(|| {
            rayon::join(
                || PreparedCloud::new(&target, &params, "target"),
                || PreparedCloud::new(&source, &params, "source"),
            )
        });
        let (t, s) = (t?, s?);
        let ms = table.time_ms(threads, || align(&t, &s, &identity, &params))?;
        table.push("GICP on preprocessed clouds", &label, threads, ms, "ms");
        table.anchored(
            real.as_ref()
                .and_then(|_| anchor("small_gicp", SMALL_GICP_ALIGN[threads - 1], script)),
        );
    }
    Ok(())
}
