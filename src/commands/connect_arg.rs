//! The arguments every client subcommand (`localize`, `query`, `relocalize`, `status`)
//! connects with: a server on this host (iceoryx2) or, with `--remote`, on another host
//! through its `kfmap gateway` (Zenoh).

use std::path::PathBuf;
use std::time::Duration;

use kfmap_client::{Client, ClientOptions};
use kfmap_remote::RemoteOptions;

/// Which server to talk to.
#[derive(clap::Args)]
pub struct ConnectArgs {
    /// The served map's name.
    #[arg(long)]
    pub map_name: String,
    /// Seconds to wait for each answer.
    #[arg(long, default_value_t = 5.0)]
    pub timeout: f64,
    /// iceoryx2 prefix (the server's).
    #[arg(long)]
    pub iceoryx_prefix: Option<String>,
    /// Reach the server on another host through its `kfmap gateway`: the gateway's Zenoh
    /// endpoint, e.g. tcp/10.0.0.5:7447 (several separated by commas).
    #[arg(long, value_name = "ENDPOINT")]
    pub remote: Option<String>,
    /// With --remote: a Zenoh config file (JSON5) for TLS, mutual TLS or other settings.
    #[arg(long, requires = "remote")]
    pub zenoh_config: Option<PathBuf>,
    /// With --remote: this client's id, the last chunk of its request keys (an access
    /// control list on the gateway grants keys by it; e.g. the name in its TLS
    /// certificate). Default: a random one.
    #[arg(long, requires = "remote")]
    pub client_id: Option<String>,
}

impl ConnectArgs {
    /// Connects to the server of `--map-name`.
    pub fn connect(&self) -> anyhow::Result<Client> {
        if !(self.timeout.is_finite() && self.timeout > 0.0) {
            anyhow::bail!(
                "--timeout must be a positive number of seconds, got {}",
                self.timeout
            );
        }
        let options = ClientOptions {
            iceoryx_prefix: self.iceoryx_prefix.clone(),
            timeout: Duration::from_secs_f64(self.timeout),
            spin: false,
        };
        Ok(match &self.remote {
            Some(endpoint) => {
                let mut remote = RemoteOptions::new(endpoint);
                remote.zenoh_config = self.zenoh_config.clone();
                remote.client_id = self.client_id.clone();
                kfmap_remote::connect_with(&remote, &self.map_name, options)?
            }
            None => Client::connect(&self.map_name, options)?,
        })
    }
}
