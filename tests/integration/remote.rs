//! Remote clients through `kfmap gateway` (Zenoh over TCP) against `kfmap serve`, as
//! real processes, inside a private network namespace this test creates (`unshare -rn`:
//! only `lo` exists, so nothing can leave the machine). The oracle is the local client
//! (iceoryx2) on the same server: every remote answer must equal its local twin.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{Prefix, Server, bake_dataset, kfmap, signal, simulate, stderr, temp_dir};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::{dataset_poses, find_scans, load_raw_scan};
use kfmap_client::{Client, ClientError, ClientOptions, LocalizeOptions, RelocalizeOptions};
use kfmap_geometry::geometry::{Pose, rotation_distance, translation_distance};
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_map::archive::{OpenOptions, open_map};
use kfmap_map::place::RelocalizeStatus;
use kfmap_map::tiles::{PlaceRanking, TileIndex};
use kfmap_protocol::remote::{decode_answer, rpc_key};
use kfmap_protocol::{ScanPayload, StatusCode};
use kfmap_remote::RemoteOptions;
use kfmap_testdata::require_capability;

/// Set in the namespace's child: the scenario runs only there.
const IN_NAMESPACE: &str = "KFMAP_TEST_IN_NETNS";
/// The gateway's endpoint inside the namespace (its own `lo`: no port conflicts).
const ENDPOINT: &str = "tcp/127.0.0.1:17447";
/// How far a place's score over the tiles may stand from the merged map's (see the
/// tiled site's relocalizations).
const SCORE_SLACK: f64 = 0.005;

#[test]
fn remote_clients_through_a_gateway_in_a_private_network_namespace() {
    in_private_network_namespace(
        module_path!(),
        "remote_clients_through_a_gateway_in_a_private_network_namespace",
        "in_namespace::scenario",
    );
}

#[test]
fn a_tiled_site_on_four_hosts_in_a_private_network_namespace() {
    in_private_network_namespace(
        module_path!(),
        "a_tiled_site_on_four_hosts_in_a_private_network_namespace",
        "in_namespace::tiled_site",
    );
}

