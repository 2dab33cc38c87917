//! `kfmap bench soak`: client processes at a fixed rate against a real `kfmap serve`
//! for minutes, with large scans and every request kind, watching the server's memory,
//! failures, lost answers and what is left in shared memory afterwards. With `--flood`
//! it also measures overload: a polite 1 Hz client's latency alone, then while other
//! processes send back to back.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_client::{Client, ClientError, ClientOptions, LocalizeOptions};
use kfmap_protocol::transport::{iceoryx_config, prefix_files};
use kfmap_protocol::{Cov2CovMode, ScanPayload, StatusCode};
use kfmap_service::server::percentile;
use kfmap_shared::geometry::Pose;
use kfmap_shared::imu::ImuSample;
use nalgebra::Vector3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use serde_json::json;

use super::bench::{keyframe_pose, synthetic_cloud};
use super::bench_ipc::start_server;
use super::server_child::ServerChild;

/// What one soak client did.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct ClientReport {
    /// Round trips of answered requests, milliseconds, by kind.
    pub latencies_ms: BTreeMap<String, Vec<f64>>,
    /// Requests sent.
    pub requests: u64,
    /// Answered with an error status other than `Busy`, or failed in the transport.
    pub failed: u64,
    /// Refused with `Busy` (the server's budget was held by others: overload).
    pub busy: u64,
    /// Never answered within the timeout.
    pub lost: u64,
    /// The first few failures, for the report.
    pub errors: Vec<String>,
}

impl ClientReport {
    fn record(&mut self, kind: &str, started: Instant, result: Result<(), ClientError>) {
        self.requests += 1;
        match result {
            Ok(()) => self
                .latencies_ms
                .entry(kind.to_string())
                .or_default()
                .push(started.elapsed().as_secs_f64() * 1e3),
            Err(ClientError::Timeout { .. }) => self.lost += 1,
            Err(e) if e.status() == Some(StatusCode::Busy) => self.busy += 1,
            Err(e) => {
                self.failed += 1;
                if self.errors.len() < 5 {
                    self.errors.push(format!("{kind}: {e}"));
                }
            }
        }
    }

    fn merge(&mut self, other: ClientReport) {
        for (kind, v) in other.latencies_ms {
            self.latencies_ms.entry(kind).or_default().extend(v);
        }
        self.requests += other.requests;
        self.failed += other.failed;
        self.busy += other.busy;
        self.lost += other.lost;
        self.errors.extend(other.errors);
    }

    fn all_latencies(&self) -> Vec<f64> {
        self.latencies_ms.values().flatten().copied().collect()
    }
}

/// How one soak client behaves.
#[derive(Debug, Clone, Copy)]
pub struct ClientPlan {
    /// Requests per second (0: back to back).
    pub rate_hz: f64,
    /// Seconds to run.
    pub seconds: f64,
    /// Seed of its scans and its share of the request mix.
    pub seed: u64,
}

/// Request kinds, in the order a client cycles through them: cov2cov (a client-side
/// GICP's iterations) most often, server-side localization, neighbours, an IMU window
/// and a status now and then.
const MIX: [&str; 10] = [
    "cov2cov", "nearest", "cov2cov", "localize", "cov2cov", "imu", "radius", "cov2cov", "nearest",
    "status",
];

/// Runs one soak client against the server of `prefix`.
pub fn run_client(prefix: &str, plan: ClientPlan) -> anyhow::Result<ClientReport> {
    let mut client = Client::connect(
        "bench",
        ClientOptions {
            iceoryx_prefix: Some(prefix.to_string()),
            timeout: Duration::from_secs(30),
            spin: false,
        },
    )?;
    let mut rng = SmallRng::seed_from_u64(plan.seed);
    // A few scans of 30k-120k points, reused (generating one costs more than a request).
    let scans: Vec<Vec<[f32; 3]>> = (0..4)
        .map(|i| synthetic_cloud(plan.seed * 10 + i, rng.random_range(30_000..=120_000)).points)
        .collect();
    let mut report = ClientReport::default();
    let started = Instant::now();
    let period = (plan.rate_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / plan.rate_hz));
    let mut next = Instant::now();
    let mut k = plan.seed as usize;
    while started.elapsed().as_secs_f64() < plan.seconds {
        let kind = MIX[k % MIX.len()];
        let points = &scans[k % scans.len()];
        let pose = keyframe_pose(5 + k % 3)
            * Pose::new(
                Vector3::new(
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.2..0.2),
                    0.0,
                ),
                Vector3::zeros(),
            );
        let t = Instant::now();
        let result = request(&mut client, kind, points, &pose, k as u64, started);
        report.record(kind, t, result);
        k += 1;
        if let Some(period) = period {
            next += period;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                // Behind (the server is slower than the rate): no catching-up burst.
                next = now;
            }
        }
    }
    Ok(report)
}

