//! `kfmap bake`: a scan sequence with poses -> one memory-mappable `.kfmap` map.

use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::gravity::BakeGravity;
use kfmap_bake::mapping::ScanVerdict;
use kfmap_bake::pipeline::{
    BakeInput, BakeOutput, BakeReport, BakeStage, MappingSummary, TileOutput, bake,
    scan_check_sidecar,
};
use kfmap_bake::scan_range::ScanRange;
use kfmap_bake::tiling::{HaloCheck, TileSetSummary, merged_map_path};
use kfmap_geometry::gravity::GravityCorrection;
use kfmap_geometry::motion::DeskewMode;
use kfmap_geometry::options::ConfigFile;
use kfmap_graph::refine::RefineReport;
use kfmap_map::select::SURROUNDINGS;
use kfmap_map::tiles::{AUTOWARE_METADATA_FILE, INDEX_FILE, TileGeometry};
use serde_json::json;

use super::source_arg::SourceArgs;

/// Bake a map: choose keyframes from a scan sequence with poses, build each keyframe's
/// KD-tree and per-point covariances and the covisibility graph, and write one .kfmap
/// file that `kfmap serve` memory-maps and answers from at once.
///
/// The dataset is a folder of scans (*.pcd, *.ply, *.bin; in DIR/scans/ or DIR itself,
/// sorted by name) with poses T_map_sensor: --poses FILE (TUM or KITTI), else the first
/// of DIR/poses_gt.txt, poses.txt, traj.txt, poses_velo_kitti.txt. Scans named by frame
/// number (000042.bin) take pose 42; otherwise one pose per scan, in order. `kfmap
/// simulate` writes datasets in this layout.
///
/// Gravity: with an IMU log in the dataset (DIR/imu.csv or imu.txt, on the poses' clock;
/// TUM poses needed), each keyframe's accelerometer window joins the map's gravity pool
/// (motion-compensated, see `kfmap gravity --help`) and, with [map] align-gravity = true,
/// every pose is rotated by the estimated roll and pitch so the map has +Z up.
///
/// Without a pose file (or with --build-poses) the poses are built from the scans:
/// scan-to-local-map GICP odometry, keyframes, loop candidates by distance verified by
/// GICP, and a pose-graph optimization; a progress bar follows each stage and the
/// summary gives loops found/accepted, the graph error and, when a pose file exists,
/// the keyframe ATE against it.
///
/// Deskew (--deskew, [build.odometry] deskew): odometry moves each scan into its
/// mid-scan frame with the motion model's constant velocity (the last scan-to-scan
/// motion). "auto" (default) deskews scans that carry per-point times (PCD/PLY fields
/// time, t or timestamp; `kfmap simulate --raw`) and, lacking those, KITTI velodyne .bin
/// scans (x y z intensity) with times from each point's azimuth: a spinning sensor
/// sweeping at a constant rate ([build.odometry.sweep]: 0.1 s, clockwise from behind the
/// sensor, the stamp facing forward, as KITTI's HDL-64E). Other scans without times
/// (PCD, PLY, x y z .bin) are taken as deskewed already. "azimuth" times every scan
/// without per-point times that way, "per-point" only uses recorded times, "off" never
/// deskews. Without timestamps (a KITTI pose file) a sweep is taken to last one scan
/// interval. Measured: the simulated street driven raw at 5 Hz, times stripped, ATE
/// 0.316 m without deskew, 0.149 m with azimuth times (as with the recorded ones); on
/// KITTI 00 frames 0-5 no change (0.247 m; see docs/DESIGN.md#deskew). A spinning
/// sensor whose beams sit off their nominal elevations makes odometry drift in pitch:
/// bake.toml's [input] vertical-angle-offset-deg raises every return by that angle on
/// load (KITTI's HDL-64E: 0.205; docs/DESIGN.md#vertical-angle).
///
/// Built poses are then checked scan by scan ([build.check] in bake.toml): each scan is
/// registered onto the clouds of the 5 scans either side at their built poses; it fits
/// when that moves it at most 0.15 m (translation plus the arc of a point 10 m away)
/// and at least 50 % of its points have a partner within 1 m at an RMS distance of at
/// most 0.4 m (as tracking's health). A scan that does not fit is re-registered onto
/// the neighbours that do, from the pose they place it at, and moved there when it
/// fits; what still does not fit keeps its built pose and is listed: "poor scans" in
/// the summary (mapping.poor_scans with --json), and in the sidecar of
/// --trajectory-out.
///
/// Then every scan's pose is refined jointly ([build.refine], on by default): the scans'
/// points (0.1 m voxels) are cut into planes by adaptive voxels (2 m cubes split while not
/// planar), and all poses are solved together so that each plane, seen from several
/// scans, is as thin as the data allows (plane bundle adjustment; scan 0 stays). A
/// result that would move a scan more than 0.5 m plus 0.5 m per 100 m of path from
/// scan 0 (drift grows along an open drive), or make the map less consistent, is
/// refused and the built poses are kept. --json's mapping.refine gives the figures
/// before and after: the ATE of every scan when there is a pose file, the map's
/// consistency (mean thickness and spread of surfaces that at least 3 keyframes see as
/// planes; also for the pose file's poses), planes, steps, time, the largest move and
/// the scan nearest its allowance (tightest_move).
/// Measured: balm_os0 2.4 s on top of a 7-9 s bake; hku2_avia ATE 0.059 -> 0.027 m.
///
/// --refine-only --poses FILE refines the poses of FILE (e.g. an earlier bake's
/// --trajectory-out, or a reference you doubt) the same way on the scans and bakes at
/// the result; the dataset's own pose file, when there is one besides, gives the ATE
/// before and after.
///
/// --scans A..B bakes only scans A to B-1 of the sorted scan list (A.. and ..B leave an
/// end open); each keeps the pose it has in the whole dataset (by frame number, or by
/// its place in the pose file), and built poses start from scan A's frame.
///
/// Outputs beside the map:
///   --trajectory-out FILE.tum  the poses used (given, or built from the scans), one per
///       baked scan: t x y z qx qy qz qw with the dataset's times (its scan index where
///       the poses have none), in the map frame of the written map, i.e. after the
///       gravity levelling bake applies, so they match the keyframe poses in the map.
///       With built poses, FILE.tum.check.csv beside it gives each scan's check, one
///       line per baked scan: scan,t,verdict,inlier_ratio,rmse_m,shift_m,moved_m with
///       verdict fits, reregistered (moved moved_m by the check), poor (the pose may
///       be off: leave it out of evaluations) or unchecked; inlier_ratio and rmse_m
///       at the final pose, shift_m how far its neighbours pulled it as built;
///   --graph-out FILE.g2o  the keyframe pose graph of the built poses (VERTEX_SE3:QUAT
///       per graph keyframe, its id the scan's index in the dataset; EDGE_SE3:QUAT for
///       consecutive and loop edges with their information; FIX on the first), in the
///       same map frame; the vertices are the written poses (after the scan check and
///       the joint refinement), the edges the pose graph's measurements, so optimizing
///       the file alone returns to the pose graph's own optimum;
///       `kfmap optimize-graph` reads it. Only when the poses are built: with a given
///       pose file there is no graph and --graph-out is refused (pass --build-poses).
///
/// Every file is written beside its final name under a temporary name and renamed when
/// complete: an interrupted bake never leaves a partial map. Memory stays bounded by a
/// few keyframes at a time, whatever the map's size.
///
/// Example:
///   kfmap simulate --preset campus --seconds 60 --out /tmp/campus
///   kfmap bake --dataset /tmp/campus --out campus.kfmap
///   kfmap bake --dataset /tmp/campus --build-poses --scans 100..400 --out part.kfmap \
///       --trajectory-out part.tum --graph-out part.g2o
///   kfmap bake --dataset ../shared/data/kitti00 --out kitti.kfmap --threads 2
///   kfmap bake --dataset ../shared/data/balm_os0 --poses ../shared/data/balm_os0/poses.txt \
///       --refine-only --out balm.kfmap --trajectory-out balm_adjusted.tum
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    source: SourceArgs,
    /// Pose file (TUM or KITTI); default: found in the dataset folder (a bag needs it,
    /// one pose per cloud in order, or --build-poses).
    #[arg(long)]
    poses: Option<PathBuf>,
    /// Build the poses from the scans even when a pose file exists (it then serves as
    /// ground truth for the printed ATE).
    #[arg(long)]
    build_poses: bool,
    /// Refine the poses of --poses (e.g. an earlier bake's --trajectory-out) jointly on
    /// the scans ([build.refine]) and bake at the refined poses; the dataset's own pose
    /// file, if any, gives the ATE before and after.
    #[arg(long, requires = "poses", conflicts_with = "build_poses")]
    refine_only: bool,
    /// Output map file (conventionally *.kfmap); with --tile-size, the tile set's directory.
    #[arg(long)]
    out: PathBuf,
    /// Bake the map as square tiles of this edge on the map's x-y grid (metres): --out
    /// is then a directory of one .kfmap per tile (its core square's keyframes plus those
    /// within --halo; each keyframe built once, its bytes written to every tile holding
    /// it, no whole map unless --keep-merged), tiles.toml (the index `kfmap serve --tiles` and `kfmap gateway
    /// --tiles` read) and, for Autoware's map loader, each core square's points as
    /// <tile>.pcd with pointcloud_map_metadata.yaml. See docs/DESIGN.md#notes-tiles.
    #[arg(long, value_name = "METRES")]
    tile_size: Option<f64>,
    /// With --tile-size: keyframes this far outside a tile's square (per axis) also go
    /// into its file, so requests near a border find every keyframe the whole map would
    /// use. At least the localizer's keyframe reach; default 50 m. The cut checks it (the
    /// halo check): at sampled guesses near each core, the active set and the keyframes
    /// nearest by position that the tracker's explained share searches, from the tile
    /// against the whole map's, with a warning for each shortfall.
    #[arg(long, value_name = "METRES", requires = "tile_size")]
    halo: Option<f64>,
    /// With --tile-size: also write the whole map as DIR/merged.kfmap (the same keyframes'
    /// bytes; tests and comparisons serve it beside the tiles).
    #[arg(long, requires = "tile_size")]
    keep_merged: bool,
    /// Bake only scans A to B-1 of the dataset's sorted scan list (A.., ..B: open end).
    #[arg(long, value_name = "A..B")]
    scans: Option<ScanRange>,
    /// Write the poses used, one per baked scan, as TUM (map frame of the written map).
    #[arg(long, value_name = "FILE.tum")]
    trajectory_out: Option<PathBuf>,
    /// Write the keyframe pose graph as g2o (only when the poses are built).
    #[arg(long, value_name = "FILE.g2o")]
    graph_out: Option<PathBuf>,
    /// bake.toml with keyframe, covariance and map options (default: config/bake.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Worker threads; 0 means one per core.
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Replace an existing output file.
    #[arg(long)]
    force: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// Which scans odometry deskews: auto, per-point, azimuth or off (default: bake.toml's
    /// [build.odometry] deskew, "auto"; see above).
    #[arg(long, value_name = "MODE", value_parser = parse_deskew)]
    deskew: Option<DeskewMode>,
}

