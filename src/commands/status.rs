//! `kfmap status`: a running server's counters (and `--reload`).

use serde_json::json;

use super::connect_arg::ConnectArgs;

/// Show a running server's map, uptime, sessions and per-kind request counts with
/// median and 99th percentile latency, and each session's gravity pool (windows pooled,
/// motion-compensated, pending and left out; the correction, its spread and the
/// accelerometer bias); `--reload` asks it to reopen its map file.
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
                json!({
                    "client": format!("{:016x}{:016x}", g.client_node[0], g.client_node[1]),
                    "busy": g.busy == 1,
                    "gravity_members": g.members, "compensated": g.compensated,
                    "pending": g.pending, "skipped": g.skipped, "inliers": g.inliers,
                    "has_gravity": g.has_gravity == 1,
                    "roll_deg": g.roll_pitch[0].to_degrees(), "pitch_deg": g.roll_pitch[1].to_degrees(),
                    "spread_deg": g.spread_deg, "accel_bias_mps2": g.accel_bias,
                    "bias_observable": g.bias_observable == 1,
                })
            })
            .collect();
        let out = json!({
            "map_name": s.map_name, "map_path": s.map_path, "keyframes": s.keyframes,
            "points": s.points, "uptime_s": s.uptime_s, "sessions": s.sessions, "in_flight": s.in_flight,
            "requests": kinds, "session_gravity": sessions,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "map {} ({}): {} keyframes, {} points",
        s.map_name, s.map_path, s.keyframes, s.points
    );
    println!(
        "uptime {:.1} s, {} client sessions, {} requests being answered",
        s.uptime_s, s.sessions, s.in_flight
    );
    for (kind, count, p50, p99) in &s.kinds {
        println!(
            "  {:<10} {count:>8} requests, p50 {p50:.0} us, p99 {p99:.0} us",
            kind.name()
        );
    }
    for g in &s.session_gravity {
        let client = format!("{:016x}{:016x}", g.client_node[0], g.client_node[1]);
        if g.busy == 1 {
            println!("  session {client}: busy answering a request");
        } else if g.has_gravity == 1 {
            println!(
                "  session {client}: gravity roll {:.3}°, pitch {:.3}° from {} windows ({} motion-compensated, {} inliers, spread {:.3}°; {} pending, {} left out), accelerometer bias [{:.4}, {:.4}, {:.4}] m/s^2{}",
                g.roll_pitch[0].to_degrees(),
                g.roll_pitch[1].to_degrees(),
                g.members,
                g.compensated,
                g.inliers,
                g.spread_deg,
                g.pending,
                g.skipped,
                g.accel_bias[0],
                g.accel_bias[1],
                g.accel_bias[2],
                if g.bias_observable == 1 {
                    " (observable)"
                } else {
                    " (not yet observable)"
                }
            );
        } else {
            println!(
                "  session {client}: {} IMU windows pooled ({} pending, {} left out), too few for gravity",
                g.members, g.pending, g.skipped
            );
        }
    }
    Ok(())
}
