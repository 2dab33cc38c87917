//! The table's KD-tree rows: the tree every answer searches, with 1-NN and k = 20
//! queries in scan and Morton order, and its build.

use std::num::NonZeroUsize;
use std::path::Path;

use kfmap_geometry::geometry::{to_point, transform_point};
use kfmap_geometry::io::read_trajectory;
use kfmap_geometry::spatial::{build_tree, morton_order};

use super::anchors::SMALL_GICP_KNN;
use super::fixtures::{data_file, read, synthetic_cloud};
use super::table::{Table, anchor};

/// Measures the KD-tree rows on KITTI 00 frames 0 and 1 (synthetic scans without them).
pub(super) fn measure(table: &mut Table, data: Option<&Path>) -> anyhow::Result<()> {
    table.stage("KD-tree");
    let kitti = data_file(data, "kitti00");
    let (target, queries) = match &kitti {
        Some(dir) => {
            let poses = read_trajectory(&dir.join("poses_velo_kitti.txt"))?.poses;
            let relative = poses[0].inverse() * poses[1];
            let moved = read(&dir.join("000001.bin"))?
                .points
                .iter()
                .map(|p| to_point(&transform_point(&relative, p)))
                .collect();
            (read(&dir.join("000000.bin"))?.points, moved)
        }
        None => (
            synthetic_cloud(1, 120_000).points,
            synthetic_cloud(2, 120_000).points,
        ),
    };
    let label = format!(
        "{}: {} queries against {} points",
        if kitti.is_some() {
            "KITTI 00 frame 1 into frame 0"
        } else {
            "synthetic scans"
        },
        queries.len(),
        target.len()
    );
    let sorted: Vec<[f32; 3]> = morton_order(&queries)
        .iter()
        .map(|&i| queries[i as usize])
        .collect();
    let tree = build_tree(&target)?;
    let tree = tree.view();
    let k20 = NonZeroUsize::new(20).expect("k");
    let knn_anchor = |i: usize| {
        let script = "tools/anchors/small_gicp_knn.py";
        kitti
            .as_ref()
            .and_then(|_| anchor("small_gicp", SMALL_GICP_KNN[i], script))
    };
    for (order, qs, column) in [("scan", &queries, 0), ("Morton", &sorted, 2)] {
        let ms = table.time_ms(1, || qs.iter().map(|q| tree.nearest_one(q).1).sum::<f32>())?;
        table.push(&format!("KD-tree 1-NN, {order} order"), &label, 1, ms, "ms");
        table.anchored(knn_anchor(column));
        let ms = table.time_ms(1, || {
            qs.iter()
                .map(|q| tree.nearest_n(q, k20).len())
                .sum::<usize>()
        })?;
        table.push(
            &format!("KD-tree k = 20, {order} order"),
            &label,
            1,
            ms,
            "ms",
        );
        table.anchored(knn_anchor(column + 1));
    }
    let ms = table.time_ms(1, || build_tree(&target).map(|t| t.len()))?;
    table.push("KD-tree build", &label, 1, ms, "ms");
    table.anchored(knn_anchor(4));

    Ok(())
}