/// A `--deskew` value.
pub(super) fn parse_deskew(name: &str) -> Result<DeskewMode, String> {
    DeskewMode::parse(name).ok_or_else(|| format!("expected one of {}", DeskewMode::NAMES))
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = BakeConfig::load(args.config.as_deref())?;
    if let Some(mode) = args.deskew {
        config.build.odometry.deskew = mode;
    }
    let tiles = args.tile_size.map(|tile_size| TileGeometry {
        tile_size,
        halo: args.halo.unwrap_or(DEFAULT_HALO_M),
    });
    if let Some(geometry) = tiles {
        geometry.validate().map_err(|e| anyhow::anyhow!("--{e}"))?;
        if args.out.join(INDEX_FILE).exists() && !args.force {
            anyhow::bail!(
                "--out {} holds a tile set; pass --force to replace it",
                args.out.display()
            );
        }
        std::fs::create_dir_all(&args.out).with_context(|| {
            format!(
                "cannot create the tile set's directory {}",
                args.out.display()
            )
        })?;
    }
    let output = BakeOutput {
        map: args.out.clone(),
        trajectory: args.trajectory_out.clone(),
        graph: args.graph_out.clone(),
        tiles: tiles.map(|geometry| TileOutput {
            geometry,
            keep_merged: args.keep_merged,
        }),
    };
    let input = BakeInput {
        source: args.source.source(),
        poses: args.poses.clone(),
        build_poses: args.build_poses,
        scans: args.scans.unwrap_or(ScanRange::ALL),
        refine_only: args.refine_only,
    };
    refuse_existing_outputs(
        &output,
        input.builds_poses() || input.refine_only,
        args.force,
    )?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()
        .context("cannot start worker threads")?;
    let (report, stages) = bake_with_progress(&pool, &input, &config, &output, args.json)?;
    let tile_set = report.tiles.as_ref();
    let threads = pool.current_num_threads();
    if args.json {
        let mut summary = summary_json(&args, &output, &report, threads);
        summary["stage_seconds"] = stages.json();
        if let Some(t) = tile_set {
            summary["tiles"] = tiles_json(t);
        }
        println!("{summary}");
    } else {
        print_summary(&output, &report, threads);
        println!("  stages: {}", stages.line());
        if let Some(t) = tile_set {
            print_tiles(&args, t);
        }
    }
    Ok(())
}

