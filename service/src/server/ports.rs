//! Who sent a request: iceoryx2 stamps every request with the sending port's
//! `UniqueClientId`, which a client cannot forge; the service's registry maps that port
//! to its node and the node to its process. Sessions are keyed by that node, so a
//! `client_node` written into the header must agree with it. A process is served
//! through at most `max-clients-per-process` ports at once; its other ports are
//! refused until some of those close.

use std::collections::HashMap;
use std::sync::Mutex;

use iceoryx2::active_request::ActiveRequest;
use iceoryx2::identifiers::UniqueClientId;
use kfmap_protocol::transport::{Rpc, Transport, registered_clients};
use kfmap_protocol::{RequestHeader, ResponseHeader, WirePairing};

/// A request as the server port hands it over.
pub type Request = ActiveRequest<Transport, [f32], RequestHeader, [WirePairing], ResponseHeader>;

/// The node and process behind a client port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Owner {
    /// iceoryx2 node id.
    pub node: u128,
    /// Process id (0 when iceoryx2 cannot tell).
    pub process: u32,
}

/// What the registry says of a port that sent a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sender {
    /// A port the server serves.
    Served(Owner),
    /// A port of a process already served through `max-clients-per-process` others.
    OverProcessLimit(Owner),
    /// Not registered (closed since it sent, or never a client of this service).
    Unregistered,
}

#[derive(Debug, Clone, Copy)]
struct Port {
    owner: Owner,
    served: bool,
}

/// Client ports seen so far, by port id.
pub struct ClientPorts<'a> {
    rpc: &'a Rpc,
    per_process: usize,
    known: Mutex<HashMap<u128, Port>>,
}

impl<'a> ClientPorts<'a> {
    /// Reads the registry of `rpc`; serves at most `per_process` ports of a process.
    pub fn new(rpc: &'a Rpc, per_process: usize) -> Self {
        Self {
            rpc,
            per_process,
            known: Mutex::new(HashMap::new()),
        }
    }

    /// The most ports of one process served at once.
    pub fn per_process(&self) -> usize {
        self.per_process
    }

    /// Who sent from `port`. A port is looked up in the registry on first sight, and
    /// while it is refused (a port of its process may have closed since).
    pub fn sender(&self, port: UniqueClientId) -> Sender {
        let id = port.value();
        let mut known = self.lock();
        if let Some(p) = known.get(&id).filter(|p| p.served) {
            return Sender::Served(p.owner);
        }
        self.refresh(&mut known);
        match known.get(&id) {
            Some(p) if p.served => Sender::Served(p.owner),
            Some(p) => Sender::OverProcessLimit(p.owner),
            None => Sender::Unregistered,
        }
    }

    /// Re-reads the registry: ports gone from it are forgotten (freeing their
    /// process's share), new ones served while their process has room.
    fn refresh(&self, known: &mut HashMap<u128, Port>) {
        let clients = registered_clients(self.rpc);
        let mut next: HashMap<u128, Port> = HashMap::with_capacity(clients.len());
        let mut served: HashMap<u32, usize> = HashMap::new();
        // Ports served before keep their place; then the others in registry order.
        for c in &clients {
            if known.get(&c.port).is_some_and(|p| p.served) {
                *served.entry(c.process).or_default() += 1;
            }
        }
        for c in &clients {
            let owner = Owner {
                node: c.node,
                process: c.process,
            };
            let was_served = known.get(&c.port).is_some_and(|p| p.served);
            let count = served.entry(c.process).or_default();
            // iceoryx2 could not tell the process: nothing to count it against.
            let room = c.process == 0 || *count < self.per_process;
            let now_served = was_served || room;
            if now_served && !was_served {
                *count += 1;
            }
            next.insert(
                c.port,
                Port {
                    owner,
                    served: now_served,
                },
            );
        }
        *known = next;
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u128, Port>> {
        self.known.lock().unwrap_or_else(|e| e.into_inner())
    }
}
