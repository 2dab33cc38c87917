//! `kfmap optimize-graph`: optimize a g2o SE(3) pose graph.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use kfmap_geometry::registration::Optimizer;
use kfmap_graph::pose_graph::{GraphParams, read_g2o, write_g2o};
use serde_json::json;

/// Optimize an SE(3) pose graph in g2o format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT, FIX) and
/// write the result in the same format. The first vertex (or the FIXed one) stays where
/// it is; every other pose moves to minimize the sum over edges of e^T W e / 2, where
/// e = Log(Z^-1 X_i^-1 X_j) (rotation first, as GTSAM), so the printed errors compare
/// with GTSAM's. Gauss-Newton by default (--lm for Levenberg-Marquardt), a sparse
/// Cholesky with AMD ordering, stopping when the error drops by less than
/// --relative-tol.
///
/// Example:
///   kfmap optimize-graph ../shared/data/g2o/parking-garage.g2o /tmp/garage-opt.g2o
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Input graph (.g2o).
    input: PathBuf,
    /// Output graph (.g2o), written atomically.
    output: PathBuf,
    /// Levenberg-Marquardt instead of Gauss-Newton.
    #[arg(long)]
    lm: bool,
    /// Iterations at most.
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// Stop when the error drops by less than this fraction.
    #[arg(long, default_value_t = 1e-5)]
    relative_tol: f64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let started = Instant::now();
    let (mut graph, fixed) = read_g2o(&args.input)?;
    let read_seconds = started.elapsed().as_secs_f64();
    let params = GraphParams {
        optimizer: if args.lm {
            Optimizer::LevenbergMarquardt
        } else {
            Optimizer::GaussNewton
        },
        max_iterations: args.max_iterations,
        relative_error_tol: args.relative_tol,
        fixed,
        ..GraphParams::default()
    };
    let started = Instant::now();
    let report = graph
        .optimize(&params)
        .with_context(|| format!("optimizing {}", args.input.display()))?;
    let seconds = started.elapsed().as_secs_f64();
    write_g2o(&args.output, &graph, fixed)?;
    if args.json {
        println!(
            "{}",
            json!({
                "vertices": graph.len(), "edges": graph.edges().len(),
                "initial_error": report.initial_error, "final_error": report.final_error,
                "errors": report.errors, "iterations": report.iterations,
                "converged": report.converged, "seconds": seconds, "read_seconds": read_seconds,
            })
        );
        return Ok(());
    }
    println!(
        "{}: {} vertices, {} edges (read in {:.1} ms)",
        args.input.display(),
        graph.len(),
        graph.edges().len(),
        read_seconds * 1e3
    );
    println!(
        "error {:.6} -> {:.6} in {} iterations ({}), {:.1} ms",
        report.initial_error,
        report.final_error,
        report.iterations,
        if report.converged {
            "converged"
        } else {
            "iteration limit"
        },
        seconds * 1e3
    );
    println!("wrote {}", args.output.display());
    Ok(())
}
