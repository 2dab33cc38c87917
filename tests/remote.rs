//! Remote clients through `kfmap gateway` (Zenoh over TCP) against `kfmap serve`, as
//! real processes, inside a private network namespace this test creates (`unshare -rn`:
//! only `lo` exists, so nothing can leave the machine). The oracle is the local client
//! (iceoryx2) on the same server: every remote answer must equal its local twin.

mod common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{Prefix, Server, bake_dataset, kfmap, signal, simulate, stderr, temp_dir};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::{dataset_poses, find_scans, load_raw_scan};
use kfmap_client::{Client, ClientError, ClientOptions, LocalizeOptions, RelocalizeOptions};
use kfmap_protocol::remote::{decode_answer, rpc_key};
use kfmap_protocol::{ScanPayload, StatusCode};
use kfmap_shared::geometry::Pose;
use kfmap_testdata::require_capability;

/// Set in the namespace's child: the scenario runs only there.
const IN_NAMESPACE: &str = "KFMAP_TEST_IN_NETNS";
/// The gateway's endpoint inside the namespace (its own `lo`: no port conflicts).
const ENDPOINT: &str = "tcp/127.0.0.1:17447";

#[test]
fn remote_clients_through_a_gateway_in_a_private_network_namespace() {
    let test = "remote_clients_through_a_gateway_in_a_private_network_namespace";
    let works = Command::new("unshare")
        .args(["-rn", "sh", "-c", "ip link set lo up"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    let what = "unprivileged user and network namespaces (`unshare -rn` with `ip`)";
    if require_capability(works, what, test).is_none() {
        return;
    }
    let me = std::env::current_exe().unwrap();
    let out = Command::new("unshare")
        .args(["-rn", "sh", "-c", "ip link set lo up && exec \"$0\" \"$@\""])
        .arg(&me)
        .args(["--exact", "in_namespace::scenario", "--include-ignored"])
        .args(["--nocapture", "--test-threads", "1"])
        .env(IN_NAMESPACE, "1")
        .output()
        .unwrap();
    let (out_text, err_text) = (common::stdout(&out), stderr(&out));
    println!("{out_text}\n{err_text}");
    assert!(out.status.success(), "the scenario failed in the namespace");
    // A filter that matched nothing would pass too: the scenario must have run.
    assert!(out_text.contains("1 passed"), "the scenario did not run");
}

mod in_namespace {
    use super::*;

    #[test]
    #[ignore = "runs inside the network namespace of remote_clients_through_a_gateway_in_a_private_network_namespace"]
    fn scenario() {
        if std::env::var_os(IN_NAMESPACE).is_none() {
            eprintln!("skipped: runs only inside the namespace the outer test creates");
            return;
        }
        only_loopback_exists();
        let prefix = Prefix::new("remote");
        let dir = temp_dir("remote");
        let data = dir.join("sim");
        simulate(&data, "courtyard", "3", "16", &[]);
        let map = dir.join("court.kfmap");
        bake_dataset(&data, &map);
        let server = Server::start(&map, "court", &prefix.0, &[]);
        // A small request cap, to see a request refused before it reaches the server.
        let gateway_toml = dir.join("gateway.toml");
        std::fs::write(&gateway_toml, "[gateway]\nmax-request-bytes = 262144\n").unwrap();
        let gateway = Gateway::start(&prefix.0, &gateway_toml);

        let options = ClientOptions {
            iceoryx_prefix: Some(prefix.0.clone()),
            timeout: Duration::from_secs(20),
            spin: false,
        };
        let mut local = Client::connect("court", options.clone()).unwrap();
        let mut remote = Client::remote(ENDPOINT, "court", options.clone()).unwrap();
        answers_equal_the_local_clients(&data, &mut local, &mut remote);
        refusals_equal_the_local_clients(&mut local, &mut remote);
        broken_frames_are_refused_with_a_reason();
        the_cli_localizes_remotely_as_locally(&data, &dir, &prefix.0);

        // The server dies: an explicit error, not a timeout; back after a restart.
        server.kill();
        let died = Instant::now();
        let error = remote.status().unwrap_err();
        let waited = died.elapsed();
        println!("server killed: remote error after {waited:?}: {error}");
        assert!(
            matches!(
                error,
                ClientError::Disconnected(_) | ClientError::NoServer(_)
            ),
            "{error:?}"
        );
        assert!(waited < options.timeout, "the error came from the timeout");
        let out = kfmap(&["status", "--remote", ENDPOINT, "--map-name", "court"]);
        assert_eq!(out.status.code(), Some(2));
        assert!(
            stderr(&out).contains("no kfmap server serves map"),
            "{}",
            stderr(&out)
        );
        let server = Server::start(&map, "court", &prefix.0, &[]);
        let restarted = Instant::now();
        let back = poll(|| remote.status().is_ok(), 500);
        println!(
            "server restarted: remote answers again after {:?}",
            restarted.elapsed()
        );
        assert!(
            back,
            "no answer within 500 tries after the server's restart"
        );

        // The gateway dies: the same.
        drop(gateway);
        let died = Instant::now();
        let error = remote.status().unwrap_err();
        println!(
            "gateway killed: remote error after {:?}: {error}",
            died.elapsed()
        );
        assert!(
            matches!(
                error,
                ClientError::Disconnected(_) | ClientError::NoServer(_)
            ),
            "{error:?}"
        );
        let _gateway = Gateway::start(&prefix.0, &gateway_toml);
        let restarted = Instant::now();
        let back = poll(|| remote.status().is_ok(), 1000);
        println!(
            "gateway restarted: remote answers again after {:?}",
            restarted.elapsed()
        );
        assert!(
            back,
            "no answer within 1000 tries after the gateway's restart"
        );
        mutual_tls_and_access_control_as_shipped(&dir, &prefix.0);
        drop(server);
    }
}

/// The shipped `config/zenoh-gateway-mtls.json5` and `zenoh-robot-mtls.json5`, with
/// certificates made here by openssl: robot7 is answered on its own key, refused on
/// another robot's, and a client without a certificate or without TLS gets nothing.
fn mutual_tls_and_access_control_as_shipped(dir: &Path, prefix: &str) {
    let test = "mutual_tls_and_access_control_as_shipped";
    let openssl = Command::new("openssl").arg("version").output().is_ok();
    if require_capability(openssl, "openssl to make test certificates", test).is_none() {
        return;
    }
    let certs = dir.join("certs");
    std::fs::create_dir_all(&certs).unwrap();
    let sh = |script: &str| {
        let out = Command::new("sh")
            .args(["-c", script])
            .current_dir(&certs)
            .output()
            .unwrap();
        assert!(out.status.success(), "{script}: {}", stderr(&out));
    };
    sh(
        "openssl req -x509 -newkey rsa:2048 -nodes -keyout ca-key.pem -out ca.pem -days 2 -subj /CN=kfmap-test-ca",
    );
    for (name, ext) in [
        ("gateway", "subjectAltName=DNS:localhost,IP:127.0.0.1"),
        (
            "robot7",
            "basicConstraints=CA:FALSE\\nextendedKeyUsage=clientAuth",
        ),
    ] {
        sh(&format!(
            "openssl req -newkey rsa:2048 -nodes -keyout {name}-key.pem -out {name}.csr -subj /CN={name} && \
             printf '{ext}\\n' > {name}.ext && \
             openssl x509 -req -in {name}.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -out {name}.pem -days 2 -extfile {name}.ext"
        ));
    }
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let gateway_json = repo.join("config/zenoh-gateway-mtls.json5");
    let robot_json = repo.join("config/zenoh-robot-mtls.json5");
    let tls = "tls/localhost:17451";
    let mut child = Command::new(common::kfmap_bin())
        .args(["gateway", "--map-name", "court", "--iceoryx-prefix", prefix])
        .args([
            "--listen",
            tls,
            "--zenoh-config",
            gateway_json.to_str().unwrap(),
        ])
        .current_dir(dir)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let _gateway = Gateway(child);
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line).unwrap();
    assert!(line.starts_with("ready: gateway"), "{line:?}");
    let status = |endpoint: &str, config: Option<&Path>, id: &str| {
        let mut args = vec!["status", "--remote", endpoint, "--map-name", "court"];
        args.extend(["--client-id", id]);
        if let Some(c) = config {
            args.extend(["--zenoh-config", c.to_str().unwrap()]);
        }
        Command::new(common::kfmap_bin())
            .args(&args)
            .current_dir(dir)
            .output()
            .unwrap()
    };
    let out = status(tls, Some(&robot_json), "robot7");
    assert!(out.status.success(), "robot7: {}", stderr(&out));
    let out = status(tls, Some(&robot_json), "robot8");
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("access control list may deny"),
        "{}",
        stderr(&out)
    );
    let ca_only = dir.join("ca-only.json5");
    std::fs::write(
        &ca_only,
        "{transport:{link:{tls:{root_ca_certificate:\"certs/ca.pem\"}}}}",
    )
    .unwrap();
    let out = status(tls, Some(&ca_only), "robot7");
    assert_eq!(
        out.status.code(),
        Some(2),
        "no client certificate: {}",
        stderr(&out)
    );
    let out = status("tcp/127.0.0.1:17451", None, "robot7");
    assert_eq!(out.status.code(), Some(2), "plain TCP: {}", stderr(&out));
    println!(
        "mutual TLS and ACL as shipped: robot7 answered; robot8, no certificate, plain TCP refused"
    );
}

