//! The connection to a map server: iceoryx2 ports, one request at a time with a
//! timeout, and reconnection after a timeout (a killed server never tells its clients,
//! so a timeout is when dead nodes are cleaned up and the ports rebuilt).

use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::client::Client as RpcClient;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::PortFactory;
use kfmap_geometry::cov::CovOptions;
use kfmap_map::tiles::TileIndex;
use kfmap_protocol::transport::{
    ALLOCATION, INITIAL_SLICE_LEN, Transport, create_node, iceoryx_config, iox, no_room_for_client,
    open_request_event, open_response_event, open_rpc,
};
use std::mem::MaybeUninit;

use kfmap_protocol::{
    PROTOCOL_VERSION, RequestHeader, ResponseHeader, ScanPayload, StatusCode, WirePairing,
};

use crate::error::ClientError;

/// A response is polled for this long before the client sleeps on the event: quick
/// answers then need no wake-up (tens of microseconds on virtual machines).
const POLL_BEFORE_SLEEP: Duration = Duration::from_micros(50);

/// Longest sleep on the response event between looks at whether the server is still
/// there: a killed server sends no event, so this bounds how late its death is noticed
/// (a gateway turns it into a remote client's error, to be heard within 50 ms).
const PRESENCE_CHECK: Duration = Duration::from_millis(5);

/// How to connect.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// iceoryx2 prefix; must equal the server's.
    pub iceoryx_prefix: Option<String>,
    /// Longest wait for one answer.
    pub timeout: Duration,
    /// Poll for the answer instead of sleeping on the event (lower latency).
    pub spin: bool,
}

impl Default for ClientOptions {
    fn default() -> Self {
        Self {
            iceoryx_prefix: None,
            timeout: Duration::from_secs(5),
            spin: false,
        }
    }
}

/// A response copied out of shared memory.
#[derive(Debug, Clone)]
pub struct Response {
    /// The server's header (status already checked: `Ok`).
    pub header: ResponseHeader,
    /// Pairings.
    pub pairings: Vec<WirePairing>,
}

type Port = RpcClient<Transport, [f32], RequestHeader, [WirePairing], ResponseHeader>;
/// A request sent and not yet answered.
type Pending = iceoryx2::pending_response::PendingResponse<
    Transport,
    [f32],
    RequestHeader,
    [WirePairing],
    ResponseHeader,
>;

struct Ports {
    rpc: Port,
    requests: Notifier<Transport>,
    responses: Listener<Transport>,
}

/// Answers requests inside the server's own process: what a server gives the client
/// it hosts (its session's tracker), so the hosted client runs the same code as one
/// over iceoryx2 without a round trip.
pub trait Dispatch: Send {
    /// The answer to one request (any status; the connection checks it).
    fn answer(
        &mut self,
        header: &RequestHeader,
        payload: &[f32],
    ) -> (ResponseHeader, Vec<WirePairing>);
}

/// A link to a map server on another host that carries requests and answers as frames
/// (`kfmap_protocol::remote`): `kfmap-remote` implements it over Zenoh to a `kfmap
/// gateway`. Here so this crate, and the server that hosts its tracker, compile
/// without a network stack.
pub trait RemoteLink: Send {
    /// Sends a request (`header` also routes it; the link frames it, or splits it into
    /// phases over a tile set) and waits at most `timeout` for the answer frame.
    fn call(
        &mut self,
        header: &RequestHeader,
        payload: &[f32],
        timeout: Duration,
    ) -> Result<Vec<u8>, ClientError>;
    /// True while a server answers on the other side.
    fn alive(&self) -> bool;
    /// The tile set's index, when the map is served in tiles.
    fn tile_index(&self) -> Option<&TileIndex>;
    /// The tile the last request went to.
    fn current_tile(&self) -> Option<&str>;
}

/// A connection to the server of one map.
pub struct Connection {
    link: Link,
    map_name: String,
    options: ClientOptions,
    client_node: [u64; 2],
    next_request_id: u64,
    /// The server's `[covariance]` from its status report, once asked; forgotten on
    /// reconnection (a restarted server may be configured otherwise).
    pub(crate) served_covariance: Option<CovOptions>,
}

/// How requests travel: iceoryx2 on the host, or Zenoh to a gateway on another host.
// One per connection, never moved on the hot path: no box for the large local ports.
#[allow(clippy::large_enum_variant)]
enum Link {
    Local {
        node: Node<Transport>,
        ports: Option<Ports>,
    },
    Remote(Box<dyn RemoteLink>),
    InProcess(Box<dyn Dispatch>),
}

