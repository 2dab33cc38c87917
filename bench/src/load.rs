//! `kfmap bench load`: cold start of a baked map (a fresh process to its first answer)
//! against rebuilding every tree and covariance, bake throughput, and queries on the
//! memory-mapped map against the same map on the heap. Also the table's rows of it.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::percentile::percentile;
use kfmap_map::archive::{OpenOptions, open_map};
use kfmap_map::map::{Keyframe, KeyframeMap, KeyframeMapOptions};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde_json::json;

use super::child::child_bench;
use super::fixtures::{bake_synthetic, keyframe_pose};
use super::table::Table;
use crate::json_number;

/// The generated map's size.
#[derive(Debug, Clone, Copy)]
pub(super) struct MapSize {
    /// Keyframes of the map.
    pub keyframes: usize,
    /// Points per keyframe.
    pub points: usize,
}

/// Runs `kfmap bench load`: generates the map in `dir` (kept with `keep`), measures and
/// prints.
pub(super) fn run(dir: &Path, size: MapSize, keep: bool, json_out: bool) -> anyhow::Result<()> {
    let path = dir.join(format!("kfmap-bench-{}.kfmap", std::process::id()));
    let small = dir.join(format!("kfmap-bench-{}-small.kfmap", std::process::id()));
    let result = measure(size, &path, &small, json_out);
    let _ = std::fs::remove_file(&small);
    if !keep {
        let _ = std::fs::remove_file(&path);
    }
    result
}

/// The hidden `kfmap bench probe MAP`: opens the map, answers one query and prints the
/// microseconds since the process started.
pub(super) fn probe(path: &Path, started: Instant) -> anyhow::Result<()> {
    let mut map = open_map(path, OpenOptions::default())?.map;
    // At the middle keyframe, half a metre off its origin (any map: a tile too).
    let at = map
        .keyframes()
        .nth(map.len() / 2)
        .context("the map has no keyframe")?
        .pose;
    let active = map.activate(&at)?;
    let t = at.translation.vector;
    let hit = active
        .nearest_one(&[t.x as f32, t.y as f32 + 0.5, t.z as f32])
        .context("no answer")?;
    println!(
        "{}",
        json!({"micros": started.elapsed().as_micros() as u64, "dist_sq": hit.dist_sq})
    );
    Ok(())
}

/// Median of samples.
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    percentile(&v, 0.5)
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

/// The figures of `kfmap bench load`.
struct LoadFigures {
    size: MapSize,
    bytes: u64,
    generate_bake_seconds: f64,
    /// Bake throughput on 1 and 2 threads, points per second.
    bake_points_per_second: [f64; 2],
    /// Median milliseconds from process start to the first answer, outside and inside
    /// the probe process.
    cold_ms: f64,
    cold_inside_ms: f64,
    rebuild_ms: f64,
    /// Queries of one pass over the 20 poses.
    queries_total: f64,
    /// Best seconds of a pass on the archived and on the heap map.
    archived_s: f64,
    heap_s: f64,
}

/// Generates the map at `path` (and the smaller one at `small`), measures it and prints
/// the figures.
fn measure(size: MapSize, path: &Path, small: &Path, json_out: bool) -> anyhow::Result<()> {
    let bar = progress_bar(json_out, size.keyframes)?;
    bar.set_message("generating the map");
    let generate_bake_seconds = bake_synthetic(path, size.keyframes, size.points, &bar)?;
    let bytes = std::fs::metadata(path)?.len();
    let bake_points_per_second = bake_throughput(small, size, &bar)?;
    bar.set_message("cold starts");
    let (cold_ms, cold_inside_ms) = cold_starts(path)?;
    bar.set_message("rebuild path");
    let opened = open_map(path, OpenOptions::default())?;
    let (rebuild_ms, mut heap) = rebuild_on_heap(&opened.map)?;
    bar.finish_and_clear();
    let queries = random_queries();
    let (archived_s, heap_s) = best_query_passes(opened.map, &mut heap, &queries)?;
    let figures = LoadFigures {
        size,
        bytes,
        generate_bake_seconds,
        bake_points_per_second,
        cold_ms,
        cold_inside_ms,
        rebuild_ms,
        queries_total: 20.0 * queries.len() as f64,
        archived_s,
        heap_s,
    };
    if json_out {
        println!("{}", figures.json());
    } else {
        figures.print(path);
    }
    Ok(())
}

