//! `kfmap bench soak`: client processes at a fixed rate against a real `kfmap serve`
//! for minutes, with large scans and every request kind, watching the server's memory,
//! failures, lost answers and what is left in shared memory afterwards. With `--flood`
//! it also measures overload: a polite 1 Hz client's latency alone, then while other
//! processes send back to back.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Child;
use std::time::{Duration, Instant};

use anyhow::bail;
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_geometry::percentile::percentile;
use kfmap_protocol::transport::{iceoryx_config, prefix_files};
use serde_json::json;

use super::fixtures::bake_served_map;
use super::soak_client::{self, ClientPlan, ClientReport};
use crate::server_child::{ServerChild, start_bench_server};
use kfmap_geometry::percentile::p99_label;

/// What `kfmap bench soak` runs.
#[derive(Debug, Clone, Copy)]
pub(super) struct SoakPlan {
    /// Client processes.
    pub clients: usize,
    /// Seconds the clients run.
    pub seconds: f64,
    /// Requests per second of each client (0: back to back).
    pub rate: f64,
    /// Processes flooding the server in the overload phase (0: no such phase).
    pub flood: usize,
}

/// Runs `kfmap bench soak` on a synthetic map baked in `dir`: an error when any request
/// failed or was lost, or shared memory was left behind.
pub(super) fn run(dir: &Path, plan: SoakPlan, json_out: bool) -> anyhow::Result<()> {
    if !(plan.seconds.is_finite() && plan.seconds >= 1.0) {
        bail!("--seconds must be at least 1");
    }
    if !(plan.rate.is_finite() && (0.0..=1000.0).contains(&plan.rate)) {
        bail!("--rate must be within 0 (back to back) to 1000 requests per second");
    }
    let map = dir.join(format!("kfmap-bench-soak-{}.kfmap", std::process::id()));
    bake_served_map(&map)?;
    let passed = soak(&map, plan, json_out);
    let _ = std::fs::remove_file(&map);
    if !passed? {
        bail!("the soak failed: requests failed or were lost, or shared memory was left behind");
    }
    Ok(())
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

/// The resident memory of process `pid`, from /proc.
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
    /// Answered requests of the polite client alone, and while flooded.
    polite_alone_samples: usize,
    polite_flooded_samples: usize,
    polite_flooded_failed: u64,
    flood_requests: u64,
    flood_busy: u64,
    rss_max_mb: f64,
}

/// The steady phase's figures: every client's requests, and the server's memory.
struct Steady {
    report: ClientReport,
    rss_start: Rss,
    rss_end: Rss,
    rss_max_mb: f64,
}