impl Connection {
    /// Connects to the server of `map_name`; fails with `NoServer` when none runs.
    pub fn connect(map_name: &str, options: ClientOptions) -> Result<Self, ClientError> {
        let config = iceoryx_config(options.iceoryx_prefix.as_deref())?;
        let node = create_node(&config, "kfmap-client")?;
        let id = node.id().value();
        let mut connection = Self {
            link: Link::Local { node, ports: None },
            map_name: map_name.to_string(),
            options,
            client_node: [(id >> 64) as u64, id as u64],
            next_request_id: 1,
            served_covariance: None,
        };
        connection.ports()?;
        if !connection.server_present()? {
            return Err(ClientError::NoServer(map_name.to_string()));
        }
        Ok(connection)
    }

    /// A connection whose requests `dispatch` answers in this process (a server hosting
    /// a client); `client_node` is written into every request.
    pub fn in_process(map_name: &str, client_node: [u64; 2], dispatch: Box<dyn Dispatch>) -> Self {
        Self {
            link: Link::InProcess(dispatch),
            map_name: map_name.to_string(),
            options: ClientOptions::default(),
            client_node,
            next_request_id: 1,
            served_covariance: None,
        }
    }

    /// A connection to the server of `map_name` on another host over an open `link`
    /// (`kfmap_remote::connect` opens one through a `kfmap gateway`).
    pub fn over_remote(map_name: &str, link: Box<dyn RemoteLink>, options: ClientOptions) -> Self {
        Self {
            link: Link::Remote(link),
            map_name: map_name.to_string(),
            options,
            // The gateway gives each remote client a session of its own on its server.
            client_node: [0; 2],
            next_request_id: 1,
            served_covariance: None,
        }
    }

    /// The tile set's index when the map is served remotely in tiles.
    pub fn tile_index(&self) -> Option<&TileIndex> {
        match &self.link {
            Link::Remote(link) => link.tile_index(),
            Link::Local { .. } | Link::InProcess(_) => None,
        }
    }

    /// The tile the last remote request went to (`None` on the host, or before any).
    pub fn current_tile(&self) -> Option<&str> {
        match &self.link {
            Link::Remote(link) => link.current_tile(),
            Link::Local { .. } | Link::InProcess(_) => None,
        }
    }

    /// True when requests travel to another host (through a gateway).
    pub fn is_remote(&self) -> bool {
        matches!(self.link, Link::Remote(_))
    }

    /// This client's node id, as it writes it into every request's `client_node`.
    pub fn client_node(&self) -> [u64; 2] {
        self.client_node
    }

    /// Writes `node` into later requests' `client_node` instead of this client's own:
    /// only for tests that the server refuses it (status `NotYourSession`).
    pub fn claim_client_node(&mut self, node: [u64; 2]) {
        self.client_node = node;
    }

    /// The map name.
    pub fn map_name(&self) -> &str {
        &self.map_name
    }

    /// The per-call timeout.
    pub fn timeout(&self) -> Duration {
        self.options.timeout
    }

    fn ports(&mut self) -> Result<(&Node<Transport>, &Ports), ClientError> {
        let Link::Local { node, ports } = &mut self.link else {
            return Err(ClientError::Invalid(
                "this request needs a connection on the server's host (iceoryx2)".into(),
            ));
        };
        if ports.is_none() {
            let service = open_rpc(node, &self.map_name)?;
            if let Some(e) = no_room_for_client(&service, &self.map_name, std::process::id()) {
                return Err(e.into());
            }
            let rpc = service
                .client_builder()
                .initial_max_slice_len(INITIAL_SLICE_LEN)
                .allocation_strategy(ALLOCATION)
                .create()
                .map_err(|e| {
                    // The table may have filled since the look above.
                    no_room_for_client(&service, &self.map_name, std::process::id())
                        .unwrap_or_else(|| iox("create the client port")(e))
                })?;
            let requests = open_request_event(node, &self.map_name)?
                .notifier_builder()
                .create()
                .map_err(iox("create the request notifier"))?;
            let responses = open_response_event(node, &self.map_name)?
                .listener_builder()
                .create()
                .map_err(iox("create the response listener"))?;
            *ports = Some(Ports {
                rpc,
                requests,
                responses,
            });
        }
        Ok((node, ports.as_ref().expect("set above")))
    }

    /// True when a server is attached to the map's service.
    pub fn server_present(&mut self) -> Result<bool, ClientError> {
        match &self.link {
            Link::Local { node, .. } => {
                let rpc = open_rpc(node, &self.map_name)?;
                Ok(rpc.dynamic_config().number_of_servers() > 0)
            }
            Link::Remote(link) => Ok(link.alive()),
            Link::InProcess(_) => Ok(true),
        }
    }

