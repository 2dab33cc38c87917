//! `kfmap bench remote`: server-side localize of a 20k-point scan through `kfmap gateway`
//! (Zenoh, TCP over loopback) against the same request over iceoryx2 to the same server,
//! alternated request by request so drift in machine speed touches both alike; then the
//! throughput of four clients each way. Network benchmarks run only in a private network
//! namespace (`unshare -rn`): the table re-executes this inside one.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use kfmap_client::{Client, ClientOptions, LocalizeOptions};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::percentile::percentile;
use kfmap_protocol::ScanPayload;
use serde_json::json;

use super::child::run_json;
use super::fixtures::{bake_served_map, keyframe_pose, synthetic_cloud};
use super::table::Table;
use crate::json_number;
use crate::server_child::start_bench_server;

/// The gateway's endpoint inside the namespace.
const ENDPOINT: &str = "tcp/127.0.0.1:17450";
/// Points of the localized scan.
const SCAN_POINTS: usize = 20_000;
/// Clients of the throughput phase.
const CLIENTS: usize = 4;

/// A `kfmap gateway` child, killed on drop.
struct GatewayChild(Child);

impl GatewayChild {
    fn start(prefix: &str) -> anyhow::Result<Self> {
        let mut child = Command::new(std::env::current_exe()?)
            .args(["gateway", "--map-name", "bench", "--iceoryx-prefix", prefix])
            .args(["--listen", ENDPOINT])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .context("start kfmap gateway")?;
        let mut line = String::new();
        let stdout = child.stdout.take().context("gateway stdout")?;
        let gateway = Self(child);
        BufReader::new(stdout).read_line(&mut line)?;
        if !line.starts_with("ready:") {
            bail!("kfmap gateway did not start: {line:?}");
        }
        Ok(gateway)
    }
}

impl Drop for GatewayChild {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The request: 20k points of keyframe 5's own synthetic scan (so it registers as a real
/// scan would), guessed 0.2 m off.
struct Request {
    points: Vec<[f32; 3]>,
    guess: Pose,
}

impl Request {
    fn new() -> Self {
        Self {
            points: synthetic_cloud(5, SCAN_POINTS).points,
            guess: keyframe_pose(5) * Pose::translation(0.2, -0.1, 0.0),
        }
    }

    /// One server-side localize; milliseconds.
    fn time(&self, client: &mut Client) -> anyhow::Result<f64> {
        let scan = ScanPayload {
            points: &self.points,
            view_dirs: None,
            covariances: None,
        };
        let t = Instant::now();
        client.localize(&scan, &self.guess, &LocalizeOptions::default())?;
        Ok(t.elapsed().as_secs_f64() * 1e3)
    }
}

fn options(prefix: &str) -> ClientOptions {
    ClientOptions {
        iceoryx_prefix: Some(prefix.to_string()),
        timeout: Duration::from_secs(30),
        spin: false,
    }
}

/// Scans per second of `CLIENTS` client processes (`kfmap bench remote-worker`), each
/// with its own server session, local or through the gateway, for `seconds`: the sum of
/// each process's own rate.
fn throughput(prefix: &str, remote: bool, seconds: f64) -> anyhow::Result<f64> {
    let exe = std::env::current_exe()?;
    let children: Vec<_> = (0..CLIENTS)
        .map(|_| {
            let mut command = Command::new(&exe);
            command
                .args(["bench", "remote-worker", prefix, "--seconds"])
                .arg(seconds.to_string())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit());
            if remote {
                command.arg("--remote");
            }
            command.spawn()
        })
        .collect::<Result<_, _>>()?;
    let mut total = 0.0;
    for child in children {
        let out = child.wait_with_output()?;
        if !out.status.success() {
            anyhow::bail!("a throughput client failed");
        }
        let v: serde_json::Value = serde_json::from_slice(&out.stdout)?;
        total += v["scans_per_s"].as_f64().unwrap_or(0.0);
    }
    Ok(total)
}

/// The hidden `kfmap bench remote-worker`: one client process of the throughput rows,
/// sending server-side localize back to back for `seconds`; prints its rate as JSON.
pub(super) fn worker(prefix: &str, remote: bool, seconds: f64) -> anyhow::Result<()> {
    let mut client = if remote {
        kfmap_remote::connect(ENDPOINT, "bench", options(prefix))?
    } else {
        Client::connect("bench", options(prefix))?
    };
    let request = Request::new();
    let started = Instant::now();
    let mut n = 0;
    while started.elapsed().as_secs_f64() < seconds {
        request.time(&mut client)?;
        n += 1;
    }
    let rate = n as f64 / started.elapsed().as_secs_f64();
    println!("{}", json!({ "scans": n, "scans_per_s": rate }));
    Ok(())
}

