//! `kfmap bench`: measurements that need whole processes or files too big for criterion.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_shared::archive::{MapWriter, OpenOptions, open_map};
use kfmap_shared::cloud::PointCloud;
use kfmap_shared::cov::{CovOptions, estimate_covariances};
use kfmap_shared::covis::CovisSnapshot;
use kfmap_shared::geometry::Pose;
use kfmap_shared::map::{Keyframe, KeyframeMap, KeyframeMapOptions};
use nalgebra::Vector3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde_json::json;

/// Benchmarks. With no subcommand: the system benchmarks in one table. `load`: cold
/// start of a baked map against rebuilding it. `ipc`: the map server's round trips and
/// throughput. `soak`: many clients for minutes.
///
/// `kfmap bench` (no subcommand) measures, each row naming its data and threads, with
/// the anchor's figure (small_gicp, GTSAM) beside it where one was measured on the same
/// data: per-point covariances, cov2cov per scan (approximate, exact on a new active
/// set, exact cached), GICP per scan pair, pose-graph optimization, cold start against
/// rebuild and bake throughput (`load`), IPC round trips of 1k/10k/100k points and
/// cov2cov throughput (`ipc`), and localization per scan with its error on the real
/// sequence balm_os0. Real data comes from ../shared/data (or $KFMAP_DATA_DIR); without
/// it, synthetic scans stand in and rows that need it are listed as skipped. About 75 s
/// on 2 cores; --quick (fewer repetitions, a 40-keyframe generated map) under a
/// minute, with noisier figures. --json: {"rows": [{name, data, threads, value, unit,
/// anchor: {tool, value, script} | null}], "skipped": [...]}.
///
/// `kfmap bench load` generates a map (default 500 keyframes x 40 000 points, about
/// 1.3 GB, under --dir), then measures: the time from starting a fresh `kfmap` process
/// to its first answered nearest-neighbour query on the memory-mapped file (median of
/// 5, page cache warm); the rebuild path (every tree and covariance from the points,
/// as a map without baked caches must do); bake throughput on 1 and 2 threads; and
/// query throughput on the archived map against the same map on the heap.
///
/// `kfmap bench ipc` bakes a small synthetic map (12 keyframes x 40 000 points),
/// starts `kfmap serve` on it as a child process and measures: echo round trips (no
/// compute) of 1k, 10k and 100k points, median and p99; cov2cov of a 10k-point scan
/// over IPC against the same call in process; and cov2cov throughput of one client
/// against four client processes at once (scans/s, p99). --spin makes server and
/// client poll instead of sleeping on events.
///
/// `kfmap bench soak` starts `kfmap serve` on the same synthetic map and --clients
/// client processes, each sending --rate requests per second for --seconds: scans of
/// 30k-120k points, mixed kinds (cov2cov, nearest, radius, localize, IMU windows,
/// status). It reports requests, failed (an error status), lost (no answer within
/// 30 s), busy (refused by the server's budgets), latency per kind, the server's RSS
/// after warm-up (the first tenth of the run, at most 60 s; in all and as heap, map-file
/// pages and shared memory), at the end and at most, and the
/// shared-memory files left after shutdown. --flood N adds an overload phase: a 1 Hz
/// client alone, then the same client while N processes send back to back. Exits 1
/// when any request failed or was lost, or shared memory was left behind.
///
/// Examples:
///   kfmap bench
///   kfmap bench --quick --json
///   kfmap bench load --dir /var/tmp/kfmap-bench
///   kfmap bench ipc --spin --json
///   kfmap bench soak --clients 8 --seconds 300 --json
///   kfmap bench soak --clients 2 --seconds 20 --flood 4
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// What to measure: load, ipc or soak (none: the whole table).
    #[arg(value_parser = ["load", "ipc", "soak"])]
    what: Option<String>,
    /// Table and ipc: fewer repetitions and a smaller generated map (a smoke run).
    #[arg(long)]
    quick: bool,
    /// soak: client processes.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=32))]
    clients: u32,
    /// soak: seconds the clients run.
    #[arg(long, default_value_t = 300.0)]
    seconds: f64,
    /// soak: requests per second of each client (0: back to back).
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// soak: processes flooding the server in the overload phase (0: no such phase).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=16))]
    flood: u32,
    /// Internal (soak): run as one soak client of the server under this prefix.
    #[arg(long, hide = true)]
    client_of: Option<String>,
    /// Internal (soak): the client's seed.
    #[arg(long, hide = true, default_value_t = 1)]
    seed: u64,
    /// ipc: server and client poll instead of waiting on events.
    #[arg(long)]
    spin: bool,
    /// Internal (ipc): run as one throughput client of the server under this prefix.
    #[arg(long, hide = true)]
    worker_of: Option<String>,
    /// Keyframes of the generated map.
    #[arg(long, default_value_t = 500)]
    keyframes: usize,
    /// Points per keyframe.
    #[arg(long, default_value_t = 40_000)]
    points: usize,
    /// Folder for the generated map (default: the system temp folder).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Keep the generated map file.
    #[arg(long)]
    keep: bool,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
    /// Internal: open MAP, answer one query, print the microseconds since start.
    #[arg(long, hide = true)]
    probe: Option<PathBuf>,
}