/// The default halo of a tile set, metres: well past the localizer's keyframe reach.
const DEFAULT_HALO_M: f64 = 50.0;

/// `--json`'s part for a tile set.
fn tiles_json(t: &TileSetSummary) -> serde_json::Value {
    json!({
        "tile_size_m": t.index.tile_size, "halo_m": t.index.halo, "count": t.index.tiles.len(),
        "map_bytes": t.map_bytes, "place_grid_bytes": t.place_bytes,
        "worst_place_grid_share": t.worst_place_share,
        "finish_seconds": t.finish_seconds,
        "halo_check": {
            "sampled": t.halo_check.sampled,
            "agree": t.halo_check.active_agree,
            "surroundings_agree": t.halo_check.surroundings_agree,
            "surroundings": SURROUNDINGS,
        },
        "tiles": t.index.tiles.iter().map(|e| json!({
            "id": e.id, "file": e.file, "keyframes": e.keyframes,
            "core_keyframes": e.core_keyframes, "points": e.points, "bytes": e.bytes,
        })).collect::<Vec<_>>(),
    })
}

/// Prints the tile set's summary for people.
fn print_tiles(args: &Args, t: &TileSetSummary) {
    let i = &t.index;
    let written: u64 = i.tiles.iter().map(|e| e.keyframes).sum();
    println!(
        "  {} tiles of {} m (halo {} m) -> {}: {} keyframes written for {} ({:.2}x), {:.1} MB; tiles finished in {:.2} s",
        i.tiles.len(),
        i.tile_size,
        i.halo,
        args.out.display(),
        written,
        i.keyframes,
        written as f64 / i.keyframes.max(1) as f64,
        t.map_bytes as f64 / 1e6,
        t.finish_seconds
    );
    println!(
        "  place grids: {:.2} MB in all, at most {:.2} % of a tile's file; index {}, Autoware metadata {}",
        t.place_bytes as f64 / 1e6,
        100.0 * t.worst_place_share,
        INDEX_FILE,
        AUTOWARE_METADATA_FILE
    );
    let HaloCheck {
        sampled,
        active_agree,
        surroundings_agree,
    } = t.halo_check;
    println!(
        "  halo check: {active_agree} of {sampled} sampled guesses (core keyframes, and half the halo past them) select the same keyframes from their tile as from the whole map; {surroundings_agree} the same {SURROUNDINGS} nearest (the tracker's explained share)"
    );
    if active_agree < sampled {
        println!(
            "  warning: {} guesses near tile borders would be answered from other keyframes than the whole map would use; widen --halo",
            sampled - active_agree
        );
    }
    if surroundings_agree < sampled {
        println!(
            "  warning: at {} guesses near tile borders the tracker would measure how much of a scan the map explains without some of the {SURROUNDINGS} nearest keyframes the whole map has; widen --halo",
            sampled - surroundings_agree
        );
    }
    if args.keep_merged {
        println!(
            "  the whole map kept as {}",
            merged_map_path(&args.out).display()
        );
    }
}

