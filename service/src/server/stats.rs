//! Request counters and latency percentiles per request kind.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};

use kfmap_protocol::KIND_SLOTS;

use kfmap_geometry::percentile::percentile;

/// Latencies kept per kind for the percentiles (the most recent ones).
pub const WINDOW: usize = 4096;

#[derive(Default, Clone)]
struct Kind {
    count: u64,
    latencies_us: Vec<f32>,
    next: usize,
}

/// Counters of a running server.
#[derive(Default)]
pub struct Stats {
    kinds: Mutex<[Kind; KIND_SLOTS]>,
    in_flight: AtomicU32,
}

/// A snapshot: requests answered, median and 99th percentile latency (microseconds).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct KindFigures {
    /// Requests answered.
    pub count: u64,
    /// Median latency, us.
    pub p50_us: f32,
    /// 99th percentile latency, us.
    pub p99_us: f32,
}

impl Stats {
    /// A worker took a request.
    pub fn started(&self) {
        self.in_flight.fetch_add(1, Ordering::Relaxed);
    }

    /// A worker sent its answer.
    pub fn finished(&self) {
        self.in_flight.fetch_sub(1, Ordering::Relaxed);
    }

    /// Requests taken by workers and not yet answered.
    pub fn in_flight(&self) -> u32 {
        self.in_flight.load(Ordering::Relaxed)
    }

    /// Records one answered request of kind code `kind` that took `latency_us`.
    pub fn record(&self, kind: u32, latency_us: f32) {
        let slot = (kind as usize).min(KIND_SLOTS - 1);
        let mut kinds = self.kinds.lock().unwrap_or_else(|e| e.into_inner());
        let k = &mut kinds[slot];
        k.count += 1;
        if k.latencies_us.len() < WINDOW {
            k.latencies_us.push(latency_us);
        } else {
            k.latencies_us[k.next] = latency_us;
            k.next = (k.next + 1) % WINDOW;
        }
    }

    /// Figures per kind code.
    pub fn figures(&self) -> [KindFigures; KIND_SLOTS] {
        let kinds = self.kinds.lock().unwrap_or_else(|e| e.into_inner()).clone();
        kinds.map(|k| {
            let mut sorted = k.latencies_us;
            sorted.sort_by(f32::total_cmp);
            KindFigures {
                count: k.count,
                p50_us: percentile(&sorted, 0.50),
                p99_us: percentile(&sorted, 0.99),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition itself is tested in `kfmap_geometry::percentile`; here, that the
    /// figures use it: 10 samples, so the p99 is their maximum.
    #[test]
    fn percentiles_by_nearest_rank() {
        let s = Stats::default();
        for x in 1..=10 {
            s.record(3, x as f32);
        }
        let f = s.figures()[3];
        assert_eq!((f.count, f.p50_us, f.p99_us), (10, 5.0, 10.0));
    }
}
