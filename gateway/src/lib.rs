//! `kfmap gateway`: a sidecar beside `kfmap serve` that answers Zenoh queries from
//! other hosts through the local server (docs/DESIGN.md#notes-remote).
//!
//! It declares, per tile it announces (one, `whole`, for a map served whole), a
//! queryable on `kfmap/<map>/v<protocol>/<tile>/rpc/*` and forwards each
//! query's frame over iceoryx2, one server session per remote client (the key's last
//! chunk), and holds the liveliness token `.../<tile>/alive` while the server answers:
//! remote clients learn within milliseconds that the server died (the token goes) or the
//! gateway died (Zenoh ends their pending queries), and when it is back.

mod bridge;
pub mod config;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use kfmap_client::{ClientError, ClientOptions, Connection};
use kfmap_map::tiles::{PlaceRanking, TileIndex};
use kfmap_protocol::remote::{
    WHOLE_MAP_TILE, alive_key, check_key_chunk, rpc_queryable_key, tile_index_key, tile_map_name,
};
use kfmap_protocol::transport::{Rpc, create_node, iceoryx_config, open_rpc, server_processes};
use kfmap_remote::zenoh_config;
use zenoh::Wait;

pub use config::{GatewayConfig, GatewaySection};

/// One tile the gateway announces.
#[derive(Debug, Clone)]
pub struct ServedTile {
    /// The tile chunk of the keys ([`WHOLE_MAP_TILE`] for a map served whole).
    pub tile: String,
    /// The local server's (iceoryx2) map name for it.
    pub local_map: String,
}

/// What to serve.
#[derive(Debug, Clone)]
pub struct GatewayOptions {
    /// The map's name in the keys (as `kfmap serve` announces it).
    pub map_name: String,
    /// The tiles announced, each forwarded to its local server.
    pub tiles: Vec<ServedTile>,
    /// A tile set's index (`tiles.toml`), answered with its servers' ranking on the map's
    /// index key so remote clients can route by pose; `None` for a map served whole.
    pub index: Option<TileIndex>,
    /// iceoryx2 prefix of the local server.
    pub iceoryx_prefix: Option<String>,
    /// `gateway.toml`.
    pub config: GatewaySection,
}

impl GatewayOptions {
    /// A gateway for the whole map `map_name` with `config`.
    pub fn new(map_name: &str, config: GatewaySection) -> Self {
        Self {
            map_name: map_name.to_string(),
            tiles: vec![ServedTile {
                tile: WHOLE_MAP_TILE.to_string(),
                local_map: map_name.to_string(),
            }],
            index: None,
            iceoryx_prefix: None,
            config,
        }
    }

    /// A gateway for `tiles` of the tile set indexed by `index`, each served
    /// locally as `<map_name>.<tile>` (`kfmap serve --tiles`).
    pub fn tiled(
        map_name: &str,
        index: TileIndex,
        tiles: &[String],
        config: GatewaySection,
    ) -> Self {
        Self {
            map_name: map_name.to_string(),
            tiles: tiles
                .iter()
                .map(|tile| ServedTile {
                    tile: tile.clone(),
                    local_map: tile_map_name(map_name, tile),
                })
                .collect(),
            index: Some(index),
            iceoryx_prefix: None,
            config,
        }
    }
}

