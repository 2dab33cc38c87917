//! The remote link: requests as Zenoh queries to a `kfmap gateway` on another host,
//! which answers them through its local map server (docs/DESIGN.md#notes-remote).
//! Frames and keys are `kfmap_protocol::remote`'s; this module only moves them.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use kfmap_protocol::remote::{RemoteFailure, WHOLE_MAP_TILE, alive_key, check_key_chunk, rpc_key};
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::SampleKind;

use crate::error::ClientError;

/// How a pending answer is watched: the token check runs this often, so a client learns
/// of a dead server within about this long after its gateway withdraws the token.
const WATCH_SLICE: Duration = Duration::from_millis(2);
/// How long a query that ended unanswered waits for the token to go (a dead gateway)
/// before it is read as a refusal.
const GONE_WAIT: Duration = Duration::from_millis(100);
/// Longest wait for the gateway's liveliness token when connecting.
const CONNECT_WAIT: Duration = Duration::from_secs(2);

/// Where and how a remote client reaches a gateway.
#[derive(Debug, Clone)]
pub struct RemoteOptions {
    /// Zenoh endpoints of gateways, e.g. `tcp/10.0.0.5:7447` (several: the client joins
    /// them all; a request goes to the one serving its tile).
    pub endpoints: Vec<String>,
    /// A Zenoh configuration file (JSON5) for TLS, mutual TLS or other transports; the
    /// endpoints above are added to its `connect` list.
    pub zenoh_config: Option<PathBuf>,
    /// This client's id, the last chunk of its request keys (access control lists grant
    /// keys by it); a random one when `None`.
    pub client_id: Option<String>,
    /// The tile the requests go to ([`WHOLE_MAP_TILE`] for a map served whole).
    pub tile: String,
}

impl RemoteOptions {
    /// Options for the gateways at `endpoints` (comma-separated), map served whole.
    pub fn new(endpoints: &str) -> Self {
        Self {
            endpoints: endpoints
                .split(',')
                .map(str::trim)
                .filter(|e| !e.is_empty())
                .map(str::to_string)
                .collect(),
            zenoh_config: None,
            client_id: None,
            tile: WHOLE_MAP_TILE.to_string(),
        }
    }
}

/// A Zenoh configuration for kfmap: `base` (a file) or Zenoh's defaults, then
/// multicast scouting off (peers are named, never discovered on a LAN), transport
/// compression off, `listen` on `listen` only (nothing when empty) and `connect` to
/// `connect`.
pub fn zenoh_config(
    base: Option<&std::path::Path>,
    listen: &[String],
    connect: &[String],
) -> Result<zenoh::Config, ClientError> {
    let mut config = match base {
        Some(path) => zenoh::Config::from_file(path).map_err(|e| {
            ClientError::Remote(format!("read the Zenoh config {}: {e}", path.display()))
        })?,
        None => zenoh::Config::default(),
    };
    let set = |config: &mut zenoh::Config, key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| ClientError::Remote(format!("set Zenoh config {key} = {value}: {e}")))
    };
    set(&mut config, "mode", "\"peer\"".into())?;
    set(&mut config, "scouting/multicast/enabled", "false".into())?;
    let list = |endpoints: &[String]| {
        let quoted: Vec<String> = endpoints.iter().map(|e| format!("{e:?}")).collect();
        format!("[{}]", quoted.join(","))
    };
    if base.is_none() || !listen.is_empty() {
        set(&mut config, "listen/endpoints", list(listen))?;
    }
    if !connect.is_empty() {
        set(&mut config, "connect/endpoints", list(connect))?;
        // Fail at open when no endpoint answers, rather than retrying forever.
        set(&mut config, "connect/exit_on_failure", "true".into())?;
        set(&mut config, "connect/timeout_ms", "3000".into())?;
    }
    Ok(config)
}

/// An open remote link to one tile of a map.
pub(crate) struct RemoteLink {
    session: zenoh::Session,
    key: String,
    map_name: String,
    tile: String,
    /// The tile's liveliness token is present (its server answers).
    alive: Arc<AtomicBool>,
    _token_watch: zenoh::pubsub::Subscriber<()>,
}

