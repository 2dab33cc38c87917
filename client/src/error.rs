//! The client's errors.

use std::time::Duration;

use kfmap_geometry::registration::RegistrationError;
use kfmap_protocol::StatusCode;
use kfmap_protocol::transport::TransportError;

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
    /// The remote link (Zenoh, through `kfmap gateway`) failed; [`RemoteError`] says how.
    #[error("remote: {0}")]
    Remote(#[from] RemoteError),
    /// A parameter of the call is out of range.
    #[error("{0}")]
    Invalid(String),
}

/// How a remote link failed, so a caller can tell a configuration mistake from an
/// unreachable gateway, a denial, a gateway's own failure or a broken answer. (A missing
/// server, its death and timeouts are [`ClientError`]'s own variants, as locally.)
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    /// A Zenoh configuration file or setting was refused.
    #[error("the Zenoh configuration: {0}")]
    Config(String),
    /// No gateway answered at the endpoints.
    #[error("connect to the gateway at {endpoints}: {reason}")]
    Unreachable {
        /// The endpoints tried.
        endpoints: String,
        /// Zenoh's reason.
        reason: String,
    },
    /// A Zenoh operation on an open session failed (declare, send a query).
    #[error("{what}: {reason}")]
    Zenoh {
        /// What was done, with its key.
        what: String,
        /// Zenoh's reason.
        reason: String,
    },
    /// No reply while the tile's server lives: the gateway's access control list denies
    /// this client's key.
    #[error(
        "the gateway of {map} answered nothing while its server lives: its access control list may deny this client's key {key}"
    )]
    Denied {
        /// The map (and tile) asked.
        map: String,
        /// The key the query went out on.
        key: String,
    },
    /// The gateway failed on its side and said why.
    #[error("the gateway of {map} failed: {message}")]
    Gateway {
        /// The map (and tile) asked.
        map: String,
        /// The gateway's message.
        message: String,
    },
    /// A frame, tile index or answer that does not decode or does not fit the request.
    #[error("{0}")]
    BadAnswer(String),
    /// A map served in tiles whose gateways publish no tile index.
    #[error(
        "{map} is served in tiles, but no gateway answers its tile index on {key} within {waited:?}"
    )]
    NoIndex {
        /// The map asked.
        map: String,
        /// The index's key.
        key: String,
        /// How long the client waited.
        waited: Duration,
    },
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
