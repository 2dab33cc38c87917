//! Answers sent and not yet read. iceoryx2 delivers an answer into the server's own
//! shared memory, and a client that never reads it keeps that memory until it does or
//! exits; nothing can take a delivered answer back. So a large answer stays charged to
//! its process's budget until the client lets go of its request (it has read the
//! answer, given up, or died): a client that never reads is refused more work once its
//! unread answers fill `client-memory-budget`, and the server's shared memory stays
//! within `memory-budget`. From shutdown on every answer is held, so the server does
//! not exit (removing that memory) before its clients have read their last answers.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use kfmap_protocol::log_limit::warn_limited;

use super::budget::Reservation;
use super::ports::Request;

/// Answers smaller than this are let go at once (at most one per client port is
/// unread at a time: one request in flight per port).
const TRACKED_BYTES: u64 = 1 << 20;
/// An answer unread this long is reported (once).
const REPORT_AFTER: Duration = Duration::from_secs(30);

struct Unread {
    request: Request,
    /// The budget it is charged to; `None` for an answer held only for shutdown.
    reservation: Option<Reservation>,
    sent: Instant,
    reported: bool,
}

/// Large answers whose clients still hold their requests.
#[derive(Default)]
pub struct UnreadAnswers {
    held: Mutex<Vec<Unread>>,
    /// `held.len()`, read without the lock: the leader sweeps on every look at the
    /// request port, and almost always there is nothing to sweep.
    count: AtomicUsize,
    /// Set at shutdown: every answer is held until read.
    closing: AtomicBool,
}

impl UnreadAnswers {
    /// `request` was answered with `answer_bytes`: its reservation keeps those bytes
    /// until the client lets go of the request (after shutdown began, any answer is
    /// kept until then).
    pub fn hold(&self, request: Request, reservation: Option<Reservation>, answer_bytes: u64) {
        let charged = reservation.is_some() && answer_bytes >= TRACKED_BYTES;
        if !charged && !self.closing.load(Ordering::Relaxed) {
            return;
        }
        let unread = Unread {
            request,
            reservation: reservation.map(|r| r.settle(answer_bytes)),
            sent: Instant::now(),
            reported: false,
        };
        let mut held = self.lock();
        held.push(unread);
        self.count.store(held.len(), Ordering::Relaxed);
    }

    /// Lets go of answers their clients are done with (the budget gets their bytes
    /// back) and reports answers unread for long.
    pub fn sweep(&self) {
        if self.count.load(Ordering::Relaxed) == 0 {
            return;
        }
        let mut held = self.lock();
        held.retain(|u| u.request.is_connected());
        self.count.store(held.len(), Ordering::Relaxed);
        for u in held.iter_mut() {
            let Some(reservation) = u.reservation.as_ref() else {
                continue;
            };
            if !u.reported && u.sent.elapsed() >= REPORT_AFTER {
                u.reported = true;
                warn_limited(
                    "answers left unread",
                    &format!(
                        "process {} has left an answer of {:.0} MiB unread for {} s; it stays charged to the process's client-memory-budget until the client reads it, drops the request or exits",
                        reservation.process(),
                        reservation.bytes() as f64 / (1u64 << 20) as f64,
                        REPORT_AFTER.as_secs()
                    ),
                );
            }
        }
    }

    /// Shutdown began: from now on every answer is held until its client reads it.
    pub fn close(&self) {
        self.closing.store(true, Ordering::Relaxed);
    }

    /// Waits until every held answer is read (or its client gone), at most `limit`;
    /// returns how many are still unread.
    pub fn wait_until_read(&self, limit: Duration) -> usize {
        let deadline = Instant::now() + limit;
        loop {
            self.sweep();
            let left = self.count.load(Ordering::Relaxed);
            if left == 0 || Instant::now() >= deadline {
                return left;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Unread>> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }
}