/// A synthetic scan: ground, two walls and scattered posts around the keyframe.
pub(super) fn synthetic_cloud(seed: u64, n: usize) -> PointCloud {
    let mut rng = SmallRng::seed_from_u64(seed);
    let points = (0..n)
        .map(|i| match i % 10 {
            0..4 => [
                rng.random_range(-30.0..30.0),
                rng.random_range(-30.0..30.0),
                rng.random_range(-0.02..0.02),
            ],
            4..7 => [
                rng.random_range(-30.0..30.0),
                if i % 2 == 0 { -8.0 } else { 9.0 },
                rng.random_range(0.0..4.0),
            ],
            _ => {
                let post = rng.random_range(0..40) as f32;
                [
                    post * 1.5 - 30.0,
                    (post * 7.3) % 16.0 - 8.0 + rng.random_range(-0.1..0.1),
                    rng.random_range(0.0..3.0),
                ]
            }
        })
        .collect();
    PointCloud::from_points(points)
}

pub(super) fn keyframe_pose(i: usize) -> Pose {
    Pose::new(
        Vector3::new(2.0 * i as f64, 0.0, 0.0),
        Vector3::new(0.0, 0.0, 0.05 * (i % 7) as f64),
    )
}

/// Builds and writes `count` synthetic keyframes; returns seconds spent (generation of
/// the raw points excluded).
fn bake_synthetic(
    path: &Path,
    count: usize,
    points: usize,
    bar: &ProgressBar,
) -> anyhow::Result<f64> {
    let options = KeyframeMapOptions::default();
    let mut writer = MapWriter::create(path, &options)?;
    let chunk = 2 * rayon::current_num_threads();
    let mut seconds = 0.0;
    for start in (0..count).step_by(chunk) {
        let clouds: Vec<PointCloud> = (start..(start + chunk).min(count))
            .into_par_iter()
            .map(|i| synthetic_cloud(i as u64, points))
            .collect();
        let started = Instant::now();
        let keyframes: Vec<Keyframe> = clouds
            .into_par_iter()
            .enumerate()
            .map(|(j, c)| {
                let i = start + j;
                Keyframe::build(i as u64, keyframe_pose(i), i as f64, c, &options.covariance)
            })
            .collect::<Result<_, _>>()?;
        for k in &keyframes {
            writer.write_keyframe(k)?;
            bar.inc(1);
        }
        seconds += started.elapsed().as_secs_f64();
    }
    let started = Instant::now();
    writer.finish(count as u64, &CovisSnapshot::default(), &[])?;
    Ok(seconds + started.elapsed().as_secs_f64())
}

fn probe(path: &Path, started: Instant) -> anyhow::Result<()> {
    let mut map = open_map(path, OpenOptions::default())?.map;
    let at = keyframe_pose(map.len() / 2);
    let active = map.activate(&at)?;
    let hit = active
        .nearest_one(&[at.translation.x as f32, 0.5, 0.0])
        .context("no answer")?;
    println!(
        "{}",
        json!({"micros": started.elapsed().as_micros() as u64, "dist_sq": hit.dist_sq})
    );
    Ok(())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    kfmap_service::server::percentile(&v, 0.5)
}