/// Why the gateway could not start.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// A map or tile name that cannot be a key chunk.
    #[error(transparent)]
    BadName(#[from] kfmap_protocol::remote::FrameError),
    /// No tile to announce.
    #[error("no tile to announce")]
    NoTiles,
    /// Zenoh could not be set up (open the session, declare a queryable or token).
    #[error("zenoh: {what}: {reason}")]
    Zenoh {
        /// What was done, with its key.
        what: String,
        /// Zenoh's reason.
        reason: String,
    },
    /// The local iceoryx2 side could not be set up.
    #[error(transparent)]
    Local(#[from] ClientError),
}

/// A failed Zenoh set-up step.
fn zenoh_failed(what: String, reason: impl std::fmt::Display) -> GatewayError {
    GatewayError::Zenoh {
        what,
        reason: reason.to_string(),
    }
}

/// Runs the gateway until `stop` is set: declares each tile's queryable (and the index's),
/// forwards, and keeps each tile's liveliness token in step with its local server.
/// `ready` is called once the Zenoh session is open, the queryables declared and each
/// server looked at once.
pub fn run(
    options: &GatewayOptions,
    stop: &Arc<AtomicBool>,
    ready: impl FnOnce(&[String]),
) -> Result<(), GatewayError> {
    check_key_chunk("map name", &options.map_name)?;
    if options.tiles.is_empty() {
        return Err(GatewayError::NoTiles);
    }
    for served in &options.tiles {
        check_key_chunk("tile", &served.tile)?;
    }
    let g = &options.config;
    let base = (!g.zenoh_config.is_empty()).then(|| PathBuf::from(&g.zenoh_config));
    let zconfig = zenoh_config(base.as_deref(), &g.listen, &g.connect)?;
    let session = zenoh::open(zconfig)
        .wait()
        .map_err(|e| zenoh_failed("open a session".into(), e))?;
    let mut queryables = Vec::new();
    let mut workers = Vec::new();
    let clients = Arc::new(bridge::ClientCap::new(g.max_sessions));
    for served in &options.tiles {
        let upstream = bridge::Upstream {
            local_map: served.local_map.clone(),
            remote_map: options.map_name.clone(),
            tile: served.tile.clone(),
            iceoryx_prefix: options.iceoryx_prefix.clone(),
            limits: g.clone(),
            clients: clients.clone(),
        };
        let (dispatch, threads) = bridge::Dispatch::start(&upstream, stop);
        workers.extend(threads);
        let key = rpc_queryable_key(&options.map_name, &served.tile);
        queryables.push(
            session
                .declare_queryable(&key)
                .complete(true)
                .callback(move |query| dispatch.dispatch(query))
                .wait()
                .map_err(|e| zenoh_failed(format!("declare the queryable {key}"), e))?,
        );
        tracing::info!(key, listen = ?g.listen, "gateway answering");
    }
    // The servers' ranking settings, learnt from their status when their tokens are
    // declared, published with the index.
    let ranking: Arc<Mutex<Option<PlaceRanking>>> = Arc::default();
    if let Some(index) = &options.index {
        let key = tile_index_key(&options.map_name);
        let index = index.clone();
        let known = ranking.clone();
        let reply_key = key.clone();
        queryables.push(
            session
                .declare_queryable(&key)
                .callback(move |query| {
                    let published = TileIndex {
                        ranking: *known.lock().unwrap_or_else(|e| e.into_inner()),
                        ..index.clone()
                    };
                    let text = published.to_toml();
                    if let Err(e) = query.reply(&reply_key, text.as_bytes()).wait() {
                        tracing::warn!("could not send the tile index: {e}");
                    }
                })
                .wait()
                .map_err(|e| zenoh_failed(format!("declare the queryable {key}"), e))?,
        );
    }
    // Ready once the servers' tokens are declared (if they run): a client that connects
    // on the ready line finds them.
    let watched = watch_servers(&session, options, &ranking, stop, || ready(&g.listen));
    drop(queryables);
    for worker in workers {
        let _ = worker.join();
    }
    let _ = session.close().wait();
    watched
}

/// Declares each tile's liveliness token while its local server answers, withdraws it
/// when the server is gone; returns when `stop` is set.
fn watch_servers(
    session: &zenoh::Session,
    options: &GatewayOptions,
    ranking: &Mutex<Option<PlaceRanking>>,
    stop: &AtomicBool,
    first_look: impl FnOnce(),
) -> Result<(), GatewayError> {
    let mut first_look = Some(first_look);
    let iceoryx = iceoryx_config(options.iceoryx_prefix.as_deref()).map_err(ClientError::from)?;
    let node = create_node(&iceoryx, "kfmap-gateway").map_err(ClientError::from)?;
    let period = Duration::from_millis(options.config.probe_interval_ms);
    let mut tokens: Vec<Option<zenoh::liveliness::LivelinessToken>> =
        options.tiles.iter().map(|_| None).collect();
    // Each tile's service, opened once: a probe then only reads its live server count
    // (reopening it every period cost milliseconds a tile under load).
    let mut services: Vec<Option<Rpc>> = options.tiles.iter().map(|_| None).collect();
    // Per tile, the server processes seen alive when its token was declared. A killed
    // server's ports stay registered until the dead-node cleanup below, which took 39 ms
    // for a three-tile server under load: its clients must hear sooner (the target: within 50 ms).
    let mut watched: Vec<Vec<u32>> = options.tiles.iter().map(|_| Vec::new()).collect();
    let mut last_cleanup = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        for ((served, token), pids) in options.tiles.iter().zip(&mut tokens).zip(&mut watched) {
            if token.is_some() && !pids.is_empty() && !pids.iter().any(|&p| process_alive(p)) {
                *token = None;
                tracing::warn!(
                    key = alive_key(&options.map_name, &served.tile),
                    "local server process gone: token withdrawn"
                );
            }
        }
        for (served, service) in options.tiles.iter().zip(&mut services) {
            if service.is_none() {
                *service = open_rpc(&node, &served.local_map).ok();
            }
        }
        let listed = |services: &[Option<Rpc>]| -> Vec<Vec<u32>> {
            services
                .iter()
                .map(|s| s.as_ref().map(server_processes).unwrap_or_default())
                .collect()
        };
        let mut listing = listed(&services);
        // A killed server's ports stay registered until some node cleans them up.
        // Cleaning lists every node of the prefix (files read and parsed): every 10 ms
        // it kept 7-18 % of a core busy per idle gateway, so only when a listed
        // server's process is gone (or out of sight), and now and then for other nodes.
        let dead_listed_server = listing.iter().flatten().any(|&p| !process_alive(p));
        if dead_listed_server || last_cleanup.elapsed() >= CLEANUP_INTERVAL {
            node.try_cleanup_dead_nodes();
            last_cleanup = Instant::now();
            listing = listed(&services);
        }
        for (((served, token), servers), pids) in options
            .tiles
            .iter()
            .zip(&mut tokens)
            .zip(listing)
            .zip(&mut watched)
        {
            let key = alive_key(&options.map_name, &served.tile);
            // Servers whose processes were seen to die are not probed: their requests
            // would wait for the cleanup or the timeout.
            let dead_listed = !pids.is_empty() && servers.iter().all(|p| pids.contains(p));
            let present = !servers.is_empty();
            if present
                && token.is_none()
                && !dead_listed
                && let Some(answered) = server_ranking(options, &served.local_map)
            {
                let mut known = ranking.lock().unwrap_or_else(|e| e.into_inner());
                match *known {
                    Some(first) if first != answered => tracing::warn!(
                        tile = served.tile,
                        "this tile's server ranks relocalization places otherwise ({answered:?}) than the first ({first:?}): clients rank by the first; give every tile's server the same [relocalize]"
                    ),
                    Some(_) => {}
                    None => *known = Some(answered),
                }
                drop(known);
                *token = Some(
                    session
                        .liveliness()
                        .declare_token(&key)
                        .wait()
                        .map_err(|e| zenoh_failed(format!("declare {key}"), e))?,
                );
                // Only processes this gateway can see (not another PID namespace's).
                *pids = servers.into_iter().filter(|&p| process_alive(p)).collect();
                tracing::info!(key, "local server answers: token declared");
            } else if !present {
                pids.clear();
                if token.take().is_some() {
                    tracing::warn!(key, "local server gone: token withdrawn");
                }
            }
        }
        if let Some(first_look) = first_look.take() {
            first_look();
        }
        std::thread::sleep(period);
    }
    Ok(())
}