/// The progress bar over the generated keyframes (hidden for JSON).
fn progress_bar(json_out: bool, keyframes: usize) -> anyhow::Result<ProgressBar> {
    let bar = if json_out {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(keyframes as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} keyframes, eta {eta}")?
            .progress_chars("=> "),
    );
    Ok(bar)
}

/// Bake throughput on 1 and 2 threads, on a tenth of the keyframes (at least 4) written
/// to `small`: points per second.
fn bake_throughput(small: &Path, size: MapSize, bar: &ProgressBar) -> anyhow::Result<[f64; 2]> {
    let sample = (size.keyframes / 10).max(4).min(size.keyframes);
    let mut throughput = [0.0; 2];
    for (slot, threads) in throughput.iter_mut().zip([1, 2]) {
        bar.set_message(format!("baking on {threads} thread(s)"));
        bar.set_length(sample as u64);
        bar.set_position(0);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        let s = pool.install(|| bake_synthetic(small, sample, size.points, bar))?;
        *slot = (sample * size.points) as f64 / s;
    }
    Ok(throughput)
}

/// Five fresh `kfmap bench probe` processes on the map: median milliseconds from
/// spawning to the printed answer, and inside the process.
pub(super) fn cold_starts(path: &Path) -> anyhow::Result<(f64, f64)> {
    let exe = std::env::current_exe()?;
    let mut wall = Vec::new();
    let mut inside = Vec::new();
    for _ in 0..5 {
        let started = Instant::now();
        let out = Command::new(&exe)
            .args(["bench", "probe"])
            .arg(path)
            .output()?;
        wall.push(started.elapsed().as_secs_f64() * 1e3);
        if !out.status.success() {
            bail!("probe failed: {}", String::from_utf8_lossy(&out.stderr));
        }
        let v: serde_json::Value = serde_json::from_slice(&out.stdout)?;
        inside.push(v["micros"].as_f64().unwrap_or(f64::NAN) / 1e3);
    }
    Ok((median(wall), median(inside)))
}

/// The path of a map without baked caches: every tree and covariance rebuilt from the
/// points, timed (milliseconds), and the result as a map on the heap.
fn rebuild_on_heap(map: &KeyframeMap) -> anyhow::Result<(f64, KeyframeMap)> {
    let cov = CovOptions::default();
    let started = Instant::now();
    let rebuilt: Vec<Keyframe> = map
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
    Ok((rebuild_ms, heap))
}

/// 20 000 query points around a keyframe (seeded).
fn random_queries() -> Vec<[f32; 3]> {
    let mut rng = SmallRng::seed_from_u64(7);
    (0..20_000)
        .map(|_| {
            [
                rng.random_range(-20.0..20.0),
                rng.random_range(-10.0..10.0),
                rng.random_range(-0.5..3.0),
            ]
        })
        .collect()
}

/// Best seconds of three query passes on the archived map and on the heap map, after
/// one pass paging in the archived map's active keyframes.
fn best_query_passes(
    mut archived: KeyframeMap,
    heap: &mut KeyframeMap,
    queries: &[[f32; 3]],
) -> anyhow::Result<(f64, f64)> {
    query_pass(&mut archived, queries)?; // Pages in the active keyframes.
    // Alternating passes, best of three each: the two layouts see the same machine noise.
    let (mut archived_s, mut heap_s) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..3 {
        let (a, a_sum) = query_pass(&mut archived, queries)?;
        let (h, h_sum) = query_pass(heap, queries)?;
        if a_sum != h_sum {
            bail!("archived and heap maps answered differently ({a_sum} vs {h_sum})");
        }
        archived_s = archived_s.min(a);
        heap_s = heap_s.min(h);
    }
    Ok((archived_s, heap_s))
}

