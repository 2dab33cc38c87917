//! The remote path's frames and key expressions (docs/DESIGN.md#notes-remote): what a
//! `kfmap gateway` and a remote client (`kfmap-remote`) exchange over Zenoh. No Zenoh
//! here: a frame is the request's or answer's `#[repr(C)]` header bytes followed by its
//! payload, the same bytes the iceoryx2 transport carries in shared memory
//! (little-endian hosts; a peer of the other byte order reads as a version mismatch).
//!
//! Keys: `kfmap/<map>/v<protocol>/<tile>/rpc/<client>` (one remote client's requests to
//! one tile), `kfmap/<map>/v<protocol>/<tile>/alive` (a liveliness token: the tile's
//! server answers). A map served whole is the tile [`WHOLE_MAP_TILE`].

use crate::{PROTOCOL_VERSION, RequestHeader, ResponseHeader, WirePairing};

/// The first chunk of every kfmap key expression.
pub const KEY_ROOT: &str = "kfmap";
/// The tile chunk of a map served whole (not cut into tiles).
pub const WHOLE_MAP_TILE: &str = "whole";
/// Request frames a gateway accepts by default, bytes (a 1M-point scan with view
/// directions is 24 MB; a 100k-point scan 1.2 MB).
pub const DEFAULT_MAX_REQUEST_BYTES: usize = 32 << 20;
/// Answer frames a gateway sends by default, bytes (a cov2cov answer for 100k points
/// is about 5.6 MB).
pub const DEFAULT_MAX_ANSWER_BYTES: usize = 64 << 20;

const REQUEST_HEADER_BYTES: usize = std::mem::size_of::<RequestHeader>();
const RESPONSE_HEADER_BYTES: usize = std::mem::size_of::<ResponseHeader>();
const PAIRING_BYTES: usize = std::mem::size_of::<WirePairing>();

/// A frame that cannot be read, or a name that cannot be a key chunk.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FrameError {
    /// Shorter than its header.
    #[error("a {what} frame of {len} bytes is shorter than its {header}-byte header")]
    Short {
        /// "request" or "answer".
        what: &'static str,
        /// The frame's bytes.
        len: usize,
        /// The header's bytes.
        header: usize,
    },
    /// The payload is not a whole number of elements.
    #[error("a {what} frame's payload of {len} bytes is not a multiple of {element} bytes")]
    Ragged {
        /// "request" or "answer".
        what: &'static str,
        /// Payload bytes.
        len: usize,
        /// Element bytes.
        element: usize,
    },
    /// Larger than the configured cap.
    #[error("a {what} frame of {len} bytes exceeds the limit of {limit} bytes")]
    TooLarge {
        /// "request" or "answer".
        what: &'static str,
        /// The frame's bytes.
        len: usize,
        /// The cap.
        limit: usize,
    },
    /// A map, tile or client name that is not a valid key chunk.
    #[error(
        "{what} {name:?} cannot be a Zenoh key chunk: it must be non-empty, without '/', '*', '$', '?' or '#'"
    )]
    BadName {
        /// "map name", "tile" or "client id".
        what: &'static str,
        /// The name.
        name: String,
    },
}

/// Checks that `name` can stand as one chunk of a key expression.
pub fn check_key_chunk(what: &'static str, name: &str) -> Result<(), FrameError> {
    let bad = name.is_empty()
        || name
            .chars()
            .any(|c| matches!(c, '/' | '*' | '$' | '?' | '#'));
    if bad {
        return Err(FrameError::BadName {
            what,
            name: name.to_string(),
        });
    }
    Ok(())
}

/// `kfmap/<map>/v<protocol>`: every key of a map at this protocol version.
pub fn map_key_prefix(map_name: &str) -> String {
    format!("{KEY_ROOT}/{map_name}/v{PROTOCOL_VERSION}")
}

/// The key one remote client sends a tile's requests to.
pub fn rpc_key(map_name: &str, tile: &str, client_id: &str) -> String {
    format!("{}/{tile}/rpc/{client_id}", map_key_prefix(map_name))
}

/// The key expression a gateway's queryable answers for one tile (every client).
pub fn rpc_queryable_key(map_name: &str, tile: &str) -> String {
    format!("{}/{tile}/rpc/*", map_key_prefix(map_name))
}

/// The liveliness token of a tile whose server answers.
pub fn alive_key(map_name: &str, tile: &str) -> String {
    format!("{}/{tile}/alive", map_key_prefix(map_name))
}

/// Every tile's requests from one client: what a relocalization over a tile set asks
/// (`QueryTarget::All`, every tile answers).
pub fn rpc_all_tiles_key(map_name: &str, client_id: &str) -> String {
    format!("{}/*/rpc/{client_id}", map_key_prefix(map_name))
}

/// The tile chunk of an rpc key of `map_name`, if it is one.
pub fn tile_of_rpc_key<'k>(map_name: &str, key: &'k str) -> Option<&'k str> {
    let rest = key
        .strip_prefix(&map_key_prefix(map_name))?
        .strip_prefix('/')?;
    let (tile, _) = rest.split_once("/rpc/")?;
    (!tile.contains('/')).then_some(tile)
}

/// The key a gateway answers a tile set's index on (`tiles.toml`'s text): a remote client
/// learns from it how to route requests to tiles.
pub fn tile_index_key(map_name: &str) -> String {
    format!("{}/index", map_key_prefix(map_name))
}

