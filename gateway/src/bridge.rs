//! Forwarding: Zenoh queries to the local server over iceoryx2, each remote client
//! through a connection (and so a server session) of its own.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use kfmap_client::{ClientError, ClientOptions, Connection};
use kfmap_protocol::remote::{
    RemoteFailure, answer_frame_len, client_of_rpc_key, decode_request, encode_answer, rpc_key,
};
use kfmap_protocol::{ResponseHeader, StatusCode, check_version};
use zenoh::Wait;
use zenoh::query::Query;

use crate::config::GatewaySection;

/// What a forwarding worker needs to reach the server.
#[derive(Clone)]
pub(crate) struct Upstream {
    /// The local server's (iceoryx2) map name.
    pub local_map: String,
    /// The map's name in the keys.
    pub remote_map: String,
    /// The tile chunk of the keys.
    pub tile: String,
    pub iceoryx_prefix: Option<String>,
    pub limits: GatewaySection,
    /// The remote clients the whole gateway serves (every tile, every worker).
    pub clients: Arc<ClientCap>,
}

/// The gateway's one cap on remote clients served at once (`max-sessions`): a client
/// holds a place while it has a session with any tile's server, whichever worker owns it.
pub(crate) struct ClientCap {
    max: usize,
    /// Per client id, its open sessions (one per tile it talks to).
    sessions: Mutex<HashMap<String, usize>>,
}

impl ClientCap {
    pub fn new(max: usize) -> Self {
        Self {
            max,
            sessions: Mutex::new(HashMap::new()),
        }
    }

    /// Takes a session for `client`: always granted to a client already served (another
    /// tile of the same robot), to a new one only while fewer than `max` are served.
    /// `Err` holds the count served.
    fn admit(&self, client: &str) -> Result<(), usize> {
        let mut sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(open) = sessions.get_mut(client) {
            *open += 1;
            return Ok(());
        }
        if sessions.len() >= self.max {
            return Err(sessions.len());
        }
        sessions.insert(client.to_string(), 1);
        Ok(())
    }

    /// Gives back one session of `client`.
    fn release(&self, client: &str) {
        let mut sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(open) = sessions.get_mut(client) {
            *open -= 1;
            if *open == 0 {
                sessions.remove(client);
            }
        }
    }
}

impl Upstream {
    /// The concrete key a reply to `query` goes out on: a query over every tile
    /// (relocalization) learns from it which tile answered.
    fn reply_key(&self, query: &Query) -> String {
        let client = client_of_rpc_key(query.key_expr().as_str()).unwrap_or("unknown");
        rpc_key(&self.remote_map, &self.tile, client)
    }
}

/// The queues into the workers; a client's queries always go to the same worker.
pub(crate) struct Dispatch {
    queues: Vec<SyncSender<Query>>,
    upstream: Upstream,
}

impl Dispatch {
    /// Starts `limits.workers` forwarding threads.
    pub fn start(
        upstream: &Upstream,
        stop: &Arc<AtomicBool>,
    ) -> (Self, Vec<std::thread::JoinHandle<()>>) {
        let mut queues = Vec::new();
        let mut threads = Vec::new();
        for index in 0..upstream.limits.workers {
            let (sender, receiver) = std::sync::mpsc::sync_channel(upstream.limits.queue_depth);
            queues.push(sender);
            let upstream = upstream.clone();
            let stop = stop.clone();
            let thread = std::thread::Builder::new()
                .name(format!("kfmap-gateway-{index}"))
                .spawn(move || Worker::new(upstream).run(receiver, &stop))
                .expect("spawn a gateway worker");
            threads.push(thread);
        }
        (
            Self {
                queues,
                upstream: upstream.clone(),
            },
            threads,
        )
    }

    /// Hands a query to its client's worker; a full queue is answered Busy at once
    /// (Zenoh's receive thread never waits here).
    pub fn dispatch(&self, query: Query) {
        let client = client_of_rpc_key(query.key_expr().as_str()).unwrap_or("");
        let worker = (fnv1a(client.as_bytes()) % self.queues.len() as u64) as usize;
        match self.queues[worker].try_send(query) {
            Ok(()) => {}
            Err(TrySendError::Full(query)) | Err(TrySendError::Disconnected(query)) => {
                let refusal = ResponseHeader::refusal(
                    request_id_of(&query),
                    StatusCode::Busy,
                    "the gateway's queue for this client is full (gateway.toml queue-depth); retry later",
                );
                reply_frame(
                    &query,
                    self.upstream.reply_key(&query),
                    encode_answer(&refusal, &[]),
                );
            }
        }
    }
}

/// One remote client's connection to the server.
struct Session {
    connection: Connection,
    last_used: Instant,
}

/// A forwarding thread: owns the connections of the clients it serves (iceoryx2 ports
/// stay on the thread that made them).
struct Worker {
    upstream: Upstream,
    sessions: HashMap<String, Session>,
}

impl Worker {
    fn new(upstream: Upstream) -> Self {
        Self {
            upstream,
            sessions: HashMap::new(),
        }
    }

    fn run(mut self, queries: Receiver<Query>, stop: &AtomicBool) {
        while !stop.load(Ordering::SeqCst) {
            match queries.recv_timeout(Duration::from_millis(100)) {
                Ok(query) => self.answer(&query),
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            }
            self.close_idle();
        }
    }