impl LoadFigures {
    /// `--json`'s object.
    fn json(&self) -> serde_json::Value {
        let total_points = (self.size.keyframes * self.size.points) as f64;
        json!({
            "keyframes": self.size.keyframes,
            "points": total_points,
            "bytes": self.bytes,
            "generate_bake_seconds": self.generate_bake_seconds,
            "bake_points_per_second_1_thread": self.bake_points_per_second[0],
            "bake_points_per_second_2_threads": self.bake_points_per_second[1],
            "cold_start_ms": self.cold_ms,
            "cold_start_in_process_ms": self.cold_inside_ms,
            "rebuild_ms": self.rebuild_ms,
            "rebuild_over_cold_start": self.rebuild_ms / self.cold_ms,
            "threads": rayon::current_num_threads(),
            "archived_nn_per_second": self.queries_total / self.archived_s,
            "heap_nn_per_second": self.queries_total / self.heap_s,
            "archived_over_heap_time": self.archived_s / self.heap_s,
        })
    }

    /// Prints the figures for people; `path` is the generated map.
    fn print(&self, path: &Path) {
        let total_points = (self.size.keyframes * self.size.points) as f64;
        let (cold_ms, cold_inside_ms, rebuild_ms) =
            (self.cold_ms, self.cold_inside_ms, self.rebuild_ms);
        println!(
            "map: {} keyframes x {} points = {:.1} M points, {:.2} GB ({})",
            self.size.keyframes,
            self.size.points,
            total_points / 1e6,
            self.bytes as f64 / 1e9,
            path.display()
        );
        println!(
            "bake (trees + covariances + write): {:.2} M points/s on 1 thread, {:.2} M points/s on 2 threads",
            self.bake_points_per_second[0] / 1e6,
            self.bake_points_per_second[1] / 1e6
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
            self.queries_total / self.archived_s / 1e6,
            self.queries_total / self.heap_s / 1e6,
            100.0 * self.archived_s / self.heap_s
        );
    }
}

/// The table's rows of cold start against rebuild: `kfmap bench load` in a child
/// process, on a map of 500 keyframes x 40 000 points (40 x 20 000 with --quick).
pub(super) fn table_rows(table: &mut Table, dir: &Path) -> anyhow::Result<()> {
    table.stage("cold start vs rebuild (generating a map)");
    let (keyframes, points) = if table.quick {
        (40, 20_000)
    } else {
        (500, 40_000)
    };
    let dir = dir.display().to_string();
    let v = child_bench(&[
        "load",
        "--keyframes",
        &keyframes.to_string(),
        "--points",
        &points.to_string(),
        "--dir",
        &dir,
    ])?;
    let label = format!(
        "synthetic map, {keyframes} keyframes x {points} points, {:.2} GB",
        json_number(&v["bytes"]) / 1e9
    );
    let threads = json_number(&v["threads"]) as usize;
    table.push(
        "cold start: new process to first NN answer (mmap)",
        &label,
        1,
        json_number(&v["cold_start_ms"]),
        "ms",
    );
    table.push(
        "rebuild instead: every tree and covariance",
        &label,
        threads,
        json_number(&v["rebuild_ms"]),
        "ms",
    );
    for (threads, key) in [
        (1, "bake_points_per_second_1_thread"),
        (2, "bake_points_per_second_2_threads"),
    ] {
        table.push(
            "bake throughput (trees, covariances, write)",
            &label,
            threads,
            json_number(&v[key]) / 1e6,
            "M points/s",
        );
    }
    table.push(
        "NN queries on the mmapped map, time vs heap",
        &label,
        1,
        100.0 * json_number(&v["archived_over_heap_time"]),
        "%",
    );
    Ok(())
}