/// Runs this binary's ignored test `inner` (of `module`) inside a new user and network
/// namespace (`unshare -rn`, then `lo` up): only loopback exists there.
pub(crate) fn in_private_network_namespace(module: &str, test: &str, inner: &str) {
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
        .args(["--exact", &common::test_name(module, inner)])
        .arg("--include-ignored")
        .args(["--nocapture", "--test-threads", "1"])
        .env(IN_NAMESPACE, "1")
        .env(common::fixtures::FIXTURES_ENV, common::fixtures::dir())
        .output()
        .unwrap();
    let (out_text, err_text) = (common::stdout(&out), stderr(&out));
    println!("{out_text}\n{err_text}");
    assert!(out.status.success(), "{inner} failed in the namespace");
    // A filter that matched nothing would pass too: the scenario must have run.
    assert!(out_text.contains("1 passed"), "{inner} did not run");
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
        let mut remote = kfmap_remote::connect(ENDPOINT, "court", options.clone()).unwrap();
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
        let gateway = Gateway::start(&prefix.0, &gateway_toml);
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
        drop(gateway);
        remote_clients_are_capped_per_gateway(&dir, &prefix.0);
        mutual_tls_and_access_control_as_shipped(&dir, &prefix.0);
        drop(server);
    }

    #[test]
    #[ignore = "runs inside the network namespace of a_tiled_site_on_four_hosts_in_a_private_network_namespace"]
    fn tiled_site() {
        if std::env::var_os(IN_NAMESPACE).is_none() {
            eprintln!("skipped: runs only inside the namespace the outer test creates");
            return;
        }
        only_loopback_exists();
        let dir = temp_dir("tiles");
        let data = dir.join("sim");
        // Three laps of the courtyard's 24 m square at 8 m/s: 10 m tiles, 12 on the ring,
        // 8 or 9 border crossings a lap (turning a corner inside the hysteresis skips one).
        simulate(&data, "courtyard", "36", "16", &["--speed", "8"]);
        let tiles = dir.join("court.tiles");
        let out = kfmap(&[
            "bake",
            "--dataset",
            data.to_str().unwrap(),
            "--out",
            tiles.to_str().unwrap(),
            "--tile-size",
            "10",
            "--halo",
            "10",
            "--keep-merged",
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        let stdout_of_bake = common::stdout(&out);
        let merged = tiles.join("merged.kfmap");
        let index = tile_set_as_cut(&tiles, &merged);

        // Four emulated hosts, each a serve + gateway pair with its own iceoryx2 prefix
        // and port, serving every fourth tile.
        let shares: Vec<String> = (0..4)
            .map(|h| {
                let ids: Vec<&str> = index
                    .tiles
                    .iter()
                    .skip(h)
                    .step_by(4)
                    .map(|t| t.id.as_str())
                    .collect();
                ids.join(",")
            })
            .collect();
        let mut hosts: Vec<TileHost> = shares
            .iter()
            .enumerate()
            .map(|(h, only)| TileHost::start(&tiles, h, only))
            .collect();
        let endpoints: Vec<String> = hosts.iter().map(|h| h.endpoint.clone()).collect();
        let options = ClientOptions {
            iceoryx_prefix: None,
            timeout: Duration::from_secs(120),
            spin: false,
        };
        let mut remote =
            kfmap_remote::connect(&endpoints.join(","), "court", options.clone()).unwrap();
        // The gateways publish the cut's index with their servers' ranking settings
        // (the defaults here).
        let published = TileIndex {
            ranking: Some(PlaceRanking::default()),
            ..index.clone()
        };
        assert_eq!(remote.connection().tile_index(), Some(&published));
        // The oracle: the merged map the tiles were cut from, served whole on this host.
        let merged_prefix = Prefix::new("tiles-merged");
        let _merged_server = Server::start(&merged, "merged", &merged_prefix.0, &[]);
        let mut oracle = Client::connect(
            "merged",
            ClientOptions {
                iceoryx_prefix: Some(merged_prefix.0.clone()),
                ..options.clone()
            },
        )
        .unwrap();

        let scans = find_scans(&data).unwrap();
        let truth = dataset_poses(&data, &scans).unwrap().unwrap().poses;
        let load = |i: usize| {
            load_raw_scan(&scans[i], &BakeConfig::default())
                .unwrap()
                .voxel_downsample(0.25)
                .unwrap()
                .points
        };
        let localize_options = LocalizeOptions::default();
        let (mut guess, mut previous) = (truth[0], truth[0]);
        let mut last_tile = String::new();
        let (mut crossings, mut worst_crossing, mut worst) = (0, 0.0_f64, 0.0_f64);
        let mut identical = 0;
        let kill_at = scans.len() / 2;
        for (i, true_pose) in truth.iter().enumerate() {
            let points = load(i);
            let scan = ScanPayload {
                points: &points,
                view_dirs: None,
                covariances: None,
            };
            if i == kill_at {
                a_killed_tile_server_is_an_explicit_error(
                    &mut remote,
                    &mut hosts,
                    &tiles,
                    &scan,
                    &guess,
                );
            }
            let answer = remote.localize(&scan, &guess, &localize_options).unwrap();
            let tile = remote.connection().current_tile().unwrap().to_string();
            // Exactly one tile answers, as the whole map would.
            let whole = oracle.localize(&scan, &guess, &localize_options).unwrap();
            let apart = (answer.pose.translation.vector - whole.pose.translation.vector).norm();
            // The same keyframes near the guess, so the same answer.
            assert!(
                apart < 1e-6,
                "scan {i} on tile {tile}: {apart} m from the merged map's answer"
            );
            if apart == 0.0 {
                identical += 1;
            }
            assert_eq!(answer.health.status, whole.health.status, "scan {i}");
            let off = (answer.pose.translation.vector - true_pose.translation.vector).norm();
            worst = worst.max(off);
            if i > 0 && tile != last_tile {
                crossings += 1;
                worst_crossing = worst_crossing.max(off);
                assert!(
                    off < 0.05,
                    "scan {i}, {last_tile} -> {tile}: {off} m from the truth"
                );
            }
            last_tile = tile;
            // Constant velocity: the next guess moves on as this scan moved.
            guess = answer.pose * (previous.inverse() * answer.pose);
            previous = answer.pose;
        }
        println!(
            "tiled drive: {} scans, {crossings} border crossings, worst error {worst:.3} m, at a crossing {worst_crossing:.3} m; {identical} answers identical to the merged map's",
            scans.len(),
        );
        assert_eq!(
            identical,
            scans.len(),
            "answers differ from the merged map's"
        );
        // The cut reports its halo check (its counts are tested against brute-force
        // selection in `kfmap_bake::tiling`; here the oracle is the drive's answers).
        let check = stdout_of_bake
            .lines()
            .find_map(|l| l.trim().strip_prefix("halo check: "))
            .expect("a halo check line");
        println!("halo check at the cut: {check}");
        assert!(crossings >= 20, "only {crossings} crossings");

        // Relocalization over every tile at once ranks as one search over the merged map.
        let (mut compared, mut found, mut tiled_ms, mut whole_ms) = (0, 0, 0.0, 0.0);
        for i in (0..scans.len()).step_by(24) {
            let points = load(i);
            let scan = ScanPayload {
                points: &points,
                view_dirs: None,
                covariances: None,
            };
            let started = Instant::now();
            let tiled = remote
                .relocalize(&scan, &RelocalizeOptions::default())
                .unwrap();
            tiled_ms += started.elapsed().as_secs_f64() * 1e3;
            let started = Instant::now();
            let whole = oracle
                .relocalize(&scan, &RelocalizeOptions::default())
                .unwrap();
            whole_ms += started.elapsed().as_secs_f64() * 1e3;
            compared += 1;
            println!(
                "relocalize scan {i}: tiled server {:.0} ms, merged server {:.0} ms",
                tiled.server_us / 1e3,
                whole.server_us / 1e3
            );
            assert_eq!(tiled.status, whole.status, "scan {i}");
            // The same places scored nearly alike (a tile's grid is the whole map's
            // around its core, its places the whole map's there). A tile scores against
            // its core and halo keyframes only, and this sensor reaches 30 m past a 10 m
            // halo: a score may differ in the third decimal (measured: at most 0.0015 of
            // 15), far below the ambiguity margin that turns it into a verdict.
            println!(
                "relocalize scan {i}: scores {:.4} / {:.4} (tiles), {:.4} / {:.4} (merged)",
                tiled.score, tiled.runner_up, whole.score, whole.runner_up
            );
            assert!((tiled.score - whole.score).abs() < SCORE_SLACK, "scan {i}");
            assert!(
                (tiled.runner_up - whole.runner_up).abs() < SCORE_SLACK,
                "scan {i}"
            );
            // The scored places come along over the tiles too, as the merged map sends
            // them: a tracker's check keeps the places near the best as hypotheses, so
            // each merged-map place within the hypotheses' margin (0.1) of the best has
            // its tiled twin: the same place (0.5 m, 5 deg) scored alike.
            let best = whole.places.first().map_or(0.0, |p| p.score);
            for place in whole.places.iter().filter(|p| p.score + 0.1 >= best) {
                let twin = tiled.places.iter().find(|t| {
                    translation_distance(&t.pose, &place.pose) < 0.5
                        && rotation_distance(&t.pose, &place.pose).to_degrees() < 5.0
                });
                println!(
                    "relocalize scan {i}: merged place {:?} score {:.4}, tiled {:?}",
                    place.pose.translation.vector.as_slice(),
                    place.score,
                    twin.map(|t| t.score)
                );
                assert!(
                    twin.is_some_and(|t| (t.score - place.score).abs() < SCORE_SLACK),
                    "scan {i}: the merged map's place scored {} has no tiled twin among {} places",
                    place.score,
                    tiled.places.len()
                );
            }
            // An ambiguous answer's pose is one of near-equal places: only found ones.
            // The best place settles from the same start against the keyframes nearest
            // it, which the halo check keeps in its tile; a wrong place would be metres
            // away.
            if tiled.status == RelocalizeStatus::Found {
                let (a, b) = (tiled.pose.unwrap(), whole.pose.unwrap());
                let apart = (a.translation.vector - b.translation.vector).norm();
                println!("relocalize scan {i}: found {apart:.4} m from the merged map's place");
                // Measured: at most 1 mm (README), the scan 264 whose score differs.
                assert!(
                    apart < 0.003,
                    "scan {i}: tiled relocalization {apart} m from the merged map's"
                );
                found += 1;
            }
        }
        println!(
            "relocalization: {compared} scans over {} tiles, the same status and place as the merged map's ({found} found); {tiled_ms:.0} ms against {whole_ms:.0} ms in all (every tile server shares this host's 2 cores)",
            index.tiles.len()
        );
        // Every one of these scans was taken on the mapped drive (a 16-ring sensor,
        // thinned as the client sends it): the merged map finds each.
        assert!(
            found + 1 >= compared,
            "only {found} of {compared} scans found"
        );
        drop(hosts);
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

/// Checks the tile set `dir` against the merged map it was cut from: every keyframe in
/// exactly one core, each tile's file holding its core and halo keyframes, and Autoware's
/// metadata naming each tile's point cloud, whose points lie in its square.
fn tile_set_as_cut(dir: &Path, merged: &Path) -> TileIndex {
    let index = TileIndex::load(dir).unwrap();
    let whole = open_map(merged, OpenOptions::default()).unwrap();
    let geometry = index.geometry();
    let (s, h) = (geometry.tile_size, geometry.halo);
    let yaml = std::fs::read_to_string(dir.join("pointcloud_map_metadata.yaml")).unwrap();
    assert!(yaml.contains("x_resolution: 10.0"), "{yaml}");
    let mut owned = 0;
    for t in &index.tiles {
        let (x0, y0) = (t.col as f64 * s, t.row as f64 * s);
        // Brute force over the merged map's keyframes: core and halo membership.
        let (mut core, mut all) = (Vec::new(), Vec::new());
        for k in whole.map.keyframes() {
            let p = k.pose.translation.vector;
            if p.x >= x0 && p.x < x0 + s && p.y >= y0 && p.y < y0 + s {
                core.push(k.id);
            }
            if p.x >= x0 - h && p.x <= x0 + s + h && p.y >= y0 - h && p.y <= y0 + s + h {
                all.push(k.id);
            }
        }
        let tile = open_map(&dir.join(&t.file), OpenOptions::default()).unwrap();
        let ids: Vec<u64> = tile.map.keyframes().map(|k| k.id).collect();
        assert_eq!(ids, all, "tile {}", t.id);
        assert_eq!(t.core_keyframes as usize, core.len(), "tile {}", t.id);
        owned += core.len();
        assert!(
            yaml.contains(&format!("{}: [{x0:?}, {y0:?}]", t.pcd)),
            "{yaml}"
        );
        let cloud = read_cloud(&dir.join(&t.pcd), &ReadOptions::default())
            .unwrap()
            .cloud;
        assert!(!cloud.points.is_empty(), "tile {}", t.id);
        for p in &cloud.points {
            let (x, y) = (p[0] as f64, p[1] as f64);
            assert!(
                x >= x0 - 0.1 && x < x0 + s + 0.1 && y >= y0 - 0.1 && y < y0 + s + 0.1,
                "tile {}: {p:?}",
                t.id
            );
        }
    }
    assert_eq!(owned, whole.map.len(), "every keyframe in exactly one core");
    assert!(index.tiles.len() >= 4, "{} tiles", index.tiles.len());
    index
}

/// The drive's tile server dies: the next request gets an explicit error naming the
/// tile (not a timeout), or, when the client already saw the tile's token go and the
/// guess lies within the router's hysteresis of a live neighbour's core, that
/// neighbour's answer (the documented failover; its halo holds what the request needs).
/// Which of the two depends on whether the token's withdrawal reached the client before
/// the request: both are checked. After the server's restart its tile answers again.
fn a_killed_tile_server_is_an_explicit_error(
    remote: &mut Client,
    hosts: &mut [TileHost],
    tiles: &Path,
    scan: &ScanPayload,
    guess: &Pose,
) {
    let tile = remote.connection().current_tile().unwrap().to_string();
    let host = hosts
        .iter_mut()
        .find(|h| h.only.split(',').any(|t| t == tile))
        .unwrap();
    // A client pinned to the tile, to see the restarted tile itself answer (the drive's
    // client may stay on the neighbour it failed over to).
    let mut to_tile = RemoteOptions::new(&host.endpoint);
    to_tile.tile = Some(tile.clone());
    let options = ClientOptions {
        timeout: remote.connection().timeout(),
        ..ClientOptions::default()
    };
    let mut pinned = kfmap_remote::connect_with(&to_tile, "court", options).unwrap();
    let killing = Instant::now();
    host.server.take().unwrap().kill();
    let died = Instant::now();
    println!(
        "tile server process gone {:?} after the kill signal",
        died - killing
    );
    let answered = remote.localize(scan, guess, &LocalizeOptions::default());
    let waited = died.elapsed();
    match answered {
        Err(error) => {
            println!("tile {tile}'s server killed mid-drive: error after {waited:?}: {error}");
            assert!(
                matches!(
                    error,
                    ClientError::Disconnected(_) | ClientError::NoServer(_)
                ),
                "{error:?}"
            );
            assert!(error.to_string().contains(&tile), "{error}");
            assert!(
                waited < remote.connection().timeout(),
                "the error came from the timeout"
            );
        }
        Ok(answer) => {
            let now = remote.connection().current_tile().unwrap().to_string();
            println!(
                "tile {tile}'s server killed mid-drive: failed over to tile {now} after {waited:?}"
            );
            assert_ne!(now, tile, "the killed tile's server answered");
            assert!(
                !host.only.split(',').any(|t| t == now),
                "tile {now} shares the killed server"
            );
            assert!(answer.pose.translation.vector.iter().all(|v| v.is_finite()));
        }
    }
    host.server = Some(Server::start_tiles(
        tiles,
        "court",
        &host.prefix.0,
        &host.only,
    ));
    let restarted = Instant::now();
    let back = poll(
        || {
            pinned
                .localize(scan, guess, &LocalizeOptions::default())
                .is_ok()
        },
        1000,
    );
    println!(
        "tile {tile}'s server restarted: answers again after {:?}",
        restarted.elapsed()
    );
    assert!(
        back,
        "tile {tile} gave no answer within 1000 tries after the restart"
    );
    // And the drive's client reaches the map again.
    assert!(
        poll(
            || remote
                .localize(scan, guess, &LocalizeOptions::default())
                .is_ok(),
            1000
        ),
        "no answer within 1000 tries after the restart"
    );
}

/// An emulated host of a tile set: `kfmap serve --tiles --only` and `kfmap gateway
/// --tiles --only` with a prefix and port of their own.
struct TileHost {
    server: Option<Server>,
    _gateway: Gateway,
    prefix: Prefix,
    only: String,
    endpoint: String,
}

impl TileHost {
    fn start(tiles: &Path, host: usize, only: &str) -> Self {
        let prefix = Prefix::new(&format!("tiles-host{host}"));
        let server = Server::start_tiles(tiles, "court", &prefix.0, only);
        let endpoint = format!("tcp/127.0.0.1:{}", 17460 + host);
        // Every tile of every host relocalizes at once on this machine's cores.
        let config = tiles.with_file_name(format!("gateway{host}.toml"));
        std::fs::write(&config, "[gateway]\nrequest-timeout-s = 120.0\n").unwrap();
        let gateway = Gateway::spawn(&[
            "--config",
            config.to_str().unwrap(),
            "--tiles",
            tiles.to_str().unwrap(),
            "--only",
            only,
            "--map-name",
            "court",
            "--iceoryx-prefix",
            &prefix.0,
            "--listen",
            &endpoint,
        ]);
        Self {
            server: Some(server),
            _gateway: gateway,
            prefix,
            only: only.to_string(),
            endpoint,
        }
    }
}

/// Nothing but `lo` in this namespace: no address outside loopback can be reached.
pub(crate) fn only_loopback_exists() {
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
    let config = kfmap_remote::zenoh_config(None, &[], &[ENDPOINT.into()]).unwrap();
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

/// `max-sessions` caps the remote clients of the whole gateway, not of each worker:
/// with 2 places and 3 workers, of six clients (raw Zenoh sessions with ids of their
/// own, spread over the workers) two are served and four answered Busy; an admitted
/// client keeps its place, and an idle session frees one.
fn remote_clients_are_capped_per_gateway(dir: &Path, prefix: &str) {
    use kfmap_protocol::remote::encode_request;
    use kfmap_protocol::{RequestHeader, RequestKind};
    use zenoh::Wait;
    let config = dir.join("capped.toml");
    std::fs::write(
        &config,
        "[gateway]\nmax-sessions = 2\nworkers = 3\nsession-idle-s = 1.0\n",
    )
    .unwrap();
    let gateway = Gateway::start(prefix, &config);
    let zconfig = kfmap_remote::zenoh_config(None, &[], &[ENDPOINT.into()]).unwrap();
    let session = zenoh::open(zconfig).wait().unwrap();
    let status = |client: &str| -> StatusCode {
        let header = RequestHeader {
            kind: RequestKind::Status as u32,
            request_id: 1,
            ..Default::default()
        };
        let replies = session
            .get(rpc_key("court", "whole", client))
            .payload(encode_request(&header, &[]))
            .timeout(Duration::from_secs(10))
            .wait()
            .unwrap();
        let reply = replies.recv().expect("one reply");
        let sample = reply.into_result().expect("an answer frame");
        let (header, _) = decode_answer(&sample.payload().to_bytes()).unwrap();
        let code = StatusCode::from_code(header.status);
        if code == StatusCode::Busy {
            assert!(
                header.message().contains("max-sessions"),
                "{}",
                header.message()
            );
        }
        code
    };
    let clients = ["cap-a", "cap-b", "cap-c", "cap-d", "cap-e", "cap-f"];
    let answers: Vec<StatusCode> = clients.iter().map(|c| status(c)).collect();
    let served = answers.iter().filter(|&&a| a == StatusCode::Ok).count();
    let busy = answers.iter().filter(|&&a| a == StatusCode::Busy).count();
    assert_eq!((served, busy), (2, 4), "{answers:?}");
    // The admitted ones keep their places.
    assert_eq!(status(clients[0]), StatusCode::Ok);
    assert_eq!(status(clients[1]), StatusCode::Ok);
    assert_eq!(status(clients[5]), StatusCode::Busy);
    // Idle for longer than session-idle-s (1 s): the places are free again.
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(status(clients[5]), StatusCode::Ok);
    let _ = session.close().wait();
    drop(gateway);
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
        Self::spawn(&[
            "--map-name",
            "court",
            "--iceoryx-prefix",
            prefix,
            "--listen",
            ENDPOINT,
            "--config",
            config.to_str().unwrap(),
        ])
    }

    /// Starts `kfmap gateway ARGS` and waits for its ready line.
    fn spawn(args: &[&str]) -> Self {
        let mut child = Command::new(common::kfmap_bin())
            .arg("gateway")
            .args(args)
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
