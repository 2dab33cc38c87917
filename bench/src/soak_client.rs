//! One `kfmap bench soak` client process (the hidden `kfmap bench soak-client`): large
//! scans and every request kind at a fixed rate against the soak's server, and what it
//! saw.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::Context;
use kfmap_client::{Client, ClientError, ClientOptions, LocalizeOptions};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::ImuSample;
use kfmap_protocol::{Cov2CovMode, ScanPayload, StatusCode};
use nalgebra::Vector3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::fixtures::{keyframe_pose, synthetic_cloud};

/// What one soak client did.
#[derive(Debug, Default, Serialize, Deserialize)]
pub(super) struct ClientReport {
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

    /// Adds another client's report to this one.
    pub fn merge(&mut self, other: ClientReport) {
        for (kind, v) in other.latencies_ms {
            self.latencies_ms.entry(kind).or_default().extend(v);
        }
        self.requests += other.requests;
        self.failed += other.failed;
        self.busy += other.busy;
        self.lost += other.lost;
        self.errors.extend(other.errors);
    }

    /// Every answered request's round trip, milliseconds, all kinds together.
    pub fn all_latencies(&self) -> Vec<f64> {
        self.latencies_ms.values().flatten().copied().collect()
    }
}

/// How one soak client behaves.
#[derive(Debug, Clone, Copy)]
pub(super) struct ClientPlan {
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

/// The hidden `kfmap bench soak-client PREFIX`: runs one client and prints its report
/// as JSON.
pub(super) fn run(prefix: &str, plan: ClientPlan) -> anyhow::Result<()> {
    let report = run_client(prefix, plan)?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

/// Starts a client process (`kfmap bench soak-client`) against the server of `prefix`;
/// its stdout, the report, is piped.
pub(super) fn spawn(exe: &Path, prefix: &str, plan: &ClientPlan) -> anyhow::Result<Child> {
    Command::new(exe)
        .args(["bench", "soak-client", prefix])
        .args(["--rate", &plan.rate_hz.to_string()])
        .args(["--seconds", &plan.seconds.to_string()])
        .args(["--seed", &plan.seed.to_string()])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .context("start a soak client")
}

/// Runs one soak client against the server of `prefix`.
fn run_client(prefix: &str, plan: ClientPlan) -> anyhow::Result<ClientReport> {
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

/// Sends one request of `kind` with `points` at `pose`.
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
