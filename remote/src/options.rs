//! Where a remote client finds its gateways ([`RemoteOptions`]) and the Zenoh
//! configuration kfmap's remote client and gateway share ([`zenoh_config`]).

use std::path::PathBuf;

use kfmap_client::{ClientError, RemoteError};

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
    /// The one tile the requests go to; `None`: the map's tiles when its gateways serve a
    /// tile set (each request routed by its pose guess), else the map served whole.
    pub tile: Option<String>,
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
            tile: None,
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
        Some(path) => zenoh::Config::from_file(path)
            .map_err(|e| RemoteError::Config(format!("read {}: {e}", path.display())))?,
        None => zenoh::Config::default(),
    };
    let set = |config: &mut zenoh::Config, key: &str, value: String| {
        config.insert_json5(key, &value).map_err(|e| {
            ClientError::from(RemoteError::Config(format!("set {key} = {value}: {e}")))
        })
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