/// An error when an output file exists and `--force` was not given (the trajectory's
/// scan check is written only when the poses are `built`).
fn refuse_existing_outputs(output: &BakeOutput, built: bool, force: bool) -> anyhow::Result<()> {
    let sidecar = output
        .trajectory
        .as_deref()
        .filter(|_| built)
        .map(scan_check_sidecar);
    let paths = [
        // A tile set's directory is checked for its index above.
        (
            "--out",
            Some(&output.map).filter(|_| output.tiles.is_none()),
        ),
        ("--trajectory-out", output.trajectory.as_ref()),
        ("--trajectory-out's scan check", sidecar.as_ref()),
        ("--graph-out", output.graph.as_ref()),
    ];
    for (flag, path) in paths {
        if let Some(path) = path.filter(|p| p.exists() && !force) {
            anyhow::bail!(
                "{flag} {} exists; pass --force to replace it",
                path.display()
            );
        }
    }
    Ok(())
}

/// Wall time spent in each stage of a bake, in the order the stages ran.
#[derive(Default)]
struct StageClock {
    spans: Vec<(BakeStage, std::time::Instant, f64)>,
}

impl StageClock {
    /// Notes that `stage` is running now.
    fn enter(&mut self, stage: BakeStage) {
        let now = std::time::Instant::now();
        if self.spans.last().is_some_and(|(s, _, _)| *s == stage) {
            return;
        }
        if let Some((_, since, seconds)) = self.spans.last_mut() {
            *seconds = (now - *since).as_secs_f64();
        }
        self.spans.push((stage, now, 0.0));
    }

