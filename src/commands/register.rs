//! `kfmap register`: align two point clouds (GICP, or point-to-point / point-to-plane ICP).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_geometry::registration::{
    Metric, Optimizer, RegistrationParams, RegistrationResult, RobustKernel, register,
};
use serde_json::json;

/// Register SOURCE onto TARGET: prints the 4x4 transform T_target_source (a point p of
/// the source maps to T p in the target's frame), fitness (share of source points with
/// a partner within --max-distance, RMS distance), iterations, convergence, whether the
/// scene constrains every direction (degenerate: e.g. a featureless corridor), and time.
///
/// Both clouds are voxel-downsampled (--voxel), get per-point covariances from their
/// --neighbours nearest points, and are matched by nearest neighbour within
/// --max-distance; the pose is refined by Gauss-Newton (or Levenberg-Marquardt) until
/// the update falls below 0.1 deg and 1 mm. Clouds: PCD, PLY, KITTI .bin, raw xyz .bin;
/// invalid returns are dropped on load.
///
/// Examples:
///   kfmap register ../shared/data/small_gicp/source.ply ../shared/data/small_gicp/target.ply
///   kfmap register b.pcd a.pcd --initial "1.0 0 0 0 0 5" --metric point-to-plane --json
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The cloud to move.
    source: PathBuf,
    /// The cloud to align to.
    target: PathBuf,
    /// Initial guess "x y z roll pitch yaw" (metres, degrees), or a file holding a 4x4
    /// row-major matrix. A guess starting with a minus sign is a value, not a flag.
    #[arg(long, allow_hyphen_values = true)]
    initial: Option<String>,
    /// Residual metric.
    #[arg(long, value_enum, default_value = "gicp")]
    metric: MetricArg,
    /// Voxel size, metres (0 keeps every point).
    #[arg(long, default_value_t = 0.25)]
    voxel: f64,
    /// Correspondences farther apart than this are ignored, metres.
    #[arg(long, default_value_t = 1.0)]
    max_distance: f64,
    /// Neighbours per point for covariances.
    #[arg(long, default_value_t = 10)]
    neighbours: usize,
    /// Iterations at most.
    #[arg(long, default_value_t = 20)]
    max_iterations: usize,
    /// Robust kernel on the Mahalanobis residual.
    #[arg(long, value_enum, default_value = "none")]
    kernel: KernelArg,
    /// Kernel scale.
    #[arg(long, default_value_t = 1.0)]
    kernel_delta: f64,
    /// Use Levenberg-Marquardt steps instead of Gauss-Newton.
    #[arg(long)]
    lm: bool,
    /// Worker threads; 0 means one per core.
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum MetricArg {
    Gicp,
    PointToPoint,
    PointToPlane,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum KernelArg {
    None,
    Huber,
    Cauchy,
    GemanMcclure,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let initial = args
        .initial
        .as_deref()
        .map(super::pose_arg::parse_pose)
        .transpose()?
        .unwrap_or_else(Pose::identity);
    let params = RegistrationParams {
        metric: match args.metric {
            MetricArg::Gicp => Metric::Gicp,
            MetricArg::PointToPoint => Metric::PointToPoint,
            MetricArg::PointToPlane => Metric::PointToPlane,
        },
        voxel_size: args.voxel,
        covariance_neighbours: args.neighbours,
        max_correspondence_distance: args.max_distance,
        max_iterations: args.max_iterations,
        kernel: match args.kernel {
            KernelArg::None => RobustKernel::None,
            KernelArg::Huber => RobustKernel::Huber {
                delta: args.kernel_delta,
            },
            KernelArg::Cauchy => RobustKernel::Cauchy {
                delta: args.kernel_delta,
            },
            KernelArg::GemanMcclure => RobustKernel::GemanMcClure {
                delta: args.kernel_delta,
            },
        },
        optimizer: if args.lm {
            Optimizer::LevenbergMarquardt
        } else {
            Optimizer::GaussNewton
        },
        ..RegistrationParams::default()
    };
    params.validate()?;
    let read =
        |p: &PathBuf| -> anyhow::Result<_> { Ok(read_cloud(p, &ReadOptions::default())?.cloud) };
    let (source, target) = (read(&args.source)?, read(&args.target)?);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads)
        .build()
        .context("cannot start worker threads")?;
    let started = Instant::now();
    let result = pool.install(|| register(&target, &source, &initial, &params))?;
    let seconds = started.elapsed().as_secs_f64();
    let m = result.pose.to_homogeneous();
    if args.json {
        let row_major: Vec<f64> = (0..16).map(|i| m[(i / 4, i % 4)]).collect();
        let hessian: Vec<f64> = (0..36).map(|i| result.hessian[(i / 6, i % 6)]).collect();
        println!(
            "{}",
            json!({
                "T_target_source": row_major, "iterations": result.iterations,
                "converged": result.converged, "fitness": result.fitness,
                "degenerate": result.degenerate, "constraint": result.constraint,
                "hessian": hessian, "seconds": seconds,
                "threads": pool.current_num_threads(),
            })
        );
        return Ok(());
    }
    print_result(&result, seconds, pool.current_num_threads());
    Ok(())
}

fn print_result(result: &RegistrationResult, seconds: f64, threads: usize) {
    let m = result.pose.to_homogeneous();
    println!("T_target_source:");
    for r in 0..4 {
        println!(
            "  {:>12.6} {:>12.6} {:>12.6} {:>12.6}",
            m[(r, 0)],
            m[(r, 1)],
            m[(r, 2)],
            m[(r, 3)]
        );
    }
    let (roll, pitch, yaw) = result.pose.rotation.euler_angles();
    println!(
        "  = translation {:.4} m, roll {:.3}°, pitch {:.3}°, yaw {:.3}°",
        result.pose.translation.vector.norm(),
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees()
    );
    println!(
        "fitness: {:.1} % of source points matched, RMS distance {:.4} m",
        100.0 * result.fitness.inlier_ratio,
        result.fitness.rmse
    );
    println!(
        "{} iterations, {}; {:.1} ms on {threads} threads",
        result.iterations,
        if result.converged {
            "converged"
        } else {
            "NOT converged (iteration limit)"
        },
        seconds * 1e3
    );
    if result.degenerate {
        println!(
            "WARNING: degenerate geometry (eigenvalue ratios: rotation {:.2e}, translation {:.2e}); the pose is unreliable along the weak direction",
            result.constraint.rotation_ratio, result.constraint.translation_ratio
        );
    }
}
