//! The arguments every client subcommand (`localize`, `query`, `status`) connects with.

use std::time::Duration;

use kfmap_client::{Client, ClientOptions};

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
        Ok(Client::connect(
            &self.map_name,
            ClientOptions {
                iceoryx_prefix: self.iceoryx_prefix.clone(),
                timeout: Duration::from_secs_f64(self.timeout),
                spin: false,
            },
        )?)
    }
}