    /// Closes the last stage.
    fn finish(&mut self) {
        if let Some((_, since, seconds)) = self.spans.last_mut() {
            *seconds = since.elapsed().as_secs_f64();
        }
    }

    /// Seconds per stage (a stage entered twice sums), for `--json`.
    fn json(&self) -> serde_json::Value {
        let mut out = serde_json::Map::new();
        for (stage, _, seconds) in &self.spans {
            let key = stage_name(*stage).to_string();
            let sum = out.get(&key).and_then(|v| v.as_f64()).unwrap_or(0.0) + seconds;
            out.insert(key, json!(sum));
        }
        serde_json::Value::Object(out)
    }

    /// One line for the text summary: "odometry 12.3 s, writing 4.0 s, ...".
    fn line(&self) -> String {
        let spans: Vec<String> = self
            .spans
            .iter()
            .map(|(stage, _, seconds)| format!("{} {seconds:.1} s", stage_name(*stage)))
            .collect();
        spans.join(", ")
    }
}

/// A stage's key in the summaries.
fn stage_name(stage: BakeStage) -> &'static str {
    match stage {
        BakeStage::Indexing => "indexing",
        BakeStage::Odometry => "odometry",
        BakeStage::Keyframes => "keyframes",
        BakeStage::Optimizing => "optimizing",
        BakeStage::Checking => "checking",
        BakeStage::Refining => "refining",
        BakeStage::Writing => "writing",
        BakeStage::Tiling => "tiling",
    }
}

/// Bakes on `pool`, showing the stage and progress (hidden with `json`), and times the stages.
fn bake_with_progress(
    pool: &rayon::ThreadPool,
    input: &BakeInput,
    config: &BakeConfig,
    output: &BakeOutput,
    json: bool,
) -> anyhow::Result<(BakeReport, StageClock)> {
    let mut clock = StageClock::default();
    let bar = if json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(0)
    };
    bar.set_style(
        ProgressStyle::with_template("baking [{bar:40}] {pos}/{len} keyframes, {msg}, eta {eta}")
            .expect("template")
            .progress_chars("=> "),
    );
    let started = std::time::Instant::now();
    let report = pool.install(|| {
        bake(input, config, output, |p| {
            clock.enter(p.stage);
            bar.set_length(p.total as u64);
            bar.set_position(p.done as u64);
            let rate = p.points_done as f64 / started.elapsed().as_secs_f64().max(1e-9);
            let clouds_per_second = p.done as f64 / started.elapsed().as_secs_f64().max(1e-9);
            bar.set_message(match p.stage {
                BakeStage::Indexing => {
                    format!("reading the bag's clouds, {clouds_per_second:.0} clouds/s")
                }
                BakeStage::Odometry => "odometry (scans)".to_string(),
                BakeStage::Keyframes => "pose-graph keyframes".to_string(),
                BakeStage::Optimizing => "loop closure and pose-graph optimization".to_string(),
                BakeStage::Checking => "checking every scan against its neighbours".to_string(),
                BakeStage::Refining => {
                    "refining every pose against the planes the scans share (solver steps)"
                        .to_string()
                }
                BakeStage::Writing => format!("writing keyframes, {:.2} M points/s", rate / 1e6),
                BakeStage::Tiling => {
                    "finishing tiles (place grids, indexes, Autoware clouds)".to_string()
                }
            });
        })
    })?;
    bar.finish_and_clear();
    clock.finish();
    Ok((report, clock))
}