impl RemoteLink {
    /// Opens a Zenoh session to the gateways and waits for the tile's token.
    pub(crate) fn open(map_name: &str, remote: &RemoteOptions) -> Result<Self, ClientError> {
        check_key_chunk("map name", map_name).map_err(|e| ClientError::Invalid(e.to_string()))?;
        check_key_chunk("tile", &remote.tile).map_err(|e| ClientError::Invalid(e.to_string()))?;
        let client_id = match &remote.client_id {
            Some(id) => {
                check_key_chunk("client id", id)
                    .map_err(|e| ClientError::Invalid(e.to_string()))?;
                id.clone()
            }
            None => random_client_id(),
        };
        if remote.endpoints.is_empty() && remote.zenoh_config.is_none() {
            return Err(ClientError::Invalid(
                "a remote client needs a gateway endpoint, e.g. tcp/10.0.0.5:7447".into(),
            ));
        }
        let config = zenoh_config(remote.zenoh_config.as_deref(), &[], &remote.endpoints)?;
        let session = zenoh::open(config).wait().map_err(|e| {
            ClientError::Remote(format!(
                "connect to the gateway at {}: {e}",
                remote.endpoints.join(", ")
            ))
        })?;
        let alive = Arc::new(AtomicBool::new(false));
        let token = alive_key(map_name, &remote.tile);
        let flag = alive.clone();
        let token_watch = session
            .liveliness()
            .declare_subscriber(&token)
            .history(true)
            .callback(move |sample| {
                flag.store(sample.kind() == SampleKind::Put, Ordering::SeqCst);
            })
            .wait()
            .map_err(|e| ClientError::Remote(format!("watch {token}: {e}")))?;
        let link = Self {
            key: rpc_key(map_name, &remote.tile, &client_id),
            session,
            map_name: map_name.to_string(),
            tile: remote.tile.clone(),
            alive,
            _token_watch: token_watch,
        };
        // The tokens alive now (the subscriber above keeps the flag current after).
        let present = link
            .session
            .liveliness()
            .get(&token)
            .timeout(CONNECT_WAIT)
            .wait()
            .map_err(|e| ClientError::Remote(format!("look up {token}: {e}")))?
            .iter()
            .any(|reply| reply.result().is_ok());
        if present {
            link.alive.store(true, Ordering::SeqCst);
        }
        if !link.alive() {
            return Err(ClientError::NoServer(format!(
                "{map_name} (tile {} at {})",
                remote.tile,
                remote.endpoints.join(", ")
            )));
        }
        Ok(link)
    }

    /// True while the tile's gateway announces a live server.
    pub(crate) fn alive(&self) -> bool {
        self.alive.load(Ordering::SeqCst)
    }

    /// Sends a request frame and waits for the answer frame.
    pub(crate) fn call(&self, frame: Vec<u8>, timeout: Duration) -> Result<Vec<u8>, ClientError> {
        let was_alive = self.alive();
        if !was_alive {
            return Err(ClientError::NoServer(self.describe()));
        }
        let replies = self
            .session
            .get(&self.key)
            .payload(frame)
            .target(QueryTarget::BestMatching)
            .consolidation(ConsolidationMode::None)
            .timeout(timeout)
            .wait()
            .map_err(|e| ClientError::Remote(format!("send to {}: {e}", self.key)))?;
        let deadline = Instant::now() + timeout;
        loop {
            match replies.recv_timeout(WATCH_SLICE) {
                Ok(Some(reply)) => return self.answer(reply),
                Err(_) => return Err(self.ended_unanswered()),
                Ok(None) => {}
            }
            if !self.alive() {
                return Err(ClientError::Disconnected(self.describe()));
            }
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    map_name: self.describe(),
                    waited: timeout,
                });
            }
        }
    }

    /// Why a query ended with no reply: the gateway's session closed (its token goes
    /// with it, within a few milliseconds), or, while the token stays, the gateway
    /// refused to see the query (an access control list denying this client's key).
    fn ended_unanswered(&self) -> ClientError {
        let deadline = Instant::now() + GONE_WAIT;
        while Instant::now() < deadline {
            if !self.alive() {
                return ClientError::Disconnected(self.describe());
            }
            std::thread::sleep(WATCH_SLICE);
        }
        ClientError::Remote(format!(
            "the gateway of {} answered nothing while its server lives: its access control list may deny this client's key {}",
            self.describe(),
            self.key
        ))
    }

    fn answer(&self, reply: zenoh::query::Reply) -> Result<Vec<u8>, ClientError> {
        match reply.into_result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(error) => {
                let text = error
                    .payload()
                    .try_to_string()
                    .unwrap_or_default()
                    .into_owned();
                let (failure, message) = RemoteFailure::parse(&text);
                Err(match failure {
                    RemoteFailure::NoServer => ClientError::NoServer(self.describe()),
                    RemoteFailure::Disconnected => ClientError::Disconnected(self.describe()),
                    RemoteFailure::Timeout => ClientError::Timeout {
                        map_name: self.describe(),
                        waited: Duration::ZERO,
                    },
                    RemoteFailure::Gateway => ClientError::Remote(format!(
                        "the gateway of {} failed: {message}",
                        self.describe()
                    )),
                })
            }
        }
    }

    fn describe(&self) -> String {
        format!("{} (remote, tile {})", self.map_name, self.tile)
    }
}

/// A client id unlikely to collide: process id and clock.
fn random_client_id() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!("c{:x}-{:x}", std::process::id(), nanos as u64)
}
