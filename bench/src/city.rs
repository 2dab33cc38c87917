//! `kfmap bench city`: a synthetic city map (keyframes along a street grid over a
//! square site) baked whole, then the same keyframes baked into tiles as `kfmap bake
//! --tile-size` does (`TileSetWriter`); bake throughput of the tile set against the
//! whole map, cold start per tile (a fresh process to its first answer) and the place
//! grids' share of the tile files.

use std::path::Path;
use std::time::Instant;

use anyhow::bail;
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_bake::tiling::TileSetWriter;
use kfmap_geometry::geometry::Pose;
use kfmap_map::covis::CovisSnapshot;
use kfmap_map::map::KeyframeMapOptions;
use kfmap_map::tiles::TileGeometry;
use nalgebra::Vector3;
use serde_json::json;

use super::fixtures::{bake_synthetic_at, build_synthetic};
use super::load::cold_starts;

/// The city's size and how it is cut.
#[derive(Debug, Clone, Copy)]
pub(super) struct CityPlan {
    /// Edge of the square site, metres.
    pub extent_m: f64,
    /// Keyframes along its streets.
    pub keyframes: usize,
    /// Points per keyframe.
    pub points: usize,
    /// How the map is cut.
    pub tiles: TileGeometry,
}

/// Where keyframe `i` of `count` lies: streets along x and y every `block` metres, the
/// keyframes spread evenly along them, each facing along its street.
fn street_pose(i: usize, count: usize, extent: f64) -> Pose {
    // Streets per direction, so that the keyframes are about 10 m apart.
    let per_direction = ((count as f64 * 10.0 / extent / 2.0).round() as usize).max(1);
    let streets = 2 * per_direction;
    let per_street = count.div_ceil(streets);
    let (street, along) = (i / per_street, (i % per_street) as f64 / per_street as f64);
    let block = extent / per_direction as f64;
    let offset = (street % per_direction) as f64 * block + block / 2.0;
    let s = along * extent;
    if street < per_direction {
        Pose::new(Vector3::new(s, offset, 0.0), Vector3::zeros())
    } else {
        Pose::new(
            Vector3::new(offset, s, 0.0),
            Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        )
    }
}

/// Runs `kfmap bench city` in `dir` (the files are removed after).
pub(super) fn run(dir: &Path, plan: CityPlan, json_out: bool) -> anyhow::Result<()> {
    plan.tiles
        .validate()
        .map_err(|e| anyhow::anyhow!("--{e}"))?;
    if plan.keyframes < 4
        || plan.points < 100
        || !plan.extent_m.is_finite()
        || plan.extent_m < 100.0
    {
        bail!("--keyframes must be at least 4, --points at least 100, --extent-m at least 100");
    }
    let work = dir.join(format!("kfmap-bench-city-{}", std::process::id()));
    std::fs::create_dir_all(&work)?;
    let result = measure(&work, plan, json_out);
    let _ = std::fs::remove_dir_all(&work);
    result
}