/// `--json`'s summary of the bake.
fn summary_json(
    args: &Args,
    output: &BakeOutput,
    report: &BakeReport,
    threads: usize,
) -> serde_json::Value {
    let w = &report.written;
    json!({
        "map": args.out,
        "scans": report.scans.len(),
        "scan_range": [report.scans.start, report.scans.end],
        "dataset_scans": report.dataset_scans,
        "trajectory_out": output.trajectory,
        "scan_check_out": output.trajectory.as_deref().filter(|_| report.mapping.is_some())
            .map(scan_check_sidecar),
        "graph_out": output.graph.as_ref().zip(report.mapping.as_ref()).map(|(path, m)| json!({
            "path": path, "vertices": m.graph.len(), "edges": m.graph.edges().len(),
        })),
        "keyframes": w.keyframes,
        "points": w.points,
        "bytes": w.bytes,
        "seconds": report.seconds,
        "points_per_second": report.points_per_second(),
        "threads": threads,
        "gravity": report.gravity.as_ref().map(gravity_json),
        "mapping": report.mapping.as_ref().map(mapping_json),
    })
}

/// The gravity levelling's part of the JSON summary.
fn gravity_json(g: &BakeGravity) -> serde_json::Value {
    let c = g.correction.as_ref();
    json!({
        "imu": g.imu, "keyframes_with_samples": g.fill.with_samples,
        "compensated": g.fill.compensated, "skipped": g.fill.skipped, "applied": g.applied,
        "roll_deg": c.map(|c| c.roll_deg()), "pitch_deg": c.map(|c| c.pitch_deg()),
        "members": c.map(|c| c.estimate.health.members),
        "spread_deg": c.map(|c| c.estimate.health.spread_deg),
        "accel_bias_mps2": c.map(|c| c.estimate.accel_bias.mps2.as_slice().to_vec()),
        "bias_observable": c.map(|c| c.estimate.accel_bias.observable),
    })
}

/// The joint refinement's part of the JSON summary: before/after figures.
fn refine_json(r: &RefineReport, m: &MappingSummary) -> serde_json::Value {
    json!({
        "accepted": r.accepted(), "refused": r.refused, "seconds": r.seconds,
        "ate_scans_before_m": m.ate_scans_before_refine, "ate_scans_after_m": m.ate_scans,
        "consistency_before": r.consistency_before, "consistency_after": r.consistency_after,
        "consistency_reference": m.reference_consistency,
        "planes": r.planes, "observations": r.observations,
        "outer_iterations": r.outer_iterations, "iterations": r.iterations,
        "cost_first": [r.cost_first.0, r.cost_first.1], "cost_last": [r.cost_last.0, r.cost_last.1],
        "largest_move_m": r.largest_move, "moved_scans": r.moved_scans,
        "tightest_move": r.tightest_move,
        "weak_scans": r.weak_scans,
    })
}

