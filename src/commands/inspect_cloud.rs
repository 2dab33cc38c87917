//! `kfmap inspect-cloud`: what is in a point-cloud file.

use std::path::PathBuf;

use crate::commands::cloud_summary::summarize;
use anyhow::Context;
use kfmap_bake::config::BakeConfig;
use kfmap_geometry::io::{BinLayout, ReadOptions, read_cloud};
use kfmap_geometry::options::ConfigFile;
use serde_json::json;

use super::report::print_summary;

/// Report a point-cloud file: format, fields, extent, density, covariance shape.
///
/// Reads PCD (ascii, binary, binary_compressed), PLY (ascii, binary_little_endian)
/// and headerless .bin (KITTI x y z intensity, or raw x y z). Invalid returns (NaN/inf,
/// exactly (0,0,0), closer than --min-range) are dropped and counted.
///
/// Example: kfmap inspect-cloud ../shared/data/small_gicp/target.ply --json
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The cloud file (.pcd, .ply, .bin).
    file: PathBuf,
    /// Layout of a .bin file: xyzi (KITTI) or xyz (raw triplets). Default: the sidecar
    /// FILE.layout if present, else xyzi.
    #[arg(long, value_parser = parse_layout)]
    bin_layout: Option<BinLayout>,
    /// Keep invalid returns instead of dropping them.
    #[arg(long)]
    no_filter: bool,
    /// Minimum range for the invalid-return filter, metres [default: from config, 0.1].
    #[arg(long)]
    min_range: Option<f64>,
    /// bake.toml whose [filter] and [covariance] sections to use [default: built in].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn parse_layout(word: &str) -> Result<BinLayout, String> {
    BinLayout::parse(word).ok_or_else(|| format!("'{word}' is not a layout; use xyz or xyzi"))
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let config = BakeConfig::load(args.config.as_deref())?;
    let mut filter = config.filter;
    filter.enabled &= !args.no_filter;
    if let Some(r) = args.min_range {
        anyhow::ensure!(
            r.is_finite() && r >= 0.0,
            "--min-range must be a finite distance >= 0 m, got {r}"
        );
        filter.min_range = r;
    }
    let options = ReadOptions {
        bin_layout: args.bin_layout,
        filter,
    };
    let loaded = read_cloud(&args.file, &options)?;
    loaded
        .cloud
        .validate()
        .with_context(|| format!("{}", args.file.display()))?;
    let summary = summarize(&loaded.cloud, &config.covariance)
        .with_context(|| format!("{}: nothing to summarize", args.file.display()))?;
    if args.json {
        let report = json!({
            "file": args.file,
            "format": loaded.format.to_string(),
            "points": loaded.cloud.len(),
            "points_in_file": loaded.points_in_file,
            "fields": loaded.fields,
            "filter": loaded.filter.map(|f| json!({
                "min_range_m": filter.min_range,
                "dropped": f.dropped(),
                "non_finite": f.non_finite,
                "at_origin": f.at_origin,
                "too_close": f.too_close,
            })),
            "bbox_min": summary.bbox_min,
            "bbox_max": summary.bbox_max,
            "density_points_per_m3": summary.density_points_per_m3,
            "median_nn_spacing_m": summary.median_nn_spacing_m,
            "fallback_fraction": summary.fallback_fraction,
            "mean_planarity": summary.mean_planarity,
            "timings_ms": { "kdtree": summary.tree_ms, "covariances": summary.covariances_ms },
            "threads": summary.threads,
        });
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!("{}", args.file.display());
    println!("  format:           {}", loaded.format);
    println!("  fields:           {}", loaded.fields.join(" "));
    match loaded.filter {
        Some(f) => println!(
            "  filter:           dropped {} of {} ({} non-finite, {} at origin, {} closer than {} m)",
            f.dropped(),
            loaded.points_in_file,
            f.non_finite,
            f.at_origin,
            f.too_close,
            filter.min_range
        ),
        None => println!("  filter:           off"),
    }
    print_summary(&summary);
    Ok(())
}