/// Starts one client process per plan.
fn spawn_clients(prefix: &str, plans: &[ClientPlan]) -> anyhow::Result<Vec<Child>> {
    let exe = std::env::current_exe()?;
    plans
        .iter()
        .map(|p| soak_client::spawn(&exe, prefix, p))
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

/// The nearest-rank 99th percentile of samples.
fn p99(v: Vec<f64>) -> f64 {
    percentile_ms(v, 0.99)
}

/// The nearest-rank `q`-percentile of samples.
fn percentile_ms(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    kfmap_geometry::percentile::percentile(&v, q)
}

/// Runs the soak on `map`: `clients` processes at `rate` Hz for `seconds`, then, with
/// `flood` > 0, the overload phase; prints the figures and returns whether it passed.
fn soak(map: &Path, plan: SoakPlan, json_out: bool) -> anyhow::Result<bool> {
    let prefix = format!("kfsoak{}_", std::process::id());
    let server = start_bench_server(map, &prefix, false)?;
    let bar = if json_out {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(plan.seconds as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} s")?.progress_chars("=> "),
    );
    let steady = steady_phase(&server, &prefix, plan, &bar)?;
    let overload = if plan.flood > 0 {
        Some(overload_phase(
            &server,
            &prefix,
            plan.seconds,
            plan.flood,
            &bar,
        )?)
    } else {
        None
    };
    bar.finish_and_clear();
    drop(server);
    let soak = Soak {
        clients: plan.clients,
        seconds: plan.seconds,
        report: steady.report,
        rss_start: steady.rss_start,
        rss_end: steady.rss_end,
        rss_max_mb: overload
            .as_ref()
            .map_or(steady.rss_max_mb, |o| steady.rss_max_mb.max(o.rss_max_mb)),
        leftover: leftover_files(&prefix),
        overload,
    };
    print(&soak, json_out)?;
    Ok(soak.report.failed == 0 && soak.report.lost == 0 && soak.leftover.is_empty())
}

/// The clients of `plan` against the server, its memory sampled every second: their
/// merged report, and the server's memory after warm-up, at the end and at most.
fn steady_phase(
    server: &ServerChild,
    prefix: &str,
    plan: SoakPlan,
    bar: &ProgressBar,
) -> anyhow::Result<Steady> {
    bar.set_message(format!(
        "soak: {} clients at {} Hz",
        plan.clients, plan.rate
    ));
    let plans: Vec<ClientPlan> = (0..plan.clients)
        .map(|i| ClientPlan {
            rate_hz: plan.rate,
            seconds: plan.seconds,
            seed: i as u64 + 1,
        })
        .collect();
    let children = spawn_clients(prefix, &plans)?;
    let samples = watch(server, plan.seconds, bar);
    let report = merged(reports(children)?);
    // Start: after the first tenth of the run (every client has sent every kind of
    // request, the map's pages are in use and the segments have grown).
    let warm = samples
        .len()
        .min(((plan.seconds * 0.1).ceil() as usize).clamp(1, 60));
    let rss_start = samples
        .get(warm)
        .or(samples.last())
        .copied()
        .unwrap_or(rss_mib(server.pid()));
    let rss_end = rss_mib(server.pid());
    let rss_max_mb = samples
        .iter()
        .map(|r| r.total)
        .fold(rss_end.total, f64::max);
    Ok(Steady {
        report,
        rss_start,
        rss_end,
        rss_max_mb,
    })
}

/// The overload phase, half the soak's `seconds` (at least 5): a 1 Hz client alone,
/// then the same client while `flood` processes send back to back.
fn overload_phase(
    server: &ServerChild,
    prefix: &str,
    seconds: f64,
    flood: usize,
    bar: &ProgressBar,
) -> anyhow::Result<Overload> {
    let phase = (seconds / 2.0).max(5.0);
    bar.set_message("overload: a 1 Hz client alone");
    let polite = ClientPlan {
        rate_hz: 1.0,
        seconds: phase,
        seed: 100,
    };
    let alone = merged(reports(spawn_clients(prefix, &[polite])?)?);
    bar.set_message(format!("overload: the 1 Hz client while {flood} flood"));
    let mut plans = vec![polite];
    plans.extend((0..flood).map(|i| ClientPlan {
        rate_hz: 0.0,
        seconds: phase,
        seed: 200 + i as u64,
    }));
    let children = spawn_clients(prefix, &plans)?;
    let flood_samples = watch(server, phase, bar);
    let mut outcomes = reports(children)?;
    let polite_flooded = outcomes.remove(0);
    let flooders = merged(outcomes);
    let max = flood_samples
        .iter()
        .map(|r| r.total)
        .fold(f64::NAN, f64::max);
    Ok(Overload {
        flooders: flood,
        polite_alone_p50_ms: percentile_ms(alone.all_latencies(), 0.5),
        polite_flooded_p50_ms: percentile_ms(polite_flooded.all_latencies(), 0.5),
        polite_alone_p99_ms: p99(alone.all_latencies()),
        polite_flooded_p99_ms: p99(polite_flooded.all_latencies()),
        polite_alone_samples: alone.all_latencies().len(),
        polite_flooded_samples: polite_flooded.all_latencies().len(),
        polite_flooded_failed: polite_flooded.failed + polite_flooded.lost,
        flood_requests: flooders.requests,
        flood_busy: flooders.busy,
        rss_max_mb: max,
    })
}

/// The iceoryx2 files of `prefix` still in shared memory.
fn leftover_files(prefix: &str) -> Vec<String> {
    iceoryx_config(Some(prefix))
        .map(|config| prefix_files(&config, prefix))
        .unwrap_or_default()
        .iter()
        .map(|p| p.display().to_string())
        .collect()
}

/// Count, p50 and p99 of each request kind's latencies.
fn per_kind(r: &ClientReport) -> BTreeMap<&String, serde_json::Value> {
    r.latencies_ms
        .iter()
        .map(|(kind, v)| {
            let mut v = v.clone();
            v.sort_by(f64::total_cmp);
            let figures = json!({"count": v.len(), "p50_ms": percentile(&v, 0.5), "p99_ms": percentile(&v, 0.99)});
            (kind, figures)
        })
        .collect()
}

/// Prints the soak's figures, as JSON or for people.
fn print(s: &Soak, json_out: bool) -> anyhow::Result<()> {
    if json_out {
        println!("{}", serde_json::to_string_pretty(&soak_json(s))?);
    } else {
        print_text(s);
    }
    Ok(())
}

/// `--json`'s object.
fn soak_json(s: &Soak) -> serde_json::Value {
    let r = &s.report;
    let overload = s.overload.as_ref().map(|o| {
        json!({"flooders": o.flooders,
            "polite_alone_p50_ms": o.polite_alone_p50_ms, "polite_flooded_p50_ms": o.polite_flooded_p50_ms,
            "polite_alone_p99_ms": o.polite_alone_p99_ms,
            "polite_flooded_p99_ms": o.polite_flooded_p99_ms,
            "polite_flooded_failed": o.polite_flooded_failed,
            "flood_requests": o.flood_requests, "flood_busy": o.flood_busy,
            "rss_max_mb": o.rss_max_mb})
    });
    json!({
        "clients": s.clients, "seconds": s.seconds,
        "requests": r.requests, "failed": r.failed, "lost": r.lost, "busy": r.busy,
        "errors": r.errors,
        "rss_start_mb": s.rss_start.total, "rss_end_mb": s.rss_end.total, "rss_max_mb": s.rss_max_mb,
        "rss_start": s.rss_start.json(), "rss_end": s.rss_end.json(),
        "p99_ms": p99(r.all_latencies()), "per_kind": per_kind(r),
        "leftover_shared_memory": s.leftover,
        "overload": overload,
    })
}

/// Prints the figures for people.
fn print_text(s: &Soak) {
    let r = &s.report;
    let all = r.all_latencies();
    println!(
        "soak: {} client processes, {:.0} s: {} requests, {} failed, {} lost, {} busy; {} {:.1} ms",
        s.clients,
        s.seconds,
        r.requests,
        r.failed,
        r.lost,
        r.busy,
        p99_label(all.len()),
        p99(all)
    );
    for (kind, f) in &per_kind(r) {
        let ms = |key: &str| f[key].as_f64().unwrap_or(f64::NAN);
        let count = f["count"].as_u64().unwrap_or(0) as usize;
        println!(
            "  {kind:>8}: {} answered, p50 {:.1} ms, {} {:.1} ms",
            f["count"],
            ms("p50_ms"),
            p99_label(count),
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
            "overload: a 1 Hz client's p50 / {} {:.1} / {:.1} ms alone, p50 / {} {:.1} / {:.1} ms while {} processes flood ({} failed); the flood sent {} requests, {} refused busy; server RSS at most {:.0} MiB",
            p99_label(o.polite_alone_samples),
            o.polite_alone_p50_ms,
            o.polite_alone_p99_ms,
            p99_label(o.polite_flooded_samples),
            o.polite_flooded_p50_ms,
            o.polite_flooded_p99_ms,
            o.flooders,
            o.polite_flooded_failed,
            o.flood_requests,
            o.flood_busy,
            o.rss_max_mb
        );
    }
}