/// The pose building's part of the JSON summary (poses built from the scans).
fn mapping_json(m: &MappingSummary) -> serde_json::Value {
    json!({
        "keyframes": m.keyframes, "loops_found": m.loops_found,
        "loops_accepted": m.loops_accepted(), "graph_error_initial": m.graph_error.0,
        "graph_error_final": m.graph_error.1, "ate_m": m.ate,
        "ate_odometry_m": m.ate_odometry, "ate_scans_m": m.ate_scans,
        "recovered_scans": m.recovered_scans, "odometry_poor_scans": m.odometry_poor_scans,
        "reregistered_scans": m.reregistered_scans, "poor_scans": m.poor_scans,
        "gyro_bias_rad_s": m.gyro_bias,
        "deskew": m.deskew.to_string(), "sweep_seconds": m.sweep_seconds,
        "refine": m.refine.as_ref().map(|r| refine_json(r, m)), "refined_only": m.refined_only,
        "loop_checks": m.loop_checks.iter().map(|c| json!({
            "older_scan": c.older_scan, "newer_scan": c.newer_scan,
            "accepted": c.accepted,
            "inlier_ratio": c.fitness.map(|f| f.inlier_ratio),
            "rmse_m": c.fitness.map(|f| f.rmse),
        })).collect::<Vec<_>>(),
    })
}

/// Prints the bake's summary for people.
fn print_summary(output: &BakeOutput, report: &BakeReport, threads: usize) {
    let w = &report.written;
    println!(
        "{}: {} keyframes from {} scans, {} points, {:.1} MB, {:.2} s ({:.2} M points/s, {} threads)",
        output.map.display(),
        w.keyframes,
        report.scans.len(),
        w.points,
        w.bytes as f64 / 1e6,
        report.seconds,
        report.points_per_second() / 1e6,
        threads
    );
    if let Some(m) = &report.mapping {
        print_mapping(m);
    }
    if let Some(g) = &report.gravity {
        print_gravity(g);
    }
    print_outputs(output, report);
}

fn print_outputs(output: &BakeOutput, report: &BakeReport) {
    if report.scans.len() != report.dataset_scans {
        println!(
            "  scans {}..{} of the dataset's {}",
            report.scans.start, report.scans.end, report.dataset_scans
        );
    }
    if let Some(path) = &output.trajectory {
        println!(
            "  trajectory: {} poses (map frame) -> {}",
            report.scans.len(),
            path.display()
        );
        if report.mapping.is_some() {
            println!(
                "  scan check: one line per scan -> {}",
                scan_check_sidecar(path).display()
            );
        }
    }
    if let (Some(path), Some(m)) = (&output.graph, &report.mapping) {
        println!(
            "  pose graph: {} vertices, {} edges ({} loops) -> {}",
            m.graph.len(),
            m.graph.edges().len(),
            m.loops_accepted(),
            path.display()
        );
    }
}

fn print_gravity(g: &BakeGravity) {
    match &g.correction {
        Some(c) => {
            print_levelled(g, c);
            println!("    {}", super::gravity::bias_line(&c.estimate.accel_bias));
        }
        None => println!(
            "  gravity from {}: only {} keyframes with samples, too few for an estimate; poses kept",
            g.imu.display(),
            g.fill.with_samples
        ),
    }
}

fn print_levelled(g: &BakeGravity, c: &GravityCorrection) {
    println!(
        "  gravity from {}: roll {:.3}°, pitch {:.3}° over {} keyframes (spread {:.3}°); {}",
        g.imu.display(),
        c.roll_deg(),
        c.pitch_deg(),
        c.estimate.health.members,
        c.estimate.health.spread_deg,
        if g.applied {
            "poses rotated to +Z up"
        } else {
            "poses kept ([map] align-gravity = false)"
        }
    );
}