/// The local (iceoryx2) map name of one tile of a tile set, as `kfmap serve --tiles`
/// serves it: `<map>.<tile>`.
pub fn tile_map_name(map_name: &str, tile: &str) -> String {
    format!("{map_name}.{tile}")
}

/// Every tile's liveliness token of a map.
pub fn alive_pattern(map_name: &str) -> String {
    format!("{}/*/alive", map_key_prefix(map_name))
}

/// The tile chunk of an `alive` key of `map_name`, if it is one.
pub fn tile_of_alive_key<'k>(map_name: &str, key: &'k str) -> Option<&'k str> {
    let rest = key
        .strip_prefix(&map_key_prefix(map_name))?
        .strip_prefix('/')?;
    let tile = rest.strip_suffix("/alive")?;
    (!tile.contains('/')).then_some(tile)
}

/// The client id (last chunk) of an rpc key.
pub fn client_of_rpc_key(key: &str) -> Option<&str> {
    let (head, client) = key.rsplit_once('/')?;
    head.ends_with("/rpc").then_some(client)
}

/// A request frame: the header's bytes, then the payload's.
pub fn encode_request(header: &RequestHeader, payload: &[f32]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(REQUEST_HEADER_BYTES + 4 * payload.len());
    frame.extend_from_slice(bytemuck::bytes_of(header));
    frame.extend_from_slice(bytemuck::cast_slice(payload));
    frame
}

/// Reads a request frame of at most `max_bytes` (the header is copied out: the frame's
/// bytes need not be aligned). The header's fields are not checked here: the server
/// checks them as it checks every request.
pub fn decode_request(
    frame: &[u8],
    max_bytes: usize,
) -> Result<(RequestHeader, Vec<f32>), FrameError> {
    let what = "request";
    if frame.len() > max_bytes {
        return Err(FrameError::TooLarge {
            what,
            len: frame.len(),
            limit: max_bytes,
        });
    }
    let (head, payload) = split_frame(what, frame, REQUEST_HEADER_BYTES, 4)?;
    let header: RequestHeader = bytemuck::pod_read_unaligned(head);
    Ok((header, read_elements(payload)))
}

/// An answer frame: the header's bytes, then the pairings'.
pub fn encode_answer(header: &ResponseHeader, pairings: &[WirePairing]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(RESPONSE_HEADER_BYTES + PAIRING_BYTES * pairings.len());
    frame.extend_from_slice(bytemuck::bytes_of(header));
    frame.extend_from_slice(bytemuck::cast_slice(pairings));
    frame
}

/// The bytes of an answer frame with `pairings` pairings.
pub fn answer_frame_len(pairings: usize) -> usize {
    RESPONSE_HEADER_BYTES + PAIRING_BYTES * pairings
}

/// Reads an answer frame.
pub fn decode_answer(frame: &[u8]) -> Result<(ResponseHeader, Vec<WirePairing>), FrameError> {
    let (head, payload) = split_frame("answer", frame, RESPONSE_HEADER_BYTES, PAIRING_BYTES)?;
    let header: ResponseHeader = bytemuck::pod_read_unaligned(head);
    Ok((header, read_elements(payload)))
}

fn split_frame<'f>(
    what: &'static str,
    frame: &'f [u8],
    header: usize,
    element: usize,
) -> Result<(&'f [u8], &'f [u8]), FrameError> {
    if frame.len() < header {
        return Err(FrameError::Short {
            what,
            len: frame.len(),
            header,
        });
    }
    let (head, payload) = frame.split_at(header);
    if payload.len() % element != 0 {
        return Err(FrameError::Ragged {
            what,
            len: payload.len(),
            element,
        });
    }
    Ok((head, payload))
}

/// Copies whole elements out of possibly unaligned bytes.
fn read_elements<T: bytemuck::Pod>(bytes: &[u8]) -> Vec<T> {
    bytes
        .chunks_exact(std::mem::size_of::<T>())
        .map(bytemuck::pod_read_unaligned)
        .collect()
}

/// Why a gateway could not get an answer from its local server: sent as a Zenoh error
/// reply `"<code>: <message>"`, read back by the remote client as the error a local
/// client would have had.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RemoteFailure {
    /// No server serves the map on the gateway's host.
    NoServer,
    /// The server stopped before answering.
    Disconnected,
    /// The server did not answer in time.
    Timeout,
    /// The gateway failed (iceoryx2 setup, an oversize answer, ...); the message says.
    Gateway,
}

impl RemoteFailure {
    const ALL: [RemoteFailure; 4] = [
        RemoteFailure::NoServer,
        RemoteFailure::Disconnected,
        RemoteFailure::Timeout,
        RemoteFailure::Gateway,
    ];

    /// The code that starts the error reply.
    pub fn code(self) -> &'static str {
        match self {
            RemoteFailure::NoServer => "no-server",
            RemoteFailure::Disconnected => "disconnected",
            RemoteFailure::Timeout => "timeout",
            RemoteFailure::Gateway => "gateway",
        }
    }

    /// The error reply's text.
    pub fn reply(self, message: &str) -> String {
        format!("{}: {message}", self.code())
    }

    /// Reads an error reply's text (an unknown code reads as `Gateway`).
    pub fn parse(text: &str) -> (RemoteFailure, &str) {
        let (code, message) = text.split_once(": ").unwrap_or(("", text));
        let failure = Self::ALL
            .into_iter()
            .find(|f| f.code() == code)
            .unwrap_or(RemoteFailure::Gateway);
        (failure, message)
    }
}
