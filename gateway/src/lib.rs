//! `kfmap gateway`: a sidecar beside `kfmap serve` that answers Zenoh queries from
//! other hosts through the local server (docs/DESIGN.md#notes-remote).
//!
//! It declares a queryable on `kfmap/<map>/v<protocol>/<tile>/rpc/*` and forwards each
//! query's frame over iceoryx2, one server session per remote client (the key's last
//! chunk), and holds the liveliness token `.../<tile>/alive` while the server answers:
//! remote clients learn within milliseconds that the server died (the token goes) or the
//! gateway died (Zenoh ends their pending queries), and when it is back.

mod bridge;
pub mod config;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use iceoryx2::prelude::PortFactory;
use kfmap_client::remote::zenoh_config;
use kfmap_client::{ClientError, ClientOptions, Connection};
use kfmap_protocol::remote::{WHOLE_MAP_TILE, alive_key, check_key_chunk, rpc_queryable_key};
use kfmap_protocol::transport::{create_node, iceoryx_config, open_rpc};
use zenoh::Wait;

pub use config::{GatewayConfig, GatewaySection};

/// What to serve.
#[derive(Debug, Clone)]
pub struct GatewayOptions {
    /// The served map's name (as `kfmap serve` announces it).
    pub map_name: String,
    /// The tile chunk of the keys ([`WHOLE_MAP_TILE`] for a map served whole).
    pub tile: String,
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
            tile: WHOLE_MAP_TILE.to_string(),
            iceoryx_prefix: None,
            config,
        }
    }
}

/// Why the gateway could not start.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// A name that cannot be a key chunk, or a bad setting.
    #[error("{0}")]
    Invalid(String),
    /// Zenoh could not be set up.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The local iceoryx2 side could not be set up.
    #[error(transparent)]
    Local(#[from] ClientError),
}

/// Runs the gateway until `stop` is set: declares the queryable, forwards, and keeps the
/// liveliness token in step with the local server. `ready` is called once the Zenoh
/// session is open and the queryable declared.
pub fn run(
    options: &GatewayOptions,
    stop: &Arc<AtomicBool>,
    ready: impl FnOnce(&[String]),
) -> Result<(), GatewayError> {
    check_key_chunk("map name", &options.map_name)
        .and_then(|_| check_key_chunk("tile", &options.tile))
        .map_err(|e| GatewayError::Invalid(e.to_string()))?;
    let g = &options.config;
    let base = (!g.zenoh_config.is_empty()).then(|| PathBuf::from(&g.zenoh_config));
    let zconfig = zenoh_config(base.as_deref(), &g.listen, &g.connect)?;
    let session = zenoh::open(zconfig)
        .wait()
        .map_err(|e| GatewayError::Zenoh(format!("open a session: {e}")))?;
    let upstream = bridge::Upstream {
        map_name: options.map_name.clone(),
        iceoryx_prefix: options.iceoryx_prefix.clone(),
        limits: g.clone(),
    };
    let (dispatch, workers) = bridge::Dispatch::start(&upstream, stop);
    let key = rpc_queryable_key(&options.map_name, &options.tile);
    let queryable = session
        .declare_queryable(&key)
        .complete(true)
        .callback(move |query| dispatch.dispatch(query))
        .wait()
        .map_err(|e| GatewayError::Zenoh(format!("declare the queryable {key}: {e}")))?;
    tracing::info!(key, listen = ?g.listen, "gateway answering");
    // Ready once the server's token is declared (if it runs): a client that connects
    // on the ready line finds it.
    let watched = watch_server(&session, options, stop, || ready(&g.listen));
    drop(queryable);
    for worker in workers {
        let _ = worker.join();
    }
    let _ = session.close().wait();
    watched
}

/// Declares the tile's liveliness token while the local server answers, withdraws it
/// when the server is gone; returns when `stop` is set.
fn watch_server(
    session: &zenoh::Session,
    options: &GatewayOptions,
    stop: &AtomicBool,
    first_look: impl FnOnce(),
) -> Result<(), GatewayError> {
    let mut first_look = Some(first_look);
    let iceoryx = iceoryx_config(options.iceoryx_prefix.as_deref()).map_err(ClientError::from)?;
    let node = create_node(&iceoryx, "kfmap-gateway").map_err(ClientError::from)?;
    let period = Duration::from_millis(options.config.probe_interval_ms);
    let key = alive_key(&options.map_name, &options.tile);
    let mut token: Option<zenoh::liveliness::LivelinessToken> = None;
    while !stop.load(Ordering::SeqCst) {
        // A killed server's ports stay registered until some node cleans them up.
        node.try_cleanup_dead_nodes();
        let present = open_rpc(&node, &options.map_name)
            .map(|rpc| rpc.dynamic_config().number_of_servers() > 0)
            .unwrap_or(false);
        if present && token.is_none() && server_answers(options) {
            token = Some(
                session
                    .liveliness()
                    .declare_token(&key)
                    .wait()
                    .map_err(|e| GatewayError::Zenoh(format!("declare {key}: {e}")))?,
            );
            tracing::info!(key, "local server answers: token declared");
        } else if !present && token.is_some() {
            token = None;
            tracing::warn!(key, "local server gone: token withdrawn");
        }
        if let Some(first_look) = first_look.take() {
            first_look();
        }
        std::thread::sleep(period);
    }
    Ok(())
}

/// True when the local server answers a status request (its map is loaded).
fn server_answers(options: &GatewayOptions) -> bool {
    let client_options = ClientOptions {
        iceoryx_prefix: options.iceoryx_prefix.clone(),
        timeout: Duration::from_secs_f64(options.config.request_timeout_s),
        spin: false,
    };
    let Ok(mut connection) = Connection::connect(&options.map_name, client_options) else {
        return false;
    };
    let probe = kfmap_protocol::RequestHeader {
        kind: kfmap_protocol::RequestKind::Status as u32,
        ..Default::default()
    };
    connection.call(probe, 0, |_, _| {}).is_ok()
}
