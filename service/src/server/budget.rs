//! What a request may cost, decided from its header before any work: its worst-case
//! answer against `max-answer-bytes`, its worst-case memory against the client's and
//! the server's budgets, and its process's share of the request slots. A request that
//! could never fit is refused as too large; one that fits but finds the budget held by
//! requests in flight is refused as busy. Answers sent stay charged to their process
//! until the client has read them. Reservations are released when dropped.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use kfmap_protocol::{Rejection, RequestHeader, RequestKind, StatusCode};

use super::limits::{MAX_K, PAIRING_BYTES};
use crate::config::ServerSection;

/// Scratch a request needs per scan point besides its answer: the decoded and moved
/// copies, covariances, the registration's cloud (an upper bound, bytes).
const SCRATCH_PER_POINT: u64 = 512;

/// The configured limits and ceilings.
#[derive(Debug, Clone, Copy)]
pub struct BudgetLimits {
    /// `max-answer-bytes`.
    pub max_answer_bytes: u64,
    /// `max-radius-points`.
    pub max_radius_points: u32,
    /// `client-memory-budget`.
    pub client_memory: u64,
    /// `memory-budget`.
    pub total_memory: u64,
    /// `max-requests-per-process`.
    pub requests_per_process: u32,
}

impl BudgetLimits {
    /// The limits of `[server]`.
    pub fn of(server: &ServerSection) -> Self {
        Self {
            max_answer_bytes: server.max_answer_bytes,
            max_radius_points: server.max_radius_points,
            client_memory: server.client_memory_budget,
            total_memory: server.memory_budget,
            requests_per_process: server.max_requests_per_process,
        }
    }
}

/// A request's worst case.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cost {
    /// Bytes of pairings in its answer, at most.
    pub answer_bytes: u64,
    /// Memory it holds while answered: the answer, its shared-memory copy, scratch.
    pub memory_bytes: u64,
}