fn measure(work: &Path, plan: CityPlan, json_out: bool) -> anyhow::Result<()> {
    let bar = if json_out {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(plan.keyframes as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len}")?.progress_chars("=> "),
    );
    bar.set_message("baking the city whole");
    let merged = work.join("city.kfmap");
    let count = plan.keyframes;
    let bake_s = bake_synthetic_at(
        &merged,
        count,
        plan.points,
        |i| street_pose(i, count, plan.extent_m),
        &bar,
    )?;
    let merged_bytes = std::fs::metadata(&merged)?.len();
    // The whole map's file is not needed any more: the tiles are baked from the same
    // keyframes, built again, as `kfmap bake --tile-size` does.
    std::fs::remove_file(&merged)?;
    bar.set_message("baking the city into tiles");
    bar.set_position(0);
    let tiles_dir = work.join("city.tiles");
    let options = KeyframeMapOptions::default();
    let mut writer =
        TileSetWriter::create(&tiles_dir, plan.tiles, &options, &Pose::identity(), false)?;
    let build_s = build_synthetic(
        count,
        plan.points,
        |i| street_pose(i, count, plan.extent_m),
        &bar,
        |keyframes| Ok(writer.write_keyframes(keyframes)?),
    )?;
    bar.set_message("finishing tiles");
    let started = Instant::now();
    let cut = writer.finish(
        count as u64,
        &CovisSnapshot::default(),
        &[],
        |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
    )?;
    let tiles_s = build_s + started.elapsed().as_secs_f64();
    bar.set_message("cold starts");
    // The largest tiles (most keyframes) start slowest: probe those.
    let mut largest: Vec<_> = cut.index.tiles.iter().collect();
    largest.sort_by_key(|t| std::cmp::Reverse(t.bytes));
    let mut cold = Vec::new();
    for t in largest.iter().take(5) {
        cold.push(cold_starts(&tiles_dir.join(&t.file))?);
    }
    bar.finish_and_clear();
    let points = (count * plan.points) as f64;
    let tile_count = cut.index.tiles.len();
    let written: u64 = cut.index.tiles.iter().map(|t| t.keyframes).sum();
    let worst_cold = cold.iter().map(|c| c.0).fold(0.0, f64::max);
    let worst_cold_inside = cold.iter().map(|c| c.1).fold(0.0, f64::max);
    let figures = json!({
        "extent_m": plan.extent_m, "keyframes": count, "points_per_keyframe": plan.points,
        "tile_size_m": plan.tiles.tile_size, "halo_m": plan.tiles.halo, "tiles": tile_count,
        "keyframes_written": written, "merged_bytes": merged_bytes, "tile_bytes": cut.map_bytes,
        "bake_whole_s": bake_s, "bake_tiles_s": tiles_s,
        "bake_tiles_finish_s": cut.finish_seconds,
        "bake_whole_points_per_s": points / bake_s,
        "bake_tiles_points_per_s": points / tiles_s,
        "cold_start_ms_worst_of_5_largest": worst_cold,
        "cold_start_inside_ms_worst_of_5_largest": worst_cold_inside,
        "place_grid_bytes": cut.place_bytes,
        "place_grid_share_of_tile_files": cut.place_bytes as f64 / cut.map_bytes.max(1) as f64,
        "place_grid_worst_tile_share": cut.worst_place_share,
    });
    if json_out {
        println!("{figures}");
        return Ok(());
    }
    println!(
        "city: {count} keyframes x {} points over {:.1} x {:.1} km, cut into {tile_count} tiles of {} m (halo {} m)",
        plan.points,
        plan.extent_m / 1e3,
        plan.extent_m / 1e3,
        plan.tiles.tile_size,
        plan.tiles.halo
    );
    println!(
        "  bake whole: {bake_s:.1} s ({:.2} M points/s, {:.2} GB)",
        points / bake_s / 1e6,
        merged_bytes as f64 / 1e9,
    );
    println!(
        "  bake into tiles: {tiles_s:.1} s ({:.2} M points/s, {:.0} % of the whole map's; {written} keyframes written, {:.2}x, {:.2} GB; tiles finished in {:.1} s)",
        points / tiles_s / 1e6,
        100.0 * bake_s / tiles_s,
        written as f64 / count as f64,
        cut.map_bytes as f64 / 1e9,
        cut.finish_seconds
    );
    println!(
        "  cold start per tile (5 largest): worst {worst_cold:.1} ms from a fresh process, {worst_cold_inside:.1} ms inside it"
    );
    println!(
        "  place grids: {:.1} MB, {:.2} % of the tile files (worst tile {:.2} %)",
        cut.place_bytes as f64 / 1e6,
        100.0 * cut.place_bytes as f64 / cut.map_bytes.max(1) as f64,
        100.0 * cut.worst_place_share
    );
    Ok(())
}