/// Dead nodes of the prefix are cleaned up at least this often.
const CLEANUP_INTERVAL: Duration = Duration::from_secs(1);

/// True while process `pid` exists (Linux: its /proc entry).
fn process_alive(pid: u32) -> bool {
    std::path::Path::new(&format!("/proc/{pid}")).exists()
}

/// The local server of `local_map`'s ranking settings, when it answers a status request
/// (its map is loaded); `None` when it does not answer.
fn server_ranking(options: &GatewayOptions, local_map: &str) -> Option<PlaceRanking> {
    let client_options = ClientOptions {
        iceoryx_prefix: options.iceoryx_prefix.clone(),
        timeout: Duration::from_secs_f64(options.config.request_timeout_s),
        spin: false,
    };
    let mut connection = Connection::connect(local_map, client_options).ok()?;
    let probe = kfmap_protocol::RequestHeader {
        kind: kfmap_protocol::RequestKind::Status as u32,
        ..Default::default()
    };
    let answer = connection.call(probe, 0, |_, _| {}).ok()?;
    Some(
        answer
            .header
            .relocalize_ranking
            .to_ranking()
            .unwrap_or_else(|| {
                tracing::warn!(
                    local_map,
                    "the server sent invalid ranking settings: defaults published"
                );
                PlaceRanking::default()
            }),
    )
}