fn too_large(message: String) -> Rejection {
    Rejection::new(StatusCode::TooLarge, message)
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

/// The worst case of a request of `kind` with `points` scan points, or why it can
/// never be answered within `limits`.
pub fn worst_case(
    kind: Option<RequestKind>,
    header: &RequestHeader,
    points: u64,
    limits: &BudgetLimits,
) -> Result<Cost, Rejection> {
    let (per_point, what) = match kind {
        Some(RequestKind::Nearest) => {
            let k = header.k.clamp(1, MAX_K) as u64;
            (k, format!("k = {k}"))
        }
        Some(RequestKind::Radius) => (
            limits.max_radius_points as u64,
            format!("max-radius-points = {}", limits.max_radius_points),
        ),
        Some(RequestKind::Cov2Cov) => (1, "one per point".to_string()),
        _ => (0, String::new()),
    };
    let mut answer_bytes = points
        .saturating_mul(per_point)
        .saturating_mul(PAIRING_BYTES);
    if kind == Some(RequestKind::Radius) {
        // How many points a radius finds is known only by searching: the search stops
        // at max-answer-bytes, so that is its worst case.
        answer_bytes = answer_bytes.min(limits.max_answer_bytes);
    }
    if answer_bytes > limits.max_answer_bytes {
        return Err(too_large(format!(
            "the answer could hold {points} points x {what} pairings = {:.0} MiB, more than max-answer-bytes ({:.0} MiB, server.toml); send fewer points or ask for fewer neighbours",
            mib(answer_bytes),
            mib(limits.max_answer_bytes)
        )));
    }
    let memory_bytes = answer_bytes
        .saturating_mul(2)
        .saturating_add(points.saturating_mul(SCRATCH_PER_POINT));
    if memory_bytes > limits.client_memory {
        return Err(too_large(format!(
            "the request could need {:.0} MiB, more than client-memory-budget ({:.0} MiB, server.toml); send fewer points",
            mib(memory_bytes),
            mib(limits.client_memory)
        )));
    }
    Ok(Cost {
        answer_bytes,
        memory_bytes,
    })
}

/// What one process holds.
#[derive(Default, Clone, Copy)]
struct ProcessHeld {
    /// Requests queued or in flight.
    requests: u32,
    /// Their worst-case memory, plus its answers sent and not yet read.
    memory: u64,
}

#[derive(Default)]
struct Held {
    by_process: HashMap<u32, ProcessHeld>,
    total: u64,
}

/// Memory and request slots held by requests queued or in flight, and by answers sent
/// but not yet read.
pub struct Budget {
    limits: BudgetLimits,
    held: Mutex<Held>,
}

/// A request's share of the budget, given back when dropped: its worst case while it
/// is queued or answered ([`Budget::reserve`]), then its answer's bytes until the
/// client has read it ([`Reservation::settle`]).
pub struct Reservation {
    budget: Arc<Budget>,
    process: u32,
    memory: u64,
    /// Holds one of its process's request slots.
    slot: bool,
}

impl Budget {
    /// An empty budget.
    pub fn new(limits: BudgetLimits) -> Arc<Self> {
        Arc::new(Self {
            limits,
            held: Mutex::new(Held::default()),
        })
    }

    /// The limits.
    pub fn limits(&self) -> &BudgetLimits {
        &self.limits
    }

    /// Reserves `cost` for a request of `process` (all its client ports together), or
    /// says which budget is held.
    pub fn reserve(self: &Arc<Self>, process: u32, cost: Cost) -> Result<Reservation, Rejection> {
        let mut held = self.lock();
        let l = &self.limits;
        let mine = held.by_process.get(&process).copied().unwrap_or_default();
        if mine.requests >= l.requests_per_process {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "process {process} has {} requests queued or in flight, max-requests-per-process ({}, server.toml); wait for answers before sending more",
                    mine.requests, l.requests_per_process
                ),
            ));
        }
        if mine.memory + cost.memory_bytes > l.client_memory {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "process {process}'s requests in flight and unread answers hold {:.0} MiB; this one could need {:.0} MiB more, over client-memory-budget ({:.0} MiB, server.toml); read the answers, or retry when they are done",
                    mib(mine.memory),
                    mib(cost.memory_bytes),
                    mib(l.client_memory)
                ),
            ));
        }
        if held.total + cost.memory_bytes > l.total_memory {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "requests in flight and unread answers hold {:.0} MiB; this one could need {:.0} MiB more, over memory-budget ({:.0} MiB, server.toml); retry later",
                    mib(held.total),
                    mib(cost.memory_bytes),
                    mib(l.total_memory)
                ),
            ));
        }
        let entry = held.by_process.entry(process).or_default();
        entry.requests += 1;
        entry.memory += cost.memory_bytes;
        held.total += cost.memory_bytes;
        Ok(Reservation {
            budget: self.clone(),
            process,
            memory: cost.memory_bytes,
            slot: true,
        })
    }

    /// Bytes held by requests queued or in flight and answers unread.
    #[cfg(test)]
    pub fn held_bytes(&self) -> u64 {
        self.lock().total
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Held> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Gives back `memory` bytes and, with `slot`, a request slot of `process`.
    fn release(&self, process: u32, memory: u64, slot: bool) {
        let mut held = self.lock();
        held.total -= memory;
        if let Some(p) = held.by_process.get_mut(&process) {
            p.memory -= memory;
            p.requests -= u32::from(slot);
            if p.memory == 0 && p.requests == 0 {
                held.by_process.remove(&process);
            }
        }
    }
}

impl Reservation {
    /// The request is answered: its slot and its scratch go back, and what stays held
    /// is its answer's `answer_bytes` in shared memory, until the client reads it.
    pub fn settle(mut self, answer_bytes: u64) -> Self {
        let kept = answer_bytes.min(self.memory);
        self.budget.release(
            self.process,
            self.memory - kept,
            std::mem::take(&mut self.slot),
        );
        self.memory = kept;
        self
    }

    /// Bytes it holds.
    pub fn bytes(&self) -> u64 {
        self.memory
    }

