//! `kfmap bench ipc`: round trips, cov2cov overhead, multi-client throughput and the
//! requests right after a client process was SIGKILLed, of a real `kfmap serve` child
//! process. Also the table's rows of it.

use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use indicatif::ProgressBar;
use kfmap_client::{Client, ClientOptions};
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::percentile::percentile;
use kfmap_protocol::transport::{create_node, iceoryx_config, open_rpc};
use kfmap_protocol::{Cov2CovMode, RequestHeader, RequestKind, ScanPayload, pose_to_wire};
use kfmap_service::server::ServedMap;
use kfmap_service::server::session::Session;
use kfmap_service::server::{Limits, answer};
use nalgebra::Translation3;
use serde_json::json;

use super::child::child_bench;
use super::fixtures::{bake_served_map, keyframe_pose, synthetic_cloud};
use super::table::Table;
use crate::json_number;
use crate::server_child::{BENCH_MAP_NAME, start_bench_server};
use kfmap_geometry::percentile::p99_label;

/// Median and 99th percentile of samples, and how many there were.
#[derive(Debug, Clone, Copy)]
struct Percentiles {
    p50: f64,
    p99: f64,
    samples: usize,
}

/// Median and 99th percentile of microsecond samples.
fn p50_p99(mut v: Vec<f64>) -> Percentiles {
    v.sort_by(f64::total_cmp);
    Percentiles {
        p50: percentile(&v, 0.5),
        p99: percentile(&v, 0.99),
        samples: v.len(),
    }
}

/// Connects to the benchmark server under `prefix`.
fn client(prefix: &str, spin: bool) -> anyhow::Result<Client> {
    Ok(Client::connect(
        BENCH_MAP_NAME,
        ClientOptions {
            iceoryx_prefix: Some(prefix.to_string()),
            timeout: Duration::from_secs(30),
            spin,
        },
    )?)
}

/// The benchmark's request: a 10k-point scan near the middle keyframe (in that
/// keyframe's frame) with its covariances, approximate cov2cov within 1 m, at one of two
/// poses 0.5 m apart, alternately: the server remembers each point's neighbours between
/// a registration's iterations (`NearestMemo`), and the same pose again would measure
/// that recall instead of the searches of a registration's first iteration.
struct Cov2CovRequest {
    headers: [RequestHeader; 2],
    points: Vec<[f32; 3]>,
    /// Sent by the client (as its GICP iterations do), or `None`: the default call,
    /// the server estimates them from the scan.
    covariances: Option<Vec<[f32; 6]>>,
}