    /// Sends one request (`fill` writes the `len` payload floats, zeroed first) and
    /// waits for its answer. Error statuses become `ClientError::Rejected`.
    pub fn call(
        &mut self,
        mut header: RequestHeader,
        len: usize,
        fill: impl FnOnce(&mut RequestHeader, &mut [f32]),
    ) -> Result<Response, ClientError> {
        header.version = PROTOCOL_VERSION;
        self.call_raw(header, len, fill)
    }

    /// As [`Self::call`] without setting the protocol version (for tests of version
    /// checks).
    pub fn call_raw(
        &mut self,
        header: RequestHeader,
        len: usize,
        fill: impl FnOnce(&mut RequestHeader, &mut [f32]),
    ) -> Result<Response, ClientError> {
        let init = |h: &mut RequestHeader, payload: &mut [MaybeUninit<f32>]| {
            payload.fill(MaybeUninit::new(0.0));
            // SAFETY: the line above initialized every element of `payload`, and
            // `MaybeUninit<f32>` has the layout of `f32`.
            let floats = unsafe { &mut *(payload as *mut [MaybeUninit<f32>] as *mut [f32]) };
            fill(h, floats);
            floats.len()
        };
        self.send_and_wait(header, len, init, copy_out)
    }

    /// Sends a scan request, written straight into shared memory.
    pub fn call_scan(
        &mut self,
        header: RequestHeader,
        scan: &ScanPayload,
    ) -> Result<Response, ClientError> {
        self.call_scan_with(header, scan, copy_out)
    }

    /// As [`Self::call_scan`], but `read` sees the answer in place in shared memory
    /// (status already checked: `Ok`), so large answers need not be copied.
    pub fn call_scan_with<R>(
        &mut self,
        mut header: RequestHeader,
        scan: &ScanPayload,
        read: impl FnOnce(&ResponseHeader, &[WirePairing]) -> R,
    ) -> Result<R, ClientError> {
        scan.check_lengths().map_err(ClientError::Invalid)?;
        header.version = PROTOCOL_VERSION;
        // `write` initializes exactly `float_len` floats: the whole loan.
        self.send_and_wait(
            header,
            scan.float_len(),
            |h, payload| scan.write(h, payload),
            read,
        )
    }

    /// Sends a scan request and abandons it: its answer is never read and the port's
    /// one request slot stays taken. Only for tests of what such a client costs the
    /// server.
    pub fn send_unread(
        &mut self,
        mut header: RequestHeader,
        scan: &ScanPayload,
    ) -> Result<(), ClientError> {
        scan.check_lengths().map_err(ClientError::Invalid)?;
        header.version = PROTOCOL_VERSION;
        let (pending, _) = self.send(header, scan.float_len(), |h, payload| {
            scan.write(h, payload)
        })?;
        std::mem::forget(pending);
        Ok(())
    }

    /// Loans `len` floats, lets `init` initialize them (it returns how many it wrote),
    /// sends, and wakes the server.
    fn send(
        &mut self,
        mut header: RequestHeader,
        len: usize,
        init: impl FnOnce(&mut RequestHeader, &mut [MaybeUninit<f32>]) -> usize,
    ) -> Result<(Pending, &Ports), ClientError> {
        header.client_node = self.client_node;
        header.request_id = self.next_request_id;
        self.next_request_id += 1;
        let (_, ports) = self.ports()?;
        let mut request = ports
            .rpc
            .loan_slice_uninit(len)
            .map_err(|e| ClientError::Transport(iox("loan a request")(e)))?;
        let written = init(&mut header, request.payload_mut());
        assert_eq!(written, len, "a request's payload is written whole");
        *request.user_header_mut() = header;
        // SAFETY: `init` wrote the first `written` floats of the `len`-float loan (it
        // counts its writes: `ScanPayload::write`, or `call_raw`'s zero-fill), and the
        // assertion above checked `written == len`: every float is initialized.
        let request = unsafe { request.assume_init() };
        let pending = request
            .send()
            .map_err(|e| ClientError::Transport(iox("send a request")(e)))?;
        let _ = ports.requests.notify();
        Ok((pending, ports))
    }

    /// Sends (see [`Self::send`]), waits, and hands an `Ok` answer to `read`.
    fn send_and_wait<R>(
        &mut self,
        header: RequestHeader,
        len: usize,
        init: impl FnOnce(&mut RequestHeader, &mut [MaybeUninit<f32>]) -> usize,
        read: impl FnOnce(&ResponseHeader, &[WirePairing]) -> R,
    ) -> Result<R, ClientError> {
        if !matches!(self.link, Link::Local { .. }) {
            return self.send_and_wait_copied(header, len, init, read);
        }
        self.wait_answer(header, len, init, read, true)
    }

