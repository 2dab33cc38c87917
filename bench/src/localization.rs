//! The table's localization rows on real data: balm_os0, a map of scans 0-115 at their
//! reference poses, scans 116-176 tracked against it by `kfmap localize` over IPC, as
//! tests/integration/health.rs checks, and the same scans relocalized with no guess by
//! `kfmap relocalize` on the same server, side by side (the target: a relocalization
//! costs at most two tracking steps).

use std::ffi::OsStr;
use std::path::Path;

use anyhow::Context;

use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::find_scans;
use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake};
use kfmap_bake::scan_range::ScanRange;
use kfmap_bake::source::Source;
use kfmap_geometry::percentile::percentile;

use super::anchors::SMALL_GICP_LOCALIZE;
use super::fixtures::data_file;
use super::table::{Table, anchor};
use crate::json_number;
use crate::server_child::{ServerChild, run_client, run_localize};
use kfmap_geometry::percentile::p99_label;

/// Bakes the map in `dir`, serves it from a child process and measures the rows
/// (skipped without balm_os0).
pub(super) fn measure(table: &mut Table, data: Option<&Path>, dir: &Path) -> anyhow::Result<()> {
    table.stage("localization on real data (balm_os0)");
    let Some(balm) = data_file(data, "balm_os0") else {
        table.skip("localization on real data: needs balm_os0 of the shared data");
        return Ok(());
    };
    let (v, relocalized) = localize_balm(&balm, dir)?;
    let label = "balm_os0: map of scans 0-115, scans 116-176 tracked";
    let script = "tools/anchors/small_gicp_localize.py --motion-model";
    table.push(
        "localization per scan, client-side GICP over IPC, median",
        label,
        2,
        json_number(&v["p50_ms"]),
        "ms",
    );
    table.anchored(anchor(
        "small_gicp (in process)",
        SMALL_GICP_LOCALIZE[0],
        script,
    ));
    let scans = v["scans"].as_u64().unwrap_or(0) as usize;
    table.push(
        &format!(
            "localization per scan, client-side GICP over IPC, {}",
            p99_label(scans)
        ),
        label,
        2,
        json_number(&v["p99_ms"]),
        "ms",
    );
    table.anchored(anchor(
        "small_gicp (in process)",
        SMALL_GICP_LOCALIZE[1],
        script,
    ));
    table.push(
        "localization error vs reference poses, RMS",
        label,
        2,
        json_number(&v["rms_error_m"]),
        "m",
    );
    table.anchored(anchor("small_gicp", SMALL_GICP_LOCALIZE[2], script));
    let label = "balm_os0: map of scans 0-115, scans 116-176 relocalized with no guess";
    let mut latencies: Vec<f64> = relocalized.iter().map(|r| r.latency_ms).collect();
    latencies.sort_by(f64::total_cmp);
    let mut server: Vec<f64> = relocalized.iter().map(|r| r.server_ms).collect();
    server.sort_by(f64::total_cmp);
    let median = percentile(&latencies, 0.5);
    table.push(
        "relocalization per scan over IPC (kfmap relocalize), median",
        label,
        2,
        median,
        "ms",
    );
    table.push(
        &format!(
            "relocalization per scan over IPC (kfmap relocalize), {}",
            p99_label(latencies.len())
        ),
        label,
        2,
        percentile(&latencies, 0.99),
        "ms",
    );
    table.push(
        "relocalization per scan, server time, median",
        label,
        2,
        percentile(&server, 0.5),
        "ms",
    );
    table.push(
        "relocalization median over the tracking step's median (same run)",
        label,
        2,
        median / json_number(&v["p50_ms"]),
        "x",
    );
    Ok(())
}

/// One scan's answer of `kfmap relocalize --json`: its latencies.
#[derive(serde::Deserialize)]
struct Relocalized {
    latency_ms: f64,
    server_ms: f64,
}

/// Bakes scans 0-115 of balm_os0 into a map in `dir`, serves it, tracks scans 116-176
/// with `kfmap localize --json` (its summary), then relocalizes each of them with
/// `kfmap relocalize --json` on the same server (one answer per scan).
fn localize_balm(balm: &Path, dir: &Path) -> anyhow::Result<(serde_json::Value, Vec<Relocalized>)> {
    let map = dir.join(format!("kfmap-bench-balm-{}.kfmap", std::process::id()));
    let input = BakeInput {
        scans: ScanRange {
            start: 0,
            end: Some(116),
        },
        ..BakeInput::dataset(balm)
    };
    bake(
        &input,
        &BakeConfig::default(),
        &BakeOutput::map(&map),
        |_| {},
    )?;
    let id = std::process::id();
    let served = ServerChild::start(
        &map,
        &format!("benchbalm{id}"),
        &format!("kfbalm{id}_"),
        &[],
    );
    let _ = std::fs::remove_file(&map); // The server holds it mapped.
    let server = served?;
    let args = [
        "--scans",
        "116..177",
        "--initial-from-ground-truth",
        "--json",
    ];
    let source = Source::Folder(balm.to_path_buf());
    let tracked = serde_json::from_str(&run_localize(&server, &source, &args.map(OsStr::new))?)?;
    let scans = find_scans(balm)?;
    let revisit = scans
        .get(116..177)
        .context("balm_os0 has fewer than 177 scans")?;
    let mut args: Vec<std::ffi::OsString> = vec!["--json".into()];
    args.extend(revisit.iter().map(|p| p.as_os_str().to_os_string()));
    let printed = run_client(&server, "relocalize", &args)?;
    let relocalized = printed
        .lines()
        .map(serde_json::from_str)
        .collect::<Result<Vec<Relocalized>, _>>()?;
    Ok((tracked, relocalized))
}