    fn close_idle(&mut self) {
        let idle = Duration::from_secs_f64(self.upstream.limits.session_idle_s);
        let clients = &self.upstream.clients;
        self.sessions.retain(|client, session| {
            let keep = session.last_used.elapsed() < idle;
            if !keep {
                clients.release(client);
                tracing::info!(client, "remote session closed after {idle:?} idle");
            }
            keep
        });
    }

    fn answer(&mut self, query: &Query) {
        let key = self.upstream.reply_key(query);
        let frame = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
        let max_request = self.upstream.limits.max_request_bytes;
        let (header, payload) = match decode_request(&frame, max_request) {
            Ok(decoded) => decoded,
            Err(e) => {
                let status = match e {
                    kfmap_protocol::remote::FrameError::TooLarge { .. } => StatusCode::TooLarge,
                    _ => StatusCode::BadRequest,
                };
                let hint = if status == StatusCode::TooLarge {
                    " (gateway.toml max-request-bytes)"
                } else {
                    ""
                };
                let refusal =
                    ResponseHeader::refusal(request_id_of(query), status, &format!("{e}{hint}"));
                return reply_frame(query, key, encode_answer(&refusal, &[]));
            }
        };
        if let Err(rejection) = check_version(&header) {
            let mut refusal =
                ResponseHeader::refusal(header.request_id, rejection.status, &rejection.message);
            refusal.detail = rejection.detail;
            return reply_frame(query, key, encode_answer(&refusal, &[]));
        }
        let client = client_of_rpc_key(query.key_expr().as_str())
            .unwrap_or("")
            .to_string();
        let max_answer = self.upstream.limits.max_answer_bytes;
        let session = match self.session(&client) {
            Ok(session) => session,
            Err(SessionRefused::Full(served)) => {
                let refusal = ResponseHeader::refusal(
                    header.request_id,
                    StatusCode::Busy,
                    &format!(
                        "the gateway serves {served} remote clients already (gateway.toml max-sessions); a session idle for session-idle-s frees a place, retry later"
                    ),
                );
                return reply_frame(query, key, encode_answer(&refusal, &[]));
            }
            Err(SessionRefused::Local(failure)) => return reply_failure(query, failure),
        };
        session.last_used = Instant::now();
        let request_id = header.request_id;
        let started = Instant::now();
        let forwarded = session.connection.forward(header, &payload, |answer, pairings| {
            if answer_frame_len(pairings.len()) > max_answer {
                let refusal = ResponseHeader::refusal(
                    request_id,
                    StatusCode::TooLarge,
                    &format!(
                        "the answer of {} bytes exceeds the gateway's max-answer-bytes {max_answer}; send fewer points or use server-side localize",
                        answer_frame_len(pairings.len())
                    ),
                );
                return encode_answer(&refusal, &[]);
            }
            let mut answer = *answer;
            answer.request_id = request_id;
            encode_answer(&answer, pairings)
        });
        match forwarded {
            Ok(frame) => reply_frame(query, key, frame),
            Err(error) => {
                tracing::warn!(
                    client,
                    "request failed after {:?}: {error}",
                    started.elapsed()
                );
                // A connection that lost its server is rebuilt on the client's next request.
                if self.sessions.remove(&client).is_some() {
                    self.upstream.clients.release(&client);
                }
                reply_failure(query, failure_of(&error));
            }
        }
    }

    /// The client's session, opened on first use.
    fn session(&mut self, client: &str) -> Result<&mut Session, SessionRefused> {
        if !self.sessions.contains_key(client) {
            self.upstream
                .clients
                .admit(client)
                .map_err(SessionRefused::Full)?;
            let options = ClientOptions {
                iceoryx_prefix: self.upstream.iceoryx_prefix.clone(),
                timeout: Duration::from_secs_f64(self.upstream.limits.request_timeout_s),
                spin: false,
            };
            let connection = match Connection::connect(&self.upstream.local_map, options) {
                Ok(connection) => connection,
                Err(e) => {
                    self.upstream.clients.release(client);
                    return Err(SessionRefused::Local(failure_of(&e)));
                }
            };
            tracing::info!(client, "remote session opened");
            self.sessions.insert(
                client.to_string(),
                Session {
                    connection,
                    last_used: Instant::now(),
                },
            );
        }
        Ok(self.sessions.get_mut(client).expect("inserted above"))
    }
}

/// Why a client got no session.
enum SessionRefused {
    /// `max-sessions` clients are served already (this many).
    Full(usize),
    /// The local server could not be reached.
    Local((RemoteFailure, String)),
}

/// The remote failure a local client error stands for.
fn failure_of(error: &ClientError) -> (RemoteFailure, String) {
    let failure = match error {
        ClientError::NoServer(_) => RemoteFailure::NoServer,
        ClientError::Disconnected(_) => RemoteFailure::Disconnected,
        ClientError::Timeout { .. } => RemoteFailure::Timeout,
        _ => RemoteFailure::Gateway,
    };
    (failure, error.to_string())
}

fn reply_failure(query: &Query, (failure, message): (RemoteFailure, String)) {
    if let Err(e) = query.reply_err(failure.reply(&message)).wait() {
        tracing::warn!("could not send an error reply: {e}");
    }
}

fn reply_frame(query: &Query, key: String, frame: Vec<u8>) {
    if let Err(e) = query.reply(key, frame).wait() {
        tracing::warn!("could not send a reply: {e}");
    }
}

/// The request id in a frame too broken to decode, when its first 16 bytes exist.
fn request_id_of(query: &Query) -> u64 {
    let frame = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
    frame
        .get(8..16)
        .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
        .unwrap_or(0)
}

/// FNV-1a: a stable hash spreading client ids over workers.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ *b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}