/// Nearest-neighbour queries around 20 poses: seconds for all of them.
fn query_pass(map: &mut KeyframeMap, queries: &[[f32; 3]]) -> anyhow::Result<(f64, f64)> {
    let mut seconds = 0.0;
    let mut checksum = 0.0;
    for p in 0..20 {
        let at = keyframe_pose(p * map.len() / 20);
        let active = map.activate(&at)?;
        let x = at.translation.x as f32;
        let started = Instant::now();
        for q in queries {
            checksum += active
                .nearest_one(&[q[0] + x, q[1], q[2]])
                .map_or(0.0, |h| h.dist_sq as f64);
        }
        seconds += started.elapsed().as_secs_f64();
    }
    Ok((seconds, checksum))
}

/// Runs the subcommand.
pub fn run(args: Args, process_start: Instant) -> anyhow::Result<()> {
    if let Some(path) = &args.probe {
        return probe(path, process_start);
    }
    if let Some(prefix) = &args.worker_of {
        return super::bench_ipc::worker(prefix, args.seconds);
    }
    if let Some(prefix) = &args.client_of {
        let plan = super::bench_soak::ClientPlan {
            rate_hz: args.rate,
            seconds: args.seconds,
            seed: args.seed,
        };
        let report = super::bench_soak::run_client(prefix, plan)?;
        println!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    if args.keyframes < 2 || args.points < 100 {
        bail!("--keyframes must be at least 2 and --points at least 100");
    }
    let dir = args.dir.clone().unwrap_or_else(std::env::temp_dir);
    std::fs::create_dir_all(&dir).with_context(|| dir.display().to_string())?;
    let Some(what) = args.what.as_deref() else {
        return super::bench_table::run(args.quick, args.json, &dir);
    };
    if what == "soak" {
        if !(args.seconds.is_finite() && args.seconds >= 1.0) {
            bail!("--seconds must be at least 1");
        }
        if !(args.rate.is_finite() && (0.0..=1000.0).contains(&args.rate)) {
            bail!("--rate must be within 0 (back to back) to 1000 requests per second");
        }
        let map = dir.join(format!("kfmap-bench-soak-{}.kfmap", std::process::id()));
        bake_synthetic(&map, 12, 40_000, &ProgressBar::hidden())?;
        let passed = super::bench_soak::run(
            &map,
            args.clients as usize,
            args.seconds,
            args.rate,
            args.flood as usize,
            args.json,
        );
        let _ = std::fs::remove_file(&map);
        if !passed? {
            bail!(
                "the soak failed: requests failed or were lost, or shared memory was left behind"
            );
        }
        return Ok(());
    }
    if what == "ipc" {
        return super::bench_ipc::run(&dir, args.spin, args.quick, args.json, |map| {
            bake_synthetic(map, 12, 40_000, &ProgressBar::hidden()).map(|_| ())
        });
    }
    let path = dir.join(format!("kfmap-bench-{}.kfmap", std::process::id()));
    let small = dir.join(format!("kfmap-bench-{}-small.kfmap", std::process::id()));
    let result = measure(&args, &path, &small);
    let _ = std::fs::remove_file(&small);
    if !args.keep {
        let _ = std::fs::remove_file(&path);
    }
    result
}

fn measure(args: &Args, path: &Path, small: &Path) -> anyhow::Result<()> {
    let bar = if args.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(args.keyframes as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} keyframes, eta {eta}")?
            .progress_chars("=> "),
    );
    bar.set_message("generating the map");
    let bake_seconds = bake_synthetic(path, args.keyframes, args.points, &bar)?;
    let bytes = std::fs::metadata(path)?.len();
    let total_points = (args.keyframes * args.points) as f64;

    // Bake throughput on 1 and 2 threads, on a tenth of the keyframes (at least 4).
    let sample = (args.keyframes / 10).max(4).min(args.keyframes);
    let mut throughput = Vec::new();
    for threads in [1, 2] {
        bar.set_message(format!("baking on {threads} thread(s)"));
        bar.set_length(sample as u64);
        bar.set_position(0);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        let s = pool.install(|| bake_synthetic(small, sample, args.points, &bar))?;
        throughput.push((sample * args.points) as f64 / s);
    }

    bar.set_message("cold starts");
    let exe = std::env::current_exe()?;
    let mut wall = Vec::new();
    let mut inside = Vec::new();
    for _ in 0..5 {
        let started = Instant::now();
        let out = Command::new(&exe)
            .args(["bench", "load", "--probe"])
            .arg(path)
            .output()?;
        wall.push(started.elapsed().as_secs_f64() * 1e3);
        if !out.status.success() {
            bail!("probe failed: {}", String::from_utf8_lossy(&out.stderr));
        }
        let v: serde_json::Value = serde_json::from_slice(&out.stdout)?;
        inside.push(v["micros"].as_f64().unwrap_or(f64::NAN) / 1e3);
    }
    let cold_ms = median(wall);
    let cold_inside_ms = median(inside);

    bar.set_message("rebuild path");
    let opened = open_map(path, OpenOptions::default())?;
    let cov = CovOptions::default();
    let started = Instant::now();
    let rebuilt: Vec<Keyframe> = opened
        .map
        .keyframes()
        .collect::<Vec<_>>()
        .par_iter()
        .map(|k| {
            let points = k.view()?.points.to_vec();
            let covariances = estimate_covariances(&points, &cov).values;
            let cloud = PointCloud::from_points(points);
            Ok(Keyframe::from_parts(
                k.id,
                k.pose,
                k.timestamp,
                cloud,
                covariances,
            )?)
        })
        .collect::<anyhow::Result<_>>()?;
    let rebuild_ms = started.elapsed().as_secs_f64() * 1e3;
    let mut heap = KeyframeMap::new(KeyframeMapOptions {
        approximate_cov: true,
        ..KeyframeMapOptions::default()
    })?;
    for k in rebuilt {
        heap.insert_keyframe(k)?;
    }
    bar.finish_and_clear();

    let mut rng = SmallRng::seed_from_u64(7);
    let queries: Vec<[f32; 3]> = (0..20_000)
        .map(|_| {
            [
                rng.random_range(-20.0..20.0),
                rng.random_range(-10.0..10.0),
                rng.random_range(-0.5..3.0),
            ]
        })
        .collect();
    let mut archived = opened.map;
    query_pass(&mut archived, &queries)?; // Pages in the active keyframes.
    // Alternating passes, best of three each: the two layouts see the same machine noise.
    let (mut archived_s, mut heap_s) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..3 {
        let (a, a_sum) = query_pass(&mut archived, &queries)?;
        let (h, h_sum) = query_pass(&mut heap, &queries)?;
        if a_sum != h_sum {
            bail!("archived and heap maps answered differently ({a_sum} vs {h_sum})");
        }
        archived_s = archived_s.min(a);
        heap_s = heap_s.min(h);
    }
    let queries_total = 20.0 * queries.len() as f64;
    let figures = json!({
        "keyframes": args.keyframes,
        "points": total_points,
        "bytes": bytes,
        "generate_bake_seconds": bake_seconds,
        "bake_points_per_second_1_thread": throughput[0],
        "bake_points_per_second_2_threads": throughput[1],
        "cold_start_ms": cold_ms,
        "cold_start_in_process_ms": cold_inside_ms,
        "rebuild_ms": rebuild_ms,
        "rebuild_over_cold_start": rebuild_ms / cold_ms,
        "threads": rayon::current_num_threads(),
        "archived_nn_per_second": queries_total / archived_s,
        "heap_nn_per_second": queries_total / heap_s,
        "archived_over_heap_time": archived_s / heap_s,
    });
    if args.json {
        println!("{figures}");
        return Ok(());
    }
    println!(
        "map: {} keyframes x {} points = {:.1} M points, {:.2} GB ({})",
        args.keyframes,
        args.points,
        total_points / 1e6,
        bytes as f64 / 1e9,
        path.display()
    );
    println!(
        "bake (trees + covariances + write): {:.2} M points/s on 1 thread, {:.2} M points/s on 2 threads",
        throughput[0] / 1e6,
        throughput[1] / 1e6
    );
    println!(
        "cold start, process start to first NN answer: {cold_ms:.1} ms (median of 5; {cold_inside_ms:.1} ms inside the process)"
    );
    println!(
        "rebuild path (all trees and covariances, {} threads): {rebuild_ms:.0} ms = {:.0}x the cold start",
        rayon::current_num_threads(),
        rebuild_ms / cold_ms
    );
    println!(
        "NN queries: archived {:.2} M/s, heap {:.2} M/s (archived takes {:.1} % of the heap time)",
        queries_total / archived_s / 1e6,
        queries_total / heap_s / 1e6,
        100.0 * archived_s / heap_s
    );
    Ok(())
}