impl Cov2CovRequest {
    fn new(client_covariances: bool) -> Self {
        let points = synthetic_cloud(1234, 10_000).points;
        let covariances = client_covariances.then(|| {
            kfmap_geometry::cov::estimate_covariances(&points, &CovOptions::default()).values
        });
        let header = |shift: f64| RequestHeader {
            kind: RequestKind::Cov2Cov as u32,
            pose: pose_to_wire(&(Translation3::new(shift, 0.0, 0.0) * keyframe_pose(5))),
            max_pair_dist: 1.0,
            mode: Cov2CovMode::Approximate as u32,
            ..Default::default()
        };
        Self {
            headers: [header(0.0), header(0.5)],
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

    /// Round trip number `call`, the client reading the pairings in place: (round
    /// trip, the server's own compute time), microseconds.
    fn over_ipc(&self, client: &mut Client, call: usize) -> anyhow::Result<(f64, f64)> {
        let header = self.headers[call % 2];
        let t = Instant::now();
        let (server_us, pairings) =
            client
                .connection()
                .call_scan_with(header, &self.scan(), |h, p| (h.server_us, p.len()))?;
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
        latencies.push(request.over_ipc(client, latencies.len())?.0);
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
    let mut headers = request.headers;
    let payloads = headers.each_mut().map(|h| request.scan().encode(h));
    let limits = Limits::default();
    let mut session = Session::new(0);
    let (mut ipc, mut server, mut local) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    while started.elapsed().as_secs_f64() < seconds {
        let call = ipc.len();
        let (round_trip, server_us) = request.over_ipc(client, call)?;
        ipc.push(round_trip);
        server.push(server_us);
        let (header, payload) = (&headers[call % 2], &payloads[call % 2]);
        let t = Instant::now();
        // The same answer the IPC client reads: pairings in the wire layout.
        let answered = answer(&served, &mut session, header, payload, &limits);
        std::hint::black_box(answered.pairings.into_wire());
        local.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok(Overhead {
        ipc: p50_p99(ipc),
        server_compute: p50_p99(server).p50,
        local: p50_p99(local),
    })
}

/// Cov2cov over IPC against the same call in process: medians and p99, microseconds.
struct Overhead {
    ipc: Percentiles,
    server_compute: f64,
    local: Percentiles,
}

impl Overhead {
    fn percent(&self) -> f64 {
        (self.ipc.p50 / self.local.p50 - 1.0) * 100.0
    }

    fn json(&self) -> serde_json::Value {
        json!({"ipc_p50_us": self.ipc.p50, "ipc_p99_us": self.ipc.p99,
            "in_process_p50_us": self.local.p50, "in_process_p99_us": self.local.p99,
            "server_compute_p50_us": self.server_compute, "overhead_percent": self.percent()})
    }

    fn line(&self, what: &str) -> String {
        format!(
            "cov2cov, 10k-point scan, {what}: IPC median {:.0} us ({} {:.0}; the server's compute {:.0}), in process {:.0} us ({} {:.0}): overhead {:.1} %",
            self.ipc.p50,
            p99_label(self.ipc.samples),
            self.ipc.p99,
            self.server_compute,
            self.local.p50,
            p99_label(self.local.samples),
            self.local.p99,
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
) -> anyhow::Result<Percentiles> {
    let mut v = Vec::with_capacity(reps);
    for _ in 0..reps {
        std::thread::sleep(pause);
        let t = Instant::now();
        client.echo(points)?;
        v.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok(p50_p99(v))
}

/// The hidden `kfmap bench ipc-worker PREFIX --seconds S`: one of the throughput
/// clients; prints its latencies (microseconds) as JSON.
pub(super) fn worker(prefix: &str, seconds: f64) -> anyhow::Result<()> {
    let mut c = client(prefix, false)?;
    let latencies = hammer(&mut c, seconds)?;
    println!("{}", serde_json::to_string(&latencies)?);
    Ok(())
}

/// Client ports of the process the bench kills: 63, the case that stalled every other
/// client for 1.8-3.3 s when iceoryx2 scanned a 16 times larger chunk table per dead
/// connection on the request path (tests/integration/hostile.rs checks the behaviour).
const KILLED_PORTS: usize = 63;

/// Seconds of requests after the kill.
const AFTER_KILL_SECONDS: f64 = 3.0;

/// The hidden `kfmap bench ipc-holder PREFIX --ports N`: opens `ports` raw client ports
/// to the server of `prefix`, says so, and waits to be killed (10 minutes at most).
pub(super) fn holder(prefix: &str, ports: usize) -> anyhow::Result<()> {
    let config = iceoryx_config(Some(prefix))?;
    let mut held = Vec::with_capacity(ports);
    for _ in 0..ports {
        let node = create_node(&config, "holder")?;
        let port = open_rpc(&node, BENCH_MAP_NAME)?
            .client_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("client port: {e:?}"))?;
        held.push((port, node));
    }
    println!("ports open: {}", held.len());
    std::thread::sleep(Duration::from_secs(600));
    Ok(())
}

/// A child process, SIGKILLed when dropped (an error leaves none behind).
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Echo requests of one client in the [`AFTER_KILL_SECONDS`] after another client
/// process holding [`KILLED_PORTS`] ports was SIGKILLed, 10 ms apart.
struct AfterKill {
    requests: usize,
    /// Slowest round trip, milliseconds.
    slowest_ms: f64,
}

/// Starts a port holder (`kfmap bench ipc-holder`), kills it once its ports are open,
/// and times `c`'s requests while the server reclaims the dead ports.
fn after_killed_client(c: &mut Client, prefix: &str) -> anyhow::Result<AfterKill> {
    let exe = std::env::current_exe()?;
    let mut holder = Killed(
        Command::new(exe)
            .args(["bench", "ipc-holder", prefix, "--ports"])
            .arg(KILLED_PORTS.to_string())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()?,
    );
    let stdout = holder.0.stdout.take().context("the port holder's stdout")?;
    let mut said = String::new();
    // The holder prints one line, or exits (end of file) on an error.
    std::io::BufReader::new(stdout).read_line(&mut said)?;
    if said.trim() != format!("ports open: {KILLED_PORTS}") {
        bail!("the port holder did not open its ports: {said:?}");
    }
    let points = synthetic_cloud(7, 1_000).points;
    c.echo(&points)?;
    drop(holder);
    let started = Instant::now();
    let (mut requests, mut slowest) = (0, Duration::ZERO);
    while started.elapsed().as_secs_f64() < AFTER_KILL_SECONDS {
        let t = Instant::now();
        c.echo(&points)?;
        slowest = slowest.max(t.elapsed());
        requests += 1;
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(AfterKill {
        requests,
        slowest_ms: slowest.as_secs_f64() * 1e3,
    })
}

/// Starts a throughput client process (`kfmap bench ipc-worker`) against the server of
/// `prefix` for `seconds`; its stdout is piped.
fn spawn_worker(exe: &Path, prefix: &str, seconds: f64) -> std::io::Result<Child> {
    Command::new(exe)
        .args(["bench", "ipc-worker", prefix, "--seconds"])
        .arg(seconds.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
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

/// Runs `kfmap bench ipc` against a synthetic map baked in `dir`.
pub(super) fn run(dir: &Path, spin: bool, quick: bool, json_out: bool) -> anyhow::Result<()> {
    let map = dir.join(format!("kfmap-bench-ipc-{}.kfmap", std::process::id()));
    bake_served_map(&map)?;
    let prefix = format!("kfbench{}_", std::process::id());
    let result = measure(&map, &prefix, spin, &Effort::new(quick), json_out);
    let _ = std::fs::remove_file(&map);
    result
}

/// Echo round trips of one size, back to back and isolated.
struct Echo {
    points: usize,
    back_to_back: Percentiles,
    isolated: Percentiles,
}

/// Cov2cov throughput of one client, then of four client processes at once.
struct Throughput {
    /// Scans per second of one client.
    one_rate: f64,
    one: Percentiles,
    /// Scans per second of the four together.
    four_rate: f64,
    four: Percentiles,
}

/// Everything `kfmap bench ipc` measured.
struct IpcFigures {
    spin: bool,
    echo: Vec<Echo>,
    /// Cov2cov with client-sent covariances.
    sent: Overhead,
    /// Cov2cov with the server estimating the covariances.
    estimated: Overhead,
    throughput: Throughput,
    after_kill: AfterKill,
}

/// Serves `map` under `prefix`, measures echo, cov2cov overhead and throughput, and
/// prints the figures.
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
    let server = start_bench_server(map, prefix, spin)?;
    let mut c = client(prefix, spin)?;
    let echo = echo_sizes(&mut c, effort, &bar)?;
    bar.set_message("cov2cov over IPC vs in process, alternated");
    let sent = ipc_against_in_process(&mut c, map, effort.alternate_seconds, true)?;
    let estimated = ipc_against_in_process(&mut c, map, effort.alternate_seconds, false)?;
    bar.set_message("throughput: 1 client, then 4 client processes");
    let throughput = throughput(&mut c, prefix, effort.throughput_seconds)?;
    bar.set_message(format!(
        "requests after a client process with {KILLED_PORTS} ports was killed"
    ));
    let after_kill = after_killed_client(&mut c, prefix)?;
    bar.finish_and_clear();
    drop(c);
    drop(server);
    let figures = IpcFigures {
        spin,
        echo,
        sent,
        estimated,
        throughput,
        after_kill,
    };
    if json_out {
        println!("{}", serde_json::to_string_pretty(&figures.json())?);
    } else {
        figures.print();
    }
    Ok(())
}

/// Echo round trips of 1k, 10k and 100k points (after 20 unmeasured ones each), back
/// to back and [`ISOLATION`] apart.
fn echo_sizes(c: &mut Client, effort: &Effort, bar: &ProgressBar) -> anyhow::Result<Vec<Echo>> {
    let mut echo = Vec::new();
    for n in [1_000usize, 10_000, 100_000] {
        bar.set_message(format!("echo round trips, {n} points"));
        let points = synthetic_cloud(7, n).points;
        let reps = effort.echo_reps[usize::from(n >= 100_000)];
        for _ in 0..20 {
            c.echo(&points)?;
        }
        let back_to_back = echo_round_trips(c, &points, reps, Duration::ZERO)?;
        let isolated = echo_round_trips(c, &points, effort.isolated_reps, ISOLATION)?;
        echo.push(Echo {
            points: n,
            back_to_back,
            isolated,
        });
    }
    Ok(echo)
}

/// Cov2cov back to back for `seconds` from this client, then from four
/// `kfmap bench ipc-worker` processes at once.
fn throughput(c: &mut Client, prefix: &str, seconds: f64) -> anyhow::Result<Throughput> {
    let one = hammer(c, seconds)?;
    let one_rate = one.len() as f64 / seconds;
    let one = p50_p99(one);
    let exe = std::env::current_exe()?;
    let workers: Vec<Child> = (0..4)
        .map(|_| spawn_worker(&exe, prefix, seconds))
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
    Ok(Throughput {
        one_rate,
        one,
        four_rate,
        four: p50_p99(all),
    })
}

impl IpcFigures {
    /// `--json`'s object.
    fn json(&self) -> serde_json::Value {
        let echo_json: Vec<_> = self
            .echo
            .iter()
            .map(|e| {
                json!({"points": e.points, "p50_us": e.back_to_back.p50, "p99_us": e.back_to_back.p99,
                    "isolated_p50_us": e.isolated.p50, "isolated_p99_us": e.isolated.p99})
            })
            .collect();
        let t = &self.throughput;
        json!({
            "spin": self.spin,
            "echo": echo_json,
            "cov2cov_10k": self.sent.json(),
            "cov2cov_10k_server_covariances": self.estimated.json(),
            "throughput_10k_cov2cov": {"one_client_scans_per_s": t.one_rate, "one_client_p99_us": t.one.p99,
                "four_clients_scans_per_s": t.four_rate, "four_clients_p99_us": t.four.p99},
            "after_killed_client": {"ports": KILLED_PORTS, "seconds": AFTER_KILL_SECONDS,
                "requests": self.after_kill.requests, "slowest_ms": self.after_kill.slowest_ms},
        })
    }

    /// Prints the figures for people.
    fn print(&self) {
        println!(
            "IPC round trips ({}):",
            if self.spin {
                "spinning"
            } else {
                "event waiting"
            }
        );
        for e in &self.echo {
            let (b, i) = (&e.back_to_back, &e.isolated);
            println!(
                "  echo {:>6} points: back to back median {:>7.1} us, {} {:>7.1} us; isolated ({} ms apart) median {:>7.1} us, {} {:>7.1} us",
                e.points,
                b.p50,
                p99_label(b.samples),
                b.p99,
                ISOLATION.as_millis(),
                i.p50,
                p99_label(i.samples),
                i.p99
            );
        }
        println!("{}", self.sent.line("client-sent covariances"));
        println!(
            "{}",
            self.estimated
                .line("the default call (the server estimates covariances)")
        );
        let t = &self.throughput;
        println!(
            "throughput, 10k-point cov2cov: 1 client {:.1} scans/s ({} {:.1} ms), 4 client processes {:.1} scans/s ({} {:.1} ms)",
            t.one_rate,
            p99_label(t.one.samples),
            t.one.p99 / 1e3,
            t.four_rate,
            p99_label(t.four.samples),
            t.four.p99 / 1e3
        );
        println!(
            "after a client process with {KILLED_PORTS} ports was SIGKILLed: {} echo requests in {AFTER_KILL_SECONDS} s, slowest {:.1} ms",
            self.after_kill.requests, self.after_kill.slowest_ms
        );
    }
}

/// The table's IPC rows: `kfmap bench ipc` in a child process.
pub(super) fn table_rows(table: &mut Table, dir: &Path) -> anyhow::Result<()> {
    table.stage("IPC round trips and throughput (kfmap serve child)");
    let dir = dir.display().to_string();
    let mut args = vec!["ipc", "--dir", &dir];
    if table.quick {
        args.push("--quick");
    }
    let v = child_bench(&args)?;
    let label = "synthetic map, 12 keyframes x 40 000 points; kfmap serve child";
    for echo in v["echo"].as_array().into_iter().flatten() {
        let name = format!("IPC round trip (echo), {} points, median", echo["points"]);
        table.push(&name, label, 1, json_number(&echo["p50_us"]), "us");
    }
    let c = &v["cov2cov_10k"];
    table.push(
        "cov2cov of a 10k-point scan over IPC, median",
        label,
        1,
        json_number(&c["ipc_p50_us"]) / 1e3,
        "ms",
    );
    table.push(
        "  the same call in process, median",
        label,
        1,
        json_number(&c["in_process_p50_us"]) / 1e3,
        "ms",
    );
    let t = &v["throughput_10k_cov2cov"];
    table.push(
        "cov2cov throughput, 1 client",
        label,
        1,
        json_number(&t["one_client_scans_per_s"]),
        "scans/s",
    );
    table.push(
        "cov2cov throughput, 4 client processes",
        label,
        4,
        json_number(&t["four_clients_scans_per_s"]),
        "scans/s",
    );
    let k = &v["after_killed_client"];
    table.push(
        &format!(
            "slowest request in the {AFTER_KILL_SECONDS} s after a client process with {KILLED_PORTS} ports was SIGKILLed"
        ),
        label,
        1,
        json_number(&k["slowest_ms"]),
        "ms",
    );
    Ok(())
}