    /// The process it is charged to.
    pub fn process(&self) -> u32 {
        self.process
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.budget.release(self.process, self.memory, self.slot);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> BudgetLimits {
        BudgetLimits::of(&ServerSection::default())
    }

    fn header(k: u32) -> RequestHeader {
        RequestHeader {
            k,
            ..Default::default()
        }
    }

    #[test]
    fn the_worst_case_is_the_product_of_points_and_pairings_per_point() {
        let l = limits();
        let nearest = worst_case(Some(RequestKind::Nearest), &header(20), 1000, &l).unwrap();
        assert_eq!(nearest.answer_bytes, 1000 * 20 * PAIRING_BYTES);
        assert_eq!(
            nearest.memory_bytes,
            2 * nearest.answer_bytes + 1000 * SCRATCH_PER_POINT
        );
        let radius = worst_case(Some(RequestKind::Radius), &header(0), 10, &l).unwrap();
        assert_eq!(radius.answer_bytes, 10 * 4096 * PAIRING_BYTES);
        let radius = worst_case(Some(RequestKind::Radius), &header(0), 1 << 20, &l).unwrap();
        assert_eq!(radius.answer_bytes, l.max_answer_bytes);
        let status = worst_case(Some(RequestKind::Status), &header(0), 0, &l).unwrap();
        assert_eq!(status.answer_bytes, 0);
        // k = 64 on a million points: 3.6 GB of pairings, refused by name.
        let e = worst_case(Some(RequestKind::Nearest), &header(64), 1 << 20, &l).unwrap_err();
        assert_eq!(e.status, StatusCode::TooLarge);
        assert!(e.message.contains("max-answer-bytes"), "{}", e.message);
        // A hostile k is clamped, never overflows.
        let huge = worst_case(Some(RequestKind::Nearest), &header(u32::MAX), u64::MAX, &l);
        assert_eq!(huge.unwrap_err().status, StatusCode::TooLarge);
    }

    #[test]
    fn reservations_are_bounded_per_process_and_server_and_given_back() {
        let l = BudgetLimits {
            client_memory: 100,
            total_memory: 130,
            requests_per_process: 3,
            ..limits()
        };
        let budget = Budget::new(l);
        let cost = |memory_bytes| Cost {
            answer_bytes: 0,
            memory_bytes,
        };
        let a = budget.reserve(10, cost(60)).unwrap();
        let busy = budget.reserve(10, cost(60)).err().unwrap();
        assert!(
            busy.message.contains("client-memory-budget"),
            "{}",
            busy.message
        );
        let b = budget.reserve(20, cost(80)).err().unwrap();
        assert!(b.message.contains("memory-budget"), "{}", b.message);
        let b = budget.reserve(20, cost(50)).unwrap();
        assert_eq!(budget.held_bytes(), 110);
        drop(a);
        assert_eq!(budget.held_bytes(), 50);
        let _c = budget.reserve(10, cost(0)).unwrap();
        let _d = budget.reserve(10, cost(0)).unwrap();
        let e = budget.reserve(10, cost(0)).unwrap();
        let slots = budget.reserve(10, cost(0)).err().unwrap();
        assert_eq!(slots.status, StatusCode::Busy);
        assert!(slots.message.contains("max-requests-per-process"));
        // An answered request gives its slot back; its answer's bytes stay held.
        let e = e.settle(0);
        let _f = budget.reserve(10, cost(0)).unwrap();
        drop(e);
        drop(b);
        assert_eq!(budget.held_bytes(), 0);
    }

    #[test]
    fn a_settled_reservation_keeps_only_its_answer_until_dropped() {
        let budget = Budget::new(BudgetLimits {
            client_memory: 100,
            total_memory: 100,
            ..limits()
        });
        let cost = Cost {
            answer_bytes: 30,
            memory_bytes: 90,
        };
        let answered = budget.reserve(1, cost).unwrap().settle(30);
        assert_eq!(budget.held_bytes(), 30);
        assert_eq!(answered.bytes(), 30);
        // The unread answer still counts: a second request of 90 does not fit.
        let busy = budget.reserve(1, cost).err().unwrap();
        assert!(busy.message.contains("unread answers"), "{}", busy.message);
        drop(answered);
        assert_eq!(budget.held_bytes(), 0);
        budget.reserve(1, cost).unwrap();
    }
}
