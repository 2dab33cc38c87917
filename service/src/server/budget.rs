//! What a request may cost, decided from its header before any work: its worst-case
//! answer against `max-answer-bytes`, its worst-case memory against the client's and
//! the server's budgets, and its process's share of the request slots. A request that
//! could never fit is refused as too large; one that fits but finds the budget held by
//! requests in flight is refused as busy. Reservations are released when dropped.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use kfmap_shared::protocol::{Rejection, RequestHeader, RequestKind, StatusCode};

use super::answer::{MAX_K, PAIRING_BYTES};
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

#[derive(Default)]
struct Held {
    by_client: HashMap<u128, u64>,
    by_process: HashMap<u32, u32>,
    total: u64,
}

/// Memory and request slots held by requests queued or in flight.
pub struct Budget {
    limits: BudgetLimits,
    held: Mutex<Held>,
}

/// A request's share of the budget, given back when dropped.
pub struct Reservation {
    budget: Arc<Budget>,
    client: u128,
    process: u32,
    memory: u64,
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

    /// Reserves `cost` for `client` of `process`, or says which budget is held.
    pub fn reserve(
        self: &Arc<Self>,
        client: u128,
        process: u32,
        cost: Cost,
    ) -> Result<Reservation, Rejection> {
        let mut held = self.lock();
        let l = &self.limits;
        let requests = held.by_process.get(&process).copied().unwrap_or(0);
        if requests >= l.requests_per_process {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "process {process} has {requests} requests queued or in flight, max-requests-per-process ({}, server.toml); wait for answers before sending more",
                    l.requests_per_process
                ),
            ));
        }
        let client_held = held.by_client.get(&client).copied().unwrap_or(0);
        if client_held + cost.memory_bytes > l.client_memory {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "this client's requests in flight hold {:.0} MiB; this one could need {:.0} MiB more, over client-memory-budget ({:.0} MiB, server.toml); retry when they are answered",
                    mib(client_held),
                    mib(cost.memory_bytes),
                    mib(l.client_memory)
                ),
            ));
        }
        if held.total + cost.memory_bytes > l.total_memory {
            return Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "requests in flight hold {:.0} MiB; this one could need {:.0} MiB more, over memory-budget ({:.0} MiB, server.toml); retry later",
                    mib(held.total),
                    mib(cost.memory_bytes),
                    mib(l.total_memory)
                ),
            ));
        }
        *held.by_client.entry(client).or_default() += cost.memory_bytes;
        *held.by_process.entry(process).or_default() += 1;
        held.total += cost.memory_bytes;
        Ok(Reservation {
            budget: self.clone(),
            client,
            process,
            memory: cost.memory_bytes,
        })
    }

    /// Bytes held by requests queued or in flight.
    #[cfg(test)]
    pub fn held_bytes(&self) -> u64 {
        self.lock().total
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Held> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        let mut held = self.budget.lock();
        held.total -= self.memory;
        if let Some(c) = held.by_client.get_mut(&self.client) {
            *c -= self.memory;
            if *c == 0 {
                held.by_client.remove(&self.client);
            }
        }
        if let Some(p) = held.by_process.get_mut(&self.process) {
            *p -= 1;
            if *p == 0 {
                held.by_process.remove(&self.process);
            }
        }
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
    fn reservations_are_bounded_per_client_process_and_server_and_given_back() {
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
        let a = budget.reserve(1, 10, cost(60)).unwrap();
        let busy = budget.reserve(1, 10, cost(60)).err().unwrap();
        assert!(
            busy.message.contains("client-memory-budget"),
            "{}",
            busy.message
        );
        let b = budget.reserve(2, 20, cost(80)).err().unwrap();
        assert!(b.message.contains("memory-budget"), "{}", b.message);
        let b = budget.reserve(2, 20, cost(50)).unwrap();
        assert_eq!(budget.held_bytes(), 110);
        drop(a);
        assert_eq!(budget.held_bytes(), 50);
        let _c = budget.reserve(1, 10, cost(0)).unwrap();
        let _d = budget.reserve(3, 10, cost(0)).unwrap();
        let _e = budget.reserve(4, 10, cost(0)).unwrap();
        let slots = budget.reserve(5, 10, cost(0)).err().unwrap();
        assert_eq!(slots.status, StatusCode::Busy);
        assert!(slots.message.contains("max-requests-per-process"));
        drop(b);
        assert_eq!(budget.held_bytes(), 0);
    }
}