fn print_mapping(m: &MappingSummary) {
    if m.refined_only {
        println!(
            "  given poses refined jointly (--refine-only; {} keyframes for the consistency figures)",
            m.keyframes
        );
        if let Some(ate) = m.ate_scans_before_refine {
            println!("  ATE of every scan against the dataset's pose file, as given: {ate:.3} m");
        }
        if let Some(r) = &m.refine {
            print_refine(r, m);
        }
        return;
    }
    println!(
        "  poses built from the scans: {} graph keyframes, loops {} found / {} accepted, graph error {:.3} -> {:.3}",
        m.keyframes,
        m.loops_found,
        m.loops_accepted(),
        m.graph_error.0,
        m.graph_error.1
    );
    match m.gyro_bias {
        Some([x, y, z]) => println!(
            "  odometry predicted rotation with the IMU's gyro (bias learned: [{x:.4}, {y:.4}, {z:.4}] rad/s)"
        ),
        None => println!("  odometry predicted with constant velocity (no IMU log used)"),
    }
    match (m.deskew, m.sweep_seconds) {
        (DeskewMode::Azimuth, Some(sweep)) => println!(
            "  deskew: scans without per-point times timed by azimuth over a {sweep} s sweep ([build.odometry.sweep])"
        ),
        (DeskewMode::Off, _) => println!("  deskew: off"),
        _ => println!("  deskew: scans with per-point times only"),
    }
    if !m.recovered_scans.is_empty() || !m.odometry_poor_scans.is_empty() {
        println!(
            "  odometry retried wider hypotheses for scans {:?}; no good registration for {:?}",
            m.recovered_scans, m.odometry_poor_scans
        );
    }
    print_scan_check(m);
    for c in &m.loop_checks {
        let verdict = if c.accepted { "accepted" } else { "rejected" };
        match c.fitness {
            Some(f) => println!(
                "  loop scan {} -> {}: {verdict}, {:.0} % paired, RMS {:.3} m",
                c.newer_scan,
                c.older_scan,
                f.inlier_ratio * 100.0,
                f.rmse
            ),
            None => println!(
                "  loop scan {} -> {}: rejected, registration failed",
                c.newer_scan, c.older_scan
            ),
        }
    }
    if let (Some(ate), Some(odometry)) = (m.ate, m.ate_odometry) {
        println!(
            "  keyframe ATE against the pose file: {:.3} m (odometry alone {:.3} m)",
            ate, odometry
        );
    }
    if let Some(ate) = m.ate_scans {
        println!("  ATE of every scan against the pose file: {ate:.3} m");
    }
    if let Some(r) = &m.refine {
        print_refine(r, m);
    }
}

/// The joint refinement in words: what it changed, or why it kept the poses.
fn print_refine(r: &RefineReport, m: &MappingSummary) {
    let (b, a) = (&r.consistency_before, &r.consistency_after);
    match &r.refused {
        None => println!(
            "  refined jointly in {:.1} s: {} planes, {} LM steps; surfaces seen by >= 3 keyframes ({}): thickness {:.1} -> {:.1} mm, spread {:.1} -> {:.1} mm; largest move {:.3} m",
            r.seconds,
            r.planes,
            r.iterations,
            a.surfaces,
            b.mean_thickness * 1e3,
            a.mean_thickness * 1e3,
            b.mean_spread * 1e3,
            a.mean_spread * 1e3,
            r.largest_move
        ),
        Some(why) => println!("  refinement refused, poses kept: {why}"),
    }
    if let Some(t) = &r.tightest_move {
        println!(
            "  nearest its move allowance: scan {}, {:.3} of {:.3} m (max-move plus \
             max-move-per-100m of its path from scan 0)",
            t.scan, t.moved, t.allowed
        );
    }
    if let (Some(before), Some(after)) = (m.ate_scans_before_refine, m.ate_scans) {
        println!("  ATE of every scan before / after the refinement: {before:.3} / {after:.3} m");
    }
    if let Some(c) = &m.reference_consistency {
        println!(
            "  the pose file's poses on the same surfaces: thickness {:.1} mm, spread {:.1} mm",
            c.mean_thickness * 1e3,
            c.mean_spread * 1e3
        );
    }
    if !r.weak_scans.is_empty() {
        println!(
            "  scans in fewer planes than [build.refine] min-planes-per-scan (held by odometry): {:?}",
            r.weak_scans
        );
    }
}

fn print_scan_check(m: &MappingSummary) {
    let checked = m
        .checks
        .iter()
        .filter(|c| c.verdict != ScanVerdict::Unchecked)
        .count();
    if checked == 0 {
        println!("  scans not checked against their neighbours ([build.check] enabled = false)");
        return;
    }
    println!(
        "  {checked} scans checked against their neighbours: re-registered {:?}; poor scans (pose may be off) {:?}",
        m.reregistered_scans, m.poor_scans
    );
}
