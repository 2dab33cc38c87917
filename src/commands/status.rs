//! `kfmap status`: a running server's counters (and `--reload`).

use serde_json::json;

use kfmap_geometry::geometry::pose_to_xyz_quat;
use kfmap_service::server::LATENCY_WINDOW;

use super::connect_arg::ConnectArgs;
use kfmap_geometry::percentile::p99_label;

/// Show a running server's map, uptime, sessions and per-kind request counts with
/// median and 99th percentile latency, and each session's gravity pool (windows pooled,
/// motion-compensated, pending and left out; the correction, its spread and the
/// accelerometer bias), and `T_map_input` (what moves the map's dataset poses into
/// the map frame: compare a reference with the served poses through it); `--reload`
/// asks it to reopen its map file.
///
/// Examples:
///   kfmap status --map-name site
///   kfmap status --map-name site --json
///   kfmap status --map-name site --reload
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    server: ConnectArgs,
    /// Ask the server to reopen its map file first.
    #[arg(long)]
    reload: bool,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut client = args.server.connect()?;
    if args.reload {
        eprintln!("{}", client.reload()?);
    }
    let s = client.status()?;
    if args.json {
        let kinds: serde_json::Map<String, serde_json::Value> = s
            .kinds
            .iter()
            .map(|(k, n, p50, p99)| {
                (
                    k.name().to_string(),
                    json!({"count": n, "p50_us": p50, "p99_us": p99}),
                )
            })
            .collect();
        let sessions: Vec<serde_json::Value> = s
            .session_gravity
            .iter()
            .map(|g| {
                let mut entry = super::gravity::served_json(&g.pool);
                entry["client"] = json!(format!("{:032x}", g.client));
                entry["busy"] = json!(g.busy);
                entry
            })
            .collect();
        let out = json!({
            "map_name": s.map_name, "map_path": s.map_path, "keyframes": s.keyframes,
            "points": s.points, "uptime_s": s.uptime_s, "sessions": s.sessions, "in_flight": s.in_flight,
            "requests": kinds, "session_gravity": sessions,
            "map_from_input": pose_to_xyz_quat(&s.map_from_input),
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "map {} ({}): {} keyframes, {} points",
        s.map_name, s.map_path, s.keyframes, s.points
    );
    println!(
        "{}",
        super::report::map_from_input_line(Some(&s.map_from_input))
    );
    println!(
        "uptime {:.1} s, {} client sessions, {} requests being answered",
        s.uptime_s, s.sessions, s.in_flight
    );
    for (kind, count, p50, p99) in &s.kinds {
        // The server's percentiles cover its latest LATENCY_WINDOW requests of a kind.
        let samples = (*count as usize).min(LATENCY_WINDOW);
        println!(
            "  {:<10} {count:>8} requests, p50 {p50:.0} us, {} {p99:.0} us",
            kind.name(),
            p99_label(samples)
        );
    }
    for g in &s.session_gravity {
        let line = if g.busy {
            "busy answering a request".to_string()
        } else {
            super::gravity::served_line(&g.pool)
        };
        println!("  session {:032x}: gravity {line}", g.client);
    }
    Ok(())
}