    /// Sends over iceoryx2 and waits; `check`: error statuses become `Rejected` (else
    /// `read` sees every answer).
    fn wait_answer<R>(
        &mut self,
        header: RequestHeader,
        len: usize,
        init: impl FnOnce(&mut RequestHeader, &mut [MaybeUninit<f32>]) -> usize,
        read: impl FnOnce(&ResponseHeader, &[WirePairing]) -> R,
        check: bool,
    ) -> Result<R, ClientError> {
        let timeout = self.options.timeout;
        let spin = self.options.spin;
        let (pending, ports) = self.send(header, len, init)?;
        let sent = Instant::now();
        let deadline = sent + timeout;
        loop {
            // Read before asking whether the server is still there: it lets go of the
            // request right after answering.
            let gone = !pending.is_connected();
            match pending.receive() {
                Ok(Some(response)) => {
                    let header = response.user_header();
                    if check {
                        check_status(header)?;
                    }
                    return Ok(read(header, response.payload()));
                }
                Ok(None) if gone => {
                    drop(pending);
                    self.reconnect();
                    return Err(ClientError::Disconnected(self.map_name.clone()));
                }
                Ok(None) => {}
                Err(e) => return Err(ClientError::Transport(iox("receive a response")(e))),
            }
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            if spin {
                std::hint::spin_loop();
            } else if now - sent < POLL_BEFORE_SLEEP {
                // Yield, not spin: the server may share this core.
                std::thread::yield_now();
            } else {
                let wait = (deadline - now).min(PRESENCE_CHECK);
                let _ = ports.responses.timed_wait(|_| {}, wait);
            }
        }
        drop(pending);
        self.reconnect();
        Err(ClientError::Timeout {
            map_name: self.map_name.clone(),
            waited: timeout,
        })
    }

    /// As [`Self::send_and_wait`] over a link that takes a copy of the request: the
    /// remote link writes it into a frame, sends it as a Zenoh query and reads the
    /// answer frame back; the in-process link answers it on this thread.
    fn send_and_wait_copied<R>(
        &mut self,
        mut header: RequestHeader,
        len: usize,
        init: impl FnOnce(&mut RequestHeader, &mut [MaybeUninit<f32>]) -> usize,
        read: impl FnOnce(&ResponseHeader, &[WirePairing]) -> R,
    ) -> Result<R, ClientError> {
        header.client_node = self.client_node;
        header.request_id = self.next_request_id;
        self.next_request_id += 1;
        let mut payload = vec![MaybeUninit::new(0.0f32); len];
        let written = init(&mut header, &mut payload);
        assert_eq!(written, len, "a request's payload is written whole");
        let floats: Vec<f32> = payload
            .into_iter()
            // SAFETY: every element was initialized (zero-filled above, then written).
            .map(|v| unsafe { v.assume_init() })
            .collect();
        let (answer, pairings) = match &mut self.link {
            Link::Remote(link) => {
                let answer = link.call(&header, &floats, self.options.timeout)?;
                kfmap_protocol::remote::decode_answer(&answer).map_err(|e| {
                    crate::error::RemoteError::BadAnswer(format!("the gateway's answer: {e}"))
                })?
            }
            Link::InProcess(dispatch) => dispatch.answer(&header, &floats),
            Link::Local { .. } => unreachable!("iceoryx2 links send in place"),
        };
        check_status(&answer)?;
        Ok(read(&answer, &pairings))
    }

    /// Sends a request exactly as given (its version and fields; `client_node` and
    /// `request_id` are this connection's) with `payload`, and hands the answer to `read`
    /// in place, whatever its status. What a gateway does for its remote clients.
    pub fn forward<R>(
        &mut self,
        header: RequestHeader,
        payload: &[f32],
        read: impl FnOnce(&ResponseHeader, &[WirePairing]) -> R,
    ) -> Result<R, ClientError> {
        let init = |_: &mut RequestHeader, loan: &mut [MaybeUninit<f32>]| {
            for (slot, value) in loan.iter_mut().zip(payload) {
                *slot = MaybeUninit::new(*value);
            }
            payload.len().min(loan.len())
        };
        self.wait_answer(header, payload.len(), init, read, false)
    }

    /// Cleans up dead nodes (e.g. a killed server) and rebuilds the ports on next use.
    pub fn reconnect(&mut self) {
        self.served_covariance = None;
        if let Link::Local { node, ports } = &mut self.link {
            *ports = None;
            node.try_cleanup_dead_nodes();
        }
    }
}

fn check_status(header: &ResponseHeader) -> Result<(), ClientError> {
    match StatusCode::from_code(header.status) {
        StatusCode::Ok => Ok(()),
        status => Err(ClientError::Rejected {
            status,
            message: header.message(),
            detail: header.detail,
        }),
    }
}

/// Copies an answer out of shared memory.
fn copy_out(header: &ResponseHeader, pairings: &[WirePairing]) -> Response {
    Response {
        header: *header,
        pairings: pairings.to_vec(),
    }
}
