//! The client's errors.

use std::time::Duration;

use kfmap_protocol::StatusCode;
use kfmap_protocol::transport::TransportError;
use kfmap_shared::registration::RegistrationError;

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// iceoryx2 setup or a port operation failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// No server serves this map name (under this iceoryx2 prefix).
    #[error(
        "no kfmap server serves map {0:?}; start one with `kfmap serve --map FILE --map-name NAME` (same --iceoryx-prefix; for a remote client also `kfmap gateway --map-name NAME` on the server's host)"
    )]
    NoServer(String),
    /// No answer within the timeout; the connection is rebuilt for the next call.
    #[error(
        "no answer from the server of map {map_name:?} within {waited:?}; it may have died (the next call reconnects)"
    )]
    Timeout {
        /// Map name.
        map_name: String,
        /// The timeout.
        waited: Duration,
    },
    /// The server stopped (or was replaced) after the request was sent, without answering
    /// it; the connection is rebuilt for the next call.
    #[error(
        "the server of map {0:?} stopped before answering (shut down or restarted); the next call reconnects"
    )]
    Disconnected(String),
    /// The server answered with an error status.
    #[error("server refused the request ({status:?}): {message}")]
    Rejected {
        /// Status code.
        status: StatusCode,
        /// The server's message.
        message: String,
        /// Detail, e.g. the index of a bad point.
        detail: u64,
    },
    /// Client-side registration failed.
    #[error(transparent)]
    Registration(#[from] RegistrationError),
    /// The remote link (Zenoh) failed: no gateway reachable, a bad Zenoh configuration, or
    /// the gateway could not use its local server.
    #[error("remote: {0}")]
    Remote(String),
    /// A parameter of the call is out of range.
    #[error("{0}")]
    Invalid(String),
}

impl ClientError {
    /// The server's status, when it refused the request.
    pub fn status(&self) -> Option<StatusCode> {
        match self {
            ClientError::Rejected { status, .. } => Some(*status),
            _ => None,
        }
    }
}