fn request(
    client: &mut Client,
    kind: &str,
    points: &[[f32; 3]],
    pose: &Pose,
    id: u64,
    started: Instant,
) -> Result<(), ClientError> {
    let scan = ScanPayload {
        points,
        view_dirs: None,
        covariances: None,
    };
    match kind {
        "cov2cov" => client
            .cov2cov_with(&scan, pose, 1.0, Cov2CovMode::Approximate, |_, p| p.len())
            .map(drop),
        "nearest" => client.nearest(points, pose, 1).map(drop),
        "radius" => client
            .radius(&points[..points.len() / 4], pose, 0.2)
            .map(drop),
        "localize" => client
            .localize(&scan, pose, &LocalizeOptions::default())
            .map(drop),
        "imu" => {
            let t0 = started.elapsed().as_secs_f64();
            let samples: Vec<ImuSample> = (0..50)
                .map(|i| ImuSample {
                    t: t0 + i as f64 * 0.01,
                    acc: [0.0, 0.0, 9.81],
                    gyro: [0.0; 3],
                })
                .collect();
            client.push_imu_window(id, pose, None, &samples).map(drop)
        }
        _ => client.status().map(drop),
    }
}

/// Resident memory of a process, MiB: in all, and its parts (NaN when unreadable).
#[derive(Debug, Clone, Copy)]
struct Rss {
    /// `VmRSS`.
    total: f64,
    /// `RssAnon`: the heap and stacks, where a leak would show.
    anon: f64,
    /// `RssFile`: pages of the memory-mapped map touched so far.
    file: f64,
    /// `RssShmem`: iceoryx2 segments (they grow with the largest answer, never shrink).
    shmem: f64,
}

fn rss_mib(pid: u32) -> Rss {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
            .map_or(f64::NAN, |kib| kib / 1024.0)
    };
    Rss {
        total: field("VmRSS:"),
        anon: field("RssAnon:"),
        file: field("RssFile:"),
        shmem: field("RssShmem:"),
    }
}

impl Rss {
    fn json(&self) -> serde_json::Value {
        json!({"total_mb": self.total, "anon_mb": self.anon, "file_mb": self.file, "shmem_mb": self.shmem})
    }

    fn line(&self) -> String {
        format!(
            "{:.0} MiB (heap {:.0}, map file {:.0}, shared memory {:.0})",
            self.total, self.anon, self.file, self.shmem
        )
    }
}

/// The soak's figures.
struct Soak {
    clients: usize,
    seconds: f64,
    report: ClientReport,
    rss_start: Rss,
    rss_end: Rss,
    rss_max_mb: f64,
    leftover: Vec<String>,
    overload: Option<Overload>,
}

/// A polite client's latency alone and while others flood.
struct Overload {
    flooders: usize,
    polite_alone_p50_ms: f64,
    polite_flooded_p50_ms: f64,
    polite_alone_p99_ms: f64,
    polite_flooded_p99_ms: f64,
    polite_flooded_failed: u64,
    flood_requests: u64,
    flood_busy: u64,
    rss_max_mb: f64,
}

fn spawn_clients(prefix: &str, plans: &[ClientPlan]) -> anyhow::Result<Vec<Child>> {
    let exe = std::env::current_exe()?;
    plans
        .iter()
        .map(|p| {
            Command::new(&exe)
                .args(["bench", "soak", "--client-of", prefix])
                .args(["--rate", &p.rate_hz.to_string()])
                .args(["--seconds", &p.seconds.to_string()])
                .args(["--seed", &p.seed.to_string()])
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit())
                .spawn()
                .context("start a soak client")
        })
        .collect()
}

