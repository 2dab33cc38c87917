//! `gateway.toml`: the gateway's configuration, validated.

use kfmap_geometry::options::{ConfigFile, InvalidOption, ensure};
use serde::{Deserialize, Serialize};

/// The default `config/gateway.toml`, as shipped.
pub const DEFAULT_GATEWAY_TOML: &str = include_str!("../../config/gateway.toml");

/// `[gateway]` of `gateway.toml` (each key is explained in the shipped file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct GatewaySection {
    /// Zenoh endpoints to listen on.
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to.
    pub connect: Vec<String>,
    /// A Zenoh JSON5 configuration file; empty: Zenoh's defaults.
    pub zenoh_config: String,
    /// Forwarding threads.
    pub workers: usize,
    /// Queries waiting per worker.
    pub queue_depth: usize,
    /// Largest request frame, bytes.
    pub max_request_bytes: usize,
    /// Largest answer frame, bytes.
    pub max_answer_bytes: usize,
    /// Remote clients served at once.
    pub max_sessions: usize,
    /// Idle time after which a remote client's session closes, seconds.
    pub session_idle_s: f64,
    /// Longest wait for the local server, seconds.
    pub request_timeout_s: f64,
    /// Liveness check period, milliseconds.
    pub probe_interval_ms: u64,
}

impl Default for GatewaySection {
    fn default() -> Self {
        Self {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: Vec::new(),
            zenoh_config: String::new(),
            workers: 2,
            queue_depth: 16,
            max_request_bytes: kfmap_protocol::remote::DEFAULT_MAX_REQUEST_BYTES,
            max_answer_bytes: kfmap_protocol::remote::DEFAULT_MAX_ANSWER_BYTES,
            max_sessions: 16,
            session_idle_s: 60.0,
            request_timeout_s: 5.0,
            probe_interval_ms: 10,
        }
    }
}

/// The whole `gateway.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GatewayConfig {
    /// `[gateway]`.
    pub gateway: GatewaySection,
}

impl ConfigFile for GatewayConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_GATEWAY_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        let g = &self.gateway;
        let check = || -> Result<(), InvalidOption> {
            ensure(
                g.listen.iter().chain(&g.connect).all(|e| e.contains('/')),
                "listen/connect",
                format!("{:?} {:?}", g.listen, g.connect),
                "Zenoh endpoints such as tcp/127.0.0.1:7447",
            )?;
            ensure(
                (1..=64).contains(&g.workers),
                "workers",
                g.workers,
                "1 to 64",
            )?;
            ensure(
                (1..=4096).contains(&g.queue_depth),
                "queue-depth",
                g.queue_depth,
                "1 to 4096",
            )?;
            ensure(
                g.max_request_bytes >= 1024,
                "max-request-bytes",
                g.max_request_bytes,
                "at least 1024",
            )?;
            ensure(
                g.max_answer_bytes >= 4096,
                "max-answer-bytes",
                g.max_answer_bytes,
                "at least 4096 (an answer header is 3416 bytes)",
            )?;
            ensure(
                (1..=1024).contains(&g.max_sessions),
                "max-sessions",
                g.max_sessions,
                "1 to 1024",
            )?;
            ensure(
                g.session_idle_s.is_finite() && g.session_idle_s > 0.0,
                "session-idle-s",
                g.session_idle_s,
                "seconds > 0",
            )?;
            ensure(
                g.request_timeout_s.is_finite() && g.request_timeout_s > 0.0,
                "request-timeout-s",
                g.request_timeout_s,
                "seconds > 0",
            )?;
            ensure(
                (1..=1000).contains(&g.probe_interval_ms),
                "probe-interval-ms",
                g.probe_interval_ms,
                "1 to 1000",
            )
        };
        check().map_err(|e| ("gateway", e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn the_shipped_file_is_the_defaults() {
        let shipped =
            GatewayConfig::from_toml(DEFAULT_GATEWAY_TOML, Path::new("gateway.toml")).unwrap();
        assert_eq!(shipped, GatewayConfig::default());
    }

    #[test]
    fn bad_values_name_their_key() {
        for (text, key) in [
            ("[gateway]\nworkers = 0", "workers"),
            ("[gateway]\nlisten = [\"127.0.0.1\"]", "listen"),
            ("[gateway]\nrequest-timeout-s = -1.0", "request-timeout-s"),
        ] {
            let err = GatewayConfig::from_toml(text, Path::new("g.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{err}");
        }
        let err = GatewayConfig::from_toml("[gateway]\nlisten-on = []", Path::new("g.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("listen-on"), "{err}");
    }
}
