//! Human-readable printing shared by subcommands.

use kfmap_geometry::geometry::Pose;

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

/// One line on `T_map_input`, the transform a map applies to its dataset's pose file
/// (bake's gravity levelling, or the fit onto built poses): `kfmap localize` moves a
/// dataset's ground truth by it, and so must anyone comparing poses with that file.
/// `None`: the stored values are no pose.
pub fn map_from_input_line(pose: Option<&Pose>) -> String {
    let Some(p) = pose else {
        return "dataset poses -> map frame (T_map_input): not a pose (bake the map again)"
            .to_string();
    };
    if p.rotation.angle() == 0.0 && p.translation.vector.norm() == 0.0 {
        return "dataset poses -> map frame (T_map_input): identity".to_string();
    }
    let (roll, pitch, yaw) = p.rotation.euler_angles();
    let t = p.translation.vector;
    format!(
        "dataset poses -> map frame (T_map_input): roll {:.4} deg, pitch {:.4} deg, yaw {:.4} deg, translation [{:.3}, {:.3}, {:.3}] m",
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees(),
        t.x,
        t.y,
        t.z
    )
}
