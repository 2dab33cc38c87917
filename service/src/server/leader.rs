//! Leader/followers: every worker runs the same loop. The one holding the leader's
//! turn waits for requests and queues them, then answers the next one itself, so a
//! request meets a thread already awake (a thread hand-off costs tens of
//! microseconds on virtual machines); a follower takes the turn meanwhile.

use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::server::Server;
use kfmap_protocol::transport::Transport;
use kfmap_protocol::{RequestHeader, RequestKind, ResponseHeader, WirePairing};

use super::queue::{FairQueue, Turn};
use super::workers::{Job, WorkerContext};

/// After an echo the leader keeps polling this long before it sleeps again: a client
/// sending back to back is then served without a wake-up.
const POLL_AFTER_ECHO: Duration = Duration::from_micros(50);
/// The leader looks at the queue's state at least this often while waiting.
const LEADER_WAKE: Duration = Duration::from_millis(250);

/// The server's request port.
pub type RequestServer = Server<Transport, [f32], RequestHeader, [WirePairing], ResponseHeader>;

/// What one look at the request port did.
#[derive(Debug, Default)]
pub struct Drained {
    /// Requests queued for the workers.
    pub queued: usize,
    /// Echoes answered at once.
    pub echoed: usize,
}

/// Where requests come from.
pub struct Requests<'a> {
    /// The request-response port.
    pub server: &'a RequestServer,
    /// Woken by clients after each request (and by the server at shutdown).
    pub listener: &'a Listener<Transport>,
    /// Poll instead of sleeping.
    pub spin: bool,
}

impl Requests<'_> {
    /// Takes every received request: echoes are answered at once, the rest queued;
    /// once the queue is closed they are refused.
    pub fn drain(&self, context: &WorkerContext, queue: &FairQueue<Job>) -> Drained {
        let mut drained = Drained::default();
        // A client sends its next request only after letting go of its last one: that
        // answer's memory goes back to the budget before the new one is admitted.
        context.unread.sweep();
        while let Ok(Some(request)) = self.server.receive() {
            let header = request.user_header();
            if header.kind == RequestKind::Echo as u32 {
                // No work to schedule: answered here, it measures the transport alone.
                context.handle(Job::new(request));
                drained.echoed += 1;
                continue;
            }
            // Refused at once when it is not the sender's session or over a budget.
            let Some(job) = context.admit(request) else {
                continue;
            };
            // Processes share the workers, however many clients each opened.
            match queue.push(job.process, job) {
                Ok(()) => drained.queued += 1,
                // Closed: the queue counts it as turned away.
                Err(job) => context.refuse_shutting_down(job),
            }
        }
        drained
    }

    /// The leader's turn: returns once work is queued or the queue closed.
    fn lead(&self, context: &WorkerContext, queue: &FairQueue<Job>) {
        let mut last_echo: Option<Instant> = None;
        while !queue.is_closed() {
            let drained = self.drain(context, queue);
            if drained.queued > 0 {
                return;
            }
            if drained.echoed > 0 {
                last_echo = Some(Instant::now());
            }
            if self.spin {
                std::hint::spin_loop();
            } else if last_echo.is_some_and(|t| t.elapsed() < POLL_AFTER_ECHO) {
                // Yield, not spin: the client may share this core.
                std::thread::yield_now();
            } else {
                last_echo = None;
                // A notification that came after the drain returns at once.
                if self.listener.timed_wait(|_| {}, LEADER_WAKE).is_err() {
                    // Interrupted by a signal, or worse: never a busy loop.
                    std::thread::sleep(Duration::from_millis(1));
                }
            }
        }
    }
}

/// One worker's loop until the queue closes.
pub fn work(context: &WorkerContext, queue: &FairQueue<Job>, requests: &Requests) {
    loop {
        match queue.next() {
            Turn::Work(job) => {
                let (process, started) = (job.process, Instant::now());
                context.handle(job);
                queue.charge(process, started.elapsed());
            }
            Turn::Lead => {
                requests.lead(context, queue);
                queue.resign();
            }
            Turn::Closed => return,
        }
    }
}