/// Runs `kfmap bench remote` (inside a network namespace) against a synthetic map in
/// `dir`; prints JSON.
pub(super) fn run(dir: &Path, quick: bool) -> anyhow::Result<()> {
    let map = dir.join(format!("kfmap-bench-remote-{}.kfmap", std::process::id()));
    bake_served_map(&map)?;
    let prefix = format!("kfbenchr{}_", std::process::id());
    let result = measure(&map, &prefix, quick);
    let _ = std::fs::remove_file(&map);
    println!("{}", serde_json::to_string_pretty(&result?)?);
    Ok(())
}

fn measure(map: &Path, prefix: &str, quick: bool) -> anyhow::Result<serde_json::Value> {
    let (reps, seconds) = if quick { (20, 1.0) } else { (200, 5.0) };
    let _server = start_bench_server(map, prefix, false)?;
    let _gateway = GatewayChild::start(prefix)?;
    let mut local = Client::connect("bench", options(prefix))?;
    let mut remote = kfmap_remote::connect(ENDPOINT, "bench", options(prefix))?;
    let request = Request::new();
    for _ in 0..5 {
        request.time(&mut local)?;
        request.time(&mut remote)?;
    }
    let (mut l, mut r) = (Vec::new(), Vec::new());
    for _ in 0..reps {
        l.push(request.time(&mut local)?);
        r.push(request.time(&mut remote)?);
    }
    l.sort_by(f64::total_cmp);
    r.sort_by(f64::total_cmp);
    drop((local, remote));
    let local_rate = throughput(prefix, false, seconds)?;
    let remote_rate = throughput(prefix, true, seconds)?;
    Ok(json!({
        "scan_points": SCAN_POINTS,
        "samples": reps,
        "local_p50_ms": percentile(&l, 0.5),
        "local_p99_ms": percentile(&l, 0.99),
        "remote_p50_ms": percentile(&r, 0.5),
        "remote_p99_ms": percentile(&r, 0.99),
        "clients": CLIENTS,
        "local_scans_per_s": local_rate,
        "remote_scans_per_s": remote_rate,
    }))
}

/// True when this machine lets an unprivileged process make a network namespace.
fn namespaces_work() -> bool {
    Command::new("unshare")
        .args(["-rn", "sh", "-c", "ip link set lo up"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// The table's remote rows: `kfmap bench remote` in a network namespace of its own.
pub(super) fn table_rows(table: &mut Table, dir: &Path) -> anyhow::Result<()> {
    table.stage("remote clients through kfmap gateway (Zenoh, loopback, private namespace)");
    if !namespaces_work() {
        table.skip("remote rows: no private network namespace here (unshare -rn)");
        return Ok(());
    }
    let dir = dir.display().to_string();
    let mut args = vec!["remote", "--dir", &dir];
    if table.quick {
        args.push("--quick");
    }
    let v = child_bench_in_namespace(&args)?;
    let label = "synthetic map, 12 keyframes x 40 000 points; serve + gateway children";
    let (local, remote) = (
        json_number(&v["local_p50_ms"]),
        json_number(&v["remote_p50_ms"]),
    );
    table.push(
        "server-side localize, 20k points, local (iceoryx2), median",
        label,
        1,
        local,
        "ms",
    );
    table.push(
        "  the same through kfmap gateway (Zenoh TCP), median",
        label,
        1,
        remote,
        "ms",
    );
    table.push(
        "  remote as a share of local, median",
        label,
        1,
        100.0 * remote / local,
        "%",
    );
    let (lr, rr) = (
        json_number(&v["local_scans_per_s"]),
        json_number(&v["remote_scans_per_s"]),
    );
    table.push(
        "localize throughput, 4 client processes, local",
        label,
        4,
        lr,
        "scans/s",
    );
    table.push(
        "  the same remote, as a share of local",
        label,
        4,
        100.0 * rr / lr,
        "%",
    );
    Ok(())
}

/// `kfmap bench ARGS --json` inside `unshare -rn` (only `lo`, brought up first).
fn child_bench_in_namespace(args: &[&str]) -> anyhow::Result<serde_json::Value> {
    let mut command = Command::new("unshare");
    command
        .args(["-rn", "sh", "-c", "ip link set lo up && exec \"$0\" \"$@\""])
        .arg(std::env::current_exe()?)
        .arg("bench")
        .args(args);
    run_json(
        command,
        &format!("kfmap bench {} (in unshare -rn)", args.join(" ")),
    )
}
