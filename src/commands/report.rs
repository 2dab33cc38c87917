//! Human-readable printing shared by subcommands.

use crate::commands::cloud_summary::CloudSummary;

fn opt(value: Option<f64>, unit: &str, digits: usize) -> String {
    value.map_or_else(|| "n/a".to_string(), |v| format!("{v:.digits$} {unit}"))
}

/// Prints the statistics block of a cloud summary.
pub fn print_summary(s: &CloudSummary) {
    let [x0, y0, z0] = s.bbox_min;
    let [x1, y1, z1] = s.bbox_max;
    println!("  points:           {}", s.points);
    println!("  bounding box:     [{x0:.2}, {y0:.2}, {z0:.2}] .. [{x1:.2}, {y1:.2}, {z1:.2}] m");
    println!(
        "  density:          {}",
        opt(s.density_points_per_m3, "points/m^3 of box", 2)
    );
    println!("  median spacing:   {}", opt(s.median_nn_spacing_m, "m", 3));
    println!(
        "  fallback covs:    {:.2} % (isotropic, too few neighbours)",
        s.fallback_fraction * 100.0
    );
    println!("  mean planarity:   {}", opt(s.mean_planarity, "", 3));
    println!(
        "  timings:          kd-tree {:.1} ms, covariances {:.1} ms on {} threads ({:.2} M points/s)",
        s.tree_ms,
        s.covariances_ms,
        s.threads,
        s.points as f64 / s.covariances_ms / 1e3
    );
}

/// A number of a JSON report (NaN when absent), for printing.
pub fn json_number(value: &serde_json::Value) -> f64 {
    value.as_f64().unwrap_or(f64::NAN)
}

/// How to name a printed p99 of `samples` values: "p99", or "p99 (= max of N)" when
/// there are too few (under 100) for the nearest-rank 99th percentile to be anything
/// but their maximum.
pub fn p99_label(samples: usize) -> String {
    if kfmap_geometry::percentile::is_maximum(samples, 0.99) {
        format!("p99 (= max of {samples})")
    } else {
        "p99".to_string()
    }
}
