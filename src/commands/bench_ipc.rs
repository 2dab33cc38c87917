//! `kfmap bench ipc`: round trips, cov2cov overhead and multi-client throughput of a
//! real `kfmap serve` child process.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::bail;
use indicatif::ProgressBar;
use kfmap_client::{Client, ClientOptions};
use kfmap_protocol::{Cov2CovMode, RequestHeader, RequestKind, ScanPayload, pose_to_wire};
use kfmap_service::server::answer::{Limits, answer};
use kfmap_service::server::session::Session;
use kfmap_service::server::{ServedMap, percentile};
use kfmap_shared::cov::CovOptions;
use serde_json::json;

use super::bench::{keyframe_pose, synthetic_cloud};
use super::server_child::ServerChild;

/// Median and 99th percentile of microsecond samples.
fn p50_p99(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (percentile(&v, 0.5), percentile(&v, 0.99))
}

pub(super) fn start_server(map: &Path, prefix: &str, spin: bool) -> anyhow::Result<ServerChild> {
    ServerChild::start(map, "bench", prefix, if spin { &["--spin"] } else { &[] })
}

fn client(prefix: &str, spin: bool) -> anyhow::Result<Client> {
    Ok(Client::connect(
        "bench",
        ClientOptions {
            iceoryx_prefix: Some(prefix.to_string()),
            timeout: Duration::from_secs(30),
            spin,
        },
    )?)
}

/// The benchmark's request: a 10k-point scan near the middle keyframe (in that
/// keyframe's frame) with its covariances, approximate cov2cov within 1 m.
struct Cov2CovRequest {
    header: RequestHeader,
    points: Vec<[f32; 3]>,
    /// Sent by the client (as its GICP iterations do), or `None`: the default call,
    /// the server estimates them from the scan.
    covariances: Option<Vec<[f32; 6]>>,
}

impl Cov2CovRequest {
    fn new(client_covariances: bool) -> Self {
        let points = synthetic_cloud(1234, 10_000).points;
        let covariances = client_covariances.then(|| {
            kfmap_shared::cov::estimate_covariances(&points, &CovOptions::default()).values
        });
        let header = RequestHeader {
            kind: RequestKind::Cov2Cov as u32,
            pose: pose_to_wire(&keyframe_pose(5)),
            max_pair_dist: 1.0,
            mode: Cov2CovMode::Approximate as u32,
            ..Default::default()
        };
        Self {
            header,
            points,
            covariances,
        }
    }

    fn scan(&self) -> ScanPayload<'_> {
        ScanPayload {
            points: &self.points,
            view_dirs: None,
            covariances: self.covariances.as_deref(),
        }
    }

    /// One round trip, the client reading the pairings in place: (round trip, the
    /// server's own compute time), microseconds.
    fn over_ipc(&self, client: &mut Client) -> anyhow::Result<(f64, f64)> {
        let t = Instant::now();
        let (server_us, pairings) =
            client
                .connection()
                .call_scan_with(self.header, &self.scan(), |h, p| (h.server_us, p.len()))?;
        std::hint::black_box(pairings);
        Ok((t.elapsed().as_secs_f64() * 1e6, server_us))
    }
}

/// Cov2cov requests for `seconds`; latencies in microseconds.
fn hammer(client: &mut Client, seconds: f64) -> anyhow::Result<Vec<f64>> {
    let request = Cov2CovRequest::new(true);
    let mut latencies = Vec::new();
    let started = Instant::now();
    while started.elapsed().as_secs_f64() < seconds {
        latencies.push(request.over_ipc(client)?.0);
    }
    Ok(latencies)
}