/// Nothing but `lo` in this namespace: no address outside loopback can be reached.
fn only_loopback_exists() {
    let out = Command::new("ip").args(["-o", "link"]).output().unwrap();
    let links = common::stdout(&out);
    let names: Vec<&str> = links
        .lines()
        .filter_map(|l| l.split(':').nth(1).map(str::trim))
        .collect();
    assert_eq!(names, ["lo"], "{links}");
}

/// Calls `ok` every 10 ms until it holds, at most `tries` times.
fn poll(mut ok: impl FnMut() -> bool, tries: usize) -> bool {
    for _ in 0..tries {
        if ok() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    false
}

/// Scan `i` of a dataset at 0.25 m voxels, and its true pose.
fn scan(data: &Path, i: usize) -> (Vec<[f32; 3]>, Pose) {
    let scans = find_scans(data).unwrap();
    let truth = dataset_poses(data, &scans).unwrap().unwrap();
    let cloud = load_raw_scan(&scans[i], &BakeConfig::default())
        .unwrap()
        .voxel_downsample(0.25)
        .unwrap();
    (cloud.points, truth.poses[i])
}

fn answers_equal_the_local_clients(data: &Path, local: &mut Client, remote: &mut Client) {
    let (l, r) = (local.status().unwrap(), remote.status().unwrap());
    assert_eq!((l.keyframes, l.points), (r.keyframes, r.points));

    let (points, truth) = scan(data, 17);
    let guess = truth * Pose::translation(0.05, -0.03, 0.02);
    let near = remote.nearest(&points, &guess, 3).unwrap();
    assert_eq!(near.len(), 3 * points.len());
    assert_eq!(near, local.nearest(&points, &guess, 3).unwrap());
    // Remote and local clients each have a session of their own.
    assert_eq!(remote.status().unwrap().sessions, 2);
    let within = remote.radius(&points, &guess, 0.4).unwrap();
    assert_eq!(within, local.radius(&points, &guess, 0.4).unwrap());

    let plain = ScanPayload {
        points: &points,
        view_dirs: None,
        covariances: None,
    };
    let options = LocalizeOptions::default();
    for i in [5, 17, 25] {
        let (points, truth) = scan(data, i);
        let scan = ScanPayload {
            points: &points,
            view_dirs: None,
            covariances: None,
        };
        let guess = truth * Pose::translation(0.2, -0.1, 0.0);
        let a = remote.localize(&scan, &guess, &options).unwrap();
        let b = local.localize(&scan, &guess, &options).unwrap();
        assert_eq!(
            a.pose.translation.vector, b.pose.translation.vector,
            "scan {i}"
        );
        assert_eq!(a.pose.rotation, b.pose.rotation, "scan {i}");
        assert_eq!(a.health.status, b.health.status, "scan {i}");
        let off = (a.pose.translation.vector - truth.translation.vector).norm();
        assert!(off < 0.05, "scan {i} localized {off} m from the truth");
    }
    let a = remote
        .relocalize(&plain, &RelocalizeOptions::default())
        .unwrap();
    let b = local
        .relocalize(&plain, &RelocalizeOptions::default())
        .unwrap();
    assert_eq!((a.status, a.pose, a.score), (b.status, b.pose, b.score));
}

fn refusals_equal_the_local_clients(local: &mut Client, remote: &mut Client) {
    let bad = [[1.0f32, 2.0, 3.0], [f32::NAN, 0.0, 0.0]];
    let status = |e: ClientError| e.status();
    let (a, b) = (
        remote.nearest(&bad, &Pose::identity(), 1).unwrap_err(),
        local.nearest(&bad, &Pose::identity(), 1).unwrap_err(),
    );
    assert_eq!(status(a), Some(StatusCode::NonFinitePoint));
    assert_eq!(status(b), Some(StatusCode::NonFinitePoint));
    // 30 000 points are 360 kB: over the gateway's 256 KiB cap, refused before any loan.
    let many = vec![[1.0f32, 2.0, 3.0]; 30_000];
    let error = remote.nearest(&many, &Pose::identity(), 1).unwrap_err();
    assert!(error.to_string().contains("max-request-bytes"), "{error}");
    assert_eq!(status(error), Some(StatusCode::TooLarge));
    // The connection still answers.
    remote.nearest(&bad[..1], &Pose::identity(), 1).unwrap();
}

/// Frames from a raw Zenoh session: garbage and a truncated header get a refusal
/// naming the problem, never a crash of the gateway.
fn broken_frames_are_refused_with_a_reason() {
    use zenoh::Wait;
    let config = kfmap_client::remote::zenoh_config(None, &[], &[ENDPOINT.into()]).unwrap();
    let session = zenoh::open(config).wait().unwrap();
    let key = rpc_key("court", "whole", "raw-tester");
    for (frame, expected) in [
        (b"garbage".to_vec(), "shorter than its 152-byte header"),
        (vec![0u8; 153], "not a multiple of 4 bytes"),
    ] {
        let replies = session
            .get(&key)
            .payload(frame)
            .timeout(Duration::from_secs(10))
            .wait()
            .unwrap();
        let reply = replies.recv().expect("one reply");
        let sample = reply
            .into_result()
            .expect("a refusal frame, not an error reply");
        let (header, pairings) = decode_answer(&sample.payload().to_bytes()).unwrap();
        assert_eq!(StatusCode::from_code(header.status), StatusCode::BadRequest);
        assert!(header.message().contains(expected), "{}", header.message());
        assert!(pairings.is_empty());
    }
    let _ = session.close().wait();
}

fn the_cli_localizes_remotely_as_locally(data: &Path, dir: &Path, prefix: &str) {
    let run = |how: &[&str], out: &Path| {
        let o = kfmap(
            &[
                &[
                    "localize",
                    "--map-name",
                    "court",
                    "--dataset",
                    data.to_str().unwrap(),
                    "--initial-from-ground-truth",
                    "--server-side",
                    "--rate",
                    "0",
                    "--out",
                    out.to_str().unwrap(),
                ],
                how,
            ]
            .concat(),
        );
        assert!(o.status.success(), "{}", stderr(&o));
        std::fs::read_to_string(out).unwrap()
    };
    let remote = run(&["--remote", ENDPOINT], &dir.join("remote.tum"));
    let local = run(&["--iceoryx-prefix", prefix], &dir.join("local.tum"));
    assert_eq!(remote.lines().filter(|l| !l.starts_with('#')).count(), 30);
    assert_eq!(
        remote, local,
        "the remote trajectory differs from the local one"
    );
}

/// A running `kfmap gateway`, killed when dropped.
struct Gateway(Child);

impl Gateway {
    fn start(prefix: &str, config: &Path) -> Self {
        let mut child = Command::new(common::kfmap_bin())
            .args(["gateway", "--map-name", "court", "--iceoryx-prefix", prefix])
            .args(["--listen", ENDPOINT, "--config", config.to_str().unwrap()])
            .stdout(Stdio::piped())
            .spawn()
            .expect("spawn kfmap gateway");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        assert!(line.starts_with("ready: gateway"), "{line:?}");
        Self(child)
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        signal(&self.0, libc::SIGKILL);
        let _ = self.0.wait();
    }
}