/// Each client's report, in spawning order.
fn reports(children: Vec<Child>) -> anyhow::Result<Vec<ClientReport>> {
    children
        .into_iter()
        .map(|child| {
            let out = child.wait_with_output()?;
            if !out.status.success() {
                bail!("a soak client failed ({})", out.status);
            }
            Ok(serde_json::from_slice(&out.stdout)?)
        })
        .collect()
}

/// The clients' reports merged into one.
fn merged(reports: Vec<ClientReport>) -> ClientReport {
    reports
        .into_iter()
        .fold(ClientReport::default(), |mut all, r| {
            all.merge(r);
            all
        })
}

/// Samples the server's memory once a second for `seconds` (the clients' run); MiB.
fn watch(server: &ServerChild, seconds: f64, bar: &ProgressBar) -> Vec<Rss> {
    let pid = server.pid();
    let mut samples = Vec::new();
    let started = Instant::now();
    loop {
        samples.push(rss_mib(pid));
        bar.set_position(started.elapsed().as_secs().min(seconds as u64));
        if started.elapsed().as_secs_f64() > seconds {
            break;
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    samples
}

fn p99(v: Vec<f64>) -> f64 {
    percentile_ms(v, 0.99)
}

fn percentile_ms(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    percentile(&v, q)
}

/// Runs the soak: `clients` processes at `rate` Hz for `seconds`, then, with
/// `flood` > 0, the overload phase.
pub fn run(
    map: &Path,
    clients: usize,
    seconds: f64,
    rate: f64,
    flood: usize,
    json_out: bool,
) -> anyhow::Result<bool> {
    let prefix = format!("kfsoak{}_", std::process::id());
    let server = start_server(map, &prefix, false)?;
    let bar = if json_out {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(seconds as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} s")?.progress_chars("=> "),
    );
    bar.set_message(format!("soak: {clients} clients at {rate} Hz"));
    let plans: Vec<ClientPlan> = (0..clients)
        .map(|i| ClientPlan {
            rate_hz: rate,
            seconds,
            seed: i as u64 + 1,
        })
        .collect();
    let children = spawn_clients(&prefix, &plans)?;
    let samples = watch(&server, seconds, &bar);
    let report = merged(reports(children)?);
    // Start: after the first tenth of the run (every client has sent every kind of
    // request, the map's pages are in use and the segments have grown).
    let warm = samples
        .len()
        .min(((seconds * 0.1).ceil() as usize).clamp(1, 60));
    let rss_start = samples
        .get(warm)
        .or(samples.last())
        .copied()
        .unwrap_or(rss_mib(server.pid()));
    let rss_end = rss_mib(server.pid());
    let mut rss_max_mb = samples
        .iter()
        .map(|r| r.total)
        .fold(rss_end.total, f64::max);

    let overload = if flood > 0 {
        let phase = (seconds / 2.0).max(5.0);
        bar.set_message("overload: a 1 Hz client alone");
        let polite = ClientPlan {
            rate_hz: 1.0,
            seconds: phase,
            seed: 100,
        };
        let alone = merged(reports(spawn_clients(&prefix, &[polite])?)?);
        bar.set_message(format!("overload: the 1 Hz client while {flood} flood"));
        let mut plans = vec![polite];
        plans.extend((0..flood).map(|i| ClientPlan {
            rate_hz: 0.0,
            seconds: phase,
            seed: 200 + i as u64,
        }));
        let children = spawn_clients(&prefix, &plans)?;
        let flood_samples = watch(&server, phase, &bar);
        let mut outcomes = reports(children)?;
        let polite_flooded = outcomes.remove(0);
        let flooders = merged(outcomes);
        let max = flood_samples
            .iter()
            .map(|r| r.total)
            .fold(f64::NAN, f64::max);
        rss_max_mb = rss_max_mb.max(max);
        Some(Overload {
            flooders: flood,
            polite_alone_p50_ms: percentile_ms(alone.all_latencies(), 0.5),
            polite_flooded_p50_ms: percentile_ms(polite_flooded.all_latencies(), 0.5),
            polite_alone_p99_ms: p99(alone.all_latencies()),
            polite_flooded_p99_ms: p99(polite_flooded.all_latencies()),
            polite_flooded_failed: polite_flooded.failed + polite_flooded.lost,
            flood_requests: flooders.requests,
            flood_busy: flooders.busy,
            rss_max_mb: max,
        })
    } else {
        None
    };
    bar.finish_and_clear();
    drop(server);
    let soak = Soak {
        clients,
        seconds,
        report,
        rss_start,
        rss_end,
        rss_max_mb,
        leftover: iceoryx_config(Some(&prefix))
            .map(|config| prefix_files(&config, &prefix))
            .unwrap_or_default()
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        overload,
    };
    print(&soak, json_out)?;
    Ok(soak.report.failed == 0 && soak.report.lost == 0 && soak.leftover.is_empty())
}

fn print(s: &Soak, json_out: bool) -> anyhow::Result<()> {
    let r = &s.report;
    let per_kind: BTreeMap<&String, serde_json::Value> = r
        .latencies_ms
        .iter()
        .map(|(kind, v)| {
            let mut v = v.clone();
            v.sort_by(f64::total_cmp);
            let figures = json!({"count": v.len(), "p50_ms": percentile(&v, 0.5), "p99_ms": percentile(&v, 0.99)});
            (kind, figures)
        })
        .collect();
    let overall_p99 = p99(r.all_latencies());
    if json_out {
        let overload = s.overload.as_ref().map(|o| {
            json!({"flooders": o.flooders,
                "polite_alone_p50_ms": o.polite_alone_p50_ms, "polite_flooded_p50_ms": o.polite_flooded_p50_ms,
                "polite_alone_p99_ms": o.polite_alone_p99_ms,
                "polite_flooded_p99_ms": o.polite_flooded_p99_ms,
                "polite_flooded_failed": o.polite_flooded_failed,
                "flood_requests": o.flood_requests, "flood_busy": o.flood_busy,
                "rss_max_mb": o.rss_max_mb})
        });
        let out = json!({
            "clients": s.clients, "seconds": s.seconds,
            "requests": r.requests, "failed": r.failed, "lost": r.lost, "busy": r.busy,
            "errors": r.errors,
            "rss_start_mb": s.rss_start.total, "rss_end_mb": s.rss_end.total, "rss_max_mb": s.rss_max_mb,
            "rss_start": s.rss_start.json(), "rss_end": s.rss_end.json(),
            "p99_ms": overall_p99, "per_kind": per_kind,
            "leftover_shared_memory": s.leftover,
            "overload": overload,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "soak: {} client processes, {:.0} s: {} requests, {} failed, {} lost, {} busy; p99 {:.1} ms",
        s.clients, s.seconds, r.requests, r.failed, r.lost, r.busy, overall_p99
    );
    for (kind, f) in &per_kind {
        let ms = |key: &str| f[key].as_f64().unwrap_or(f64::NAN);
        println!(
            "  {kind:>8}: {} answered, p50 {:.1} ms, p99 {:.1} ms",
            f["count"],
            ms("p50_ms"),
            ms("p99_ms")
        );
    }
    println!(
        "server RSS: {} after warm-up, {} at the end ({:+.1} %), {:.0} MiB at most",
        s.rss_start.line(),
        s.rss_end.line(),
        (s.rss_end.total / s.rss_start.total - 1.0) * 100.0,
        s.rss_max_mb
    );
    println!(
        "shared memory left after shutdown: {}",
        if s.leftover.is_empty() {
            "none".to_string()
        } else {
            s.leftover.join(", ")
        }
    );
    for e in &r.errors {
        println!("  error: {e}");
    }
    if let Some(o) = &s.overload {
        println!(
            "overload: a 1 Hz client's p50 / p99 {:.1} / {:.1} ms alone, {:.1} / {:.1} ms while {} processes flood ({} failed); the flood sent {} requests, {} refused busy; server RSS at most {:.0} MiB",
            o.polite_alone_p50_ms,
            o.polite_alone_p99_ms,
            o.polite_flooded_p50_ms,
            o.polite_flooded_p99_ms,
            o.flooders,
            o.polite_flooded_failed,
            o.flood_requests,
            o.flood_busy,
            o.rss_max_mb
        );
    }
    Ok(())
}