/// The same cov2cov request over IPC and through the server's `answer` in this
/// process, alternated call by call for `seconds` so that drift in machine speed
/// touches both alike; microseconds (IPC round trips, the server's compute within
/// them, in process).
fn ipc_against_in_process(
    client: &mut Client,
    map: &Path,
    seconds: f64,
    client_covariances: bool,
) -> anyhow::Result<Overhead> {
    let request = Cov2CovRequest::new(client_covariances);
    let served = ServedMap::open(map, false, 0)?;
    let mut header = request.header;
    let payload = request.scan().encode(&mut header);
    let limits = Limits::default();
    let mut session = Session::new(0);
    let (mut ipc, mut server, mut local) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    while started.elapsed().as_secs_f64() < seconds {
        let (round_trip, server_us) = request.over_ipc(client)?;
        ipc.push(round_trip);
        server.push(server_us);
        let t = Instant::now();
        // The same answer the IPC client reads: pairings in the wire layout.
        let answered = answer(&served, &mut session, &header, &payload, &limits);
        std::hint::black_box(answered.pairings.into_wire());
        local.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok(Overhead {
        ipc: p50_p99(ipc),
        server_compute: p50_p99(server).0,
        local: p50_p99(local),
    })
}

/// Cov2cov over IPC against the same call in process: medians and p99, microseconds.
struct Overhead {
    ipc: (f64, f64),
    server_compute: f64,
    local: (f64, f64),
}

impl Overhead {
    fn percent(&self) -> f64 {
        (self.ipc.0 / self.local.0 - 1.0) * 100.0
    }

    fn json(&self) -> serde_json::Value {
        json!({"ipc_p50_us": self.ipc.0, "ipc_p99_us": self.ipc.1,
            "in_process_p50_us": self.local.0, "in_process_p99_us": self.local.1,
            "server_compute_p50_us": self.server_compute, "overhead_percent": self.percent()})
    }

    fn line(&self, what: &str) -> String {
        format!(
            "cov2cov, 10k-point scan, {what}: IPC median {:.0} us (p99 {:.0}; the server's compute {:.0}), in process {:.0} us (p99 {:.0}): overhead {:.1} %",
            self.ipc.0,
            self.ipc.1,
            self.server_compute,
            self.local.0,
            self.local.1,
            self.percent()
        )
    }
}

/// Pause between isolated echo requests: long enough for both sides to fall asleep.
const ISOLATION: Duration = Duration::from_millis(2);

/// Median and p99 of `reps` echo round trips of `points`, `pause` apart.
fn echo_round_trips(
    client: &mut Client,
    points: &[[f32; 3]],
    reps: usize,
    pause: Duration,
) -> anyhow::Result<(f64, f64)> {
    let mut v = Vec::with_capacity(reps);
    for _ in 0..reps {
        std::thread::sleep(pause);
        let t = Instant::now();
        client.echo(points)?;
        v.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok(p50_p99(v))
}

/// Hidden worker mode: one of the throughput clients.
pub fn worker(prefix: &str, seconds: f64) -> anyhow::Result<()> {
    let mut c = client(prefix, false)?;
    let latencies = hammer(&mut c, seconds)?;
    println!("{}", serde_json::to_string(&latencies)?);
    Ok(())
}

/// How much each measurement repeats: the full run, or a smoke run (`--quick`) whose
/// figures are noisier.
struct Effort {
    /// Echo round trips of 1k and 10k points, and of 100k.
    echo_reps: [usize; 2],
    /// Isolated echo round trips per size.
    isolated_reps: usize,
    /// Seconds of alternating IPC and in-process cov2cov calls.
    alternate_seconds: f64,
    /// Seconds of each throughput phase.
    throughput_seconds: f64,
}

impl Effort {
    fn new(quick: bool) -> Self {
        if quick {
            Self {
                echo_reps: [100, 30],
                isolated_reps: 30,
                alternate_seconds: 1.0,
                throughput_seconds: 1.0,
            }
        } else {
            Self {
                echo_reps: [1000, 200],
                isolated_reps: 200,
                alternate_seconds: 6.0,
                throughput_seconds: 5.0,
            }
        }
    }
}

/// Runs the IPC benchmarks against a synthetic map in `dir`.
pub fn run(
    dir: &Path,
    spin: bool,
    quick: bool,
    json_out: bool,
    bake: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let map = dir.join(format!("kfmap-bench-ipc-{}.kfmap", std::process::id()));
    bake(&map)?;
    let prefix = format!("kfbench{}_", std::process::id());
    let result = measure(&map, &prefix, spin, &Effort::new(quick), json_out);
    let _ = std::fs::remove_file(&map);
    result
}

fn measure(
    map: &Path,
    prefix: &str,
    spin: bool,
    effort: &Effort,
    json_out: bool,
) -> anyhow::Result<()> {
    let bar = if json_out {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    let server = start_server(map, prefix, spin)?;
    let mut c = client(prefix, spin)?;

    let mut echo = Vec::new();
    for n in [1_000usize, 10_000, 100_000] {
        bar.set_message(format!("echo round trips, {n} points"));
        let points = synthetic_cloud(7, n).points;
        let reps = effort.echo_reps[usize::from(n >= 100_000)];
        for _ in 0..20 {
            c.echo(&points)?;
        }
        let back_to_back = echo_round_trips(&mut c, &points, reps, Duration::ZERO)?;
        let isolated = echo_round_trips(&mut c, &points, effort.isolated_reps, ISOLATION)?;
        echo.push((n, back_to_back, isolated));
    }

    bar.set_message("cov2cov over IPC vs in process, alternated");
    let sent = ipc_against_in_process(&mut c, map, effort.alternate_seconds, true)?;
    let estimated = ipc_against_in_process(&mut c, map, effort.alternate_seconds, false)?;

    bar.set_message("throughput: 1 client, then 4 client processes");
    let seconds = effort.throughput_seconds;
    let one = hammer(&mut c, seconds)?;
    let one_rate = one.len() as f64 / seconds;
    let one_p99 = p50_p99(one).1;
    let exe = std::env::current_exe()?;
    let workers: Vec<Child> = (0..4)
        .map(|_| {
            Command::new(&exe)
                .args(["bench", "ipc", "--worker-of", prefix, "--seconds"])
                .arg(seconds.to_string())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit())
                .spawn()
        })
        .collect::<Result<_, _>>()?;
    let mut all = Vec::new();
    for w in workers {
        let out = w.wait_with_output()?;
        if !out.status.success() {
            bail!("a throughput client failed");
        }
        let v: Vec<f64> = serde_json::from_slice(&out.stdout)?;
        all.extend(v);
    }
    let four_rate = all.len() as f64 / seconds;
    let four_p99 = p50_p99(all).1;
    bar.finish_and_clear();
    drop(c);
    drop(server);

    if json_out {
        let echo_json: Vec<_> = echo
            .iter()
            .map(|(n, (p50, p99), (iso_p50, iso_p99))| {
                json!({"points": n, "p50_us": p50, "p99_us": p99,
                    "isolated_p50_us": iso_p50, "isolated_p99_us": iso_p99})
            })
            .collect();
        let out = json!({
            "spin": spin,
            "echo": echo_json,
            "cov2cov_10k": sent.json(),
            "cov2cov_10k_server_covariances": estimated.json(),
            "throughput_10k_cov2cov": {"one_client_scans_per_s": one_rate, "one_client_p99_us": one_p99,
                "four_clients_scans_per_s": four_rate, "four_clients_p99_us": four_p99},
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "IPC round trips ({}):",
        if spin { "spinning" } else { "event waiting" }
    );
    for (n, (p50, p99), (iso_p50, iso_p99)) in &echo {
        println!(
            "  echo {n:>6} points: back to back median {p50:>7.1} us, p99 {p99:>7.1} us; isolated ({} ms apart) median {iso_p50:>7.1} us, p99 {iso_p99:>7.1} us",
            ISOLATION.as_millis()
        );
    }
    println!("{}", sent.line("client-sent covariances"));
    println!(
        "{}",
        estimated.line("the default call (the server estimates covariances)")
    );
    println!(
        "throughput, 10k-point cov2cov: 1 client {one_rate:.1} scans/s (p99 {:.1} ms), 4 client processes {four_rate:.1} scans/s (p99 {:.1} ms)",
        one_p99 / 1e3,
        four_p99 / 1e3
    );
    Ok(())
}
