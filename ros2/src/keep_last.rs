//! A bounded queue that keeps the newest: the readers' hand-over to the localizing loop.
//! A localizer behind its sensor wants the freshest cloud, so a full queue gives up its
//! oldest message (and counts it), never the one that just arrived.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Duration;

/// At most `depth` messages, oldest first; pushing onto a full queue evicts the oldest.
pub(crate) struct KeepLast<T> {
    queue: Mutex<VecDeque<T>>,
    arrived: Condvar,
    depth: usize,
    pushed: AtomicU64,
    evicted: AtomicU64,
}

impl<T> KeepLast<T> {
    /// An empty queue of `depth` (at least 1) messages.
    pub fn new(depth: usize) -> Self {
        Self {
            queue: Mutex::new(VecDeque::with_capacity(depth.max(1))),
            arrived: Condvar::new(),
            depth: depth.max(1),
            pushed: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> MutexGuard<'_, VecDeque<T>> {
        // A panicking holder cannot leave the deque half-changed: keep using it.
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Adds `message`; when the queue is full its oldest message goes (counted).
    pub fn push(&self, message: T) {
        self.pushed.fetch_add(1, Ordering::Relaxed);
        let mut queue = self.lock();
        if queue.len() == self.depth {
            queue.pop_front();
            self.evicted.fetch_add(1, Ordering::Relaxed);
        }
        queue.push_back(message);
        drop(queue);
        self.arrived.notify_one();
    }

    /// The oldest message kept, waiting at most `wait` for one.
    pub fn pop_timeout(&self, wait: Duration) -> Option<T> {
        let queue = self.lock();
        let (mut queue, _) = self
            .arrived
            .wait_timeout_while(queue, wait, |q| q.is_empty())
            .unwrap_or_else(|e| e.into_inner());
        queue.pop_front()
    }

    /// Every message kept, oldest first, leaving the queue empty.
    pub fn drain(&self) -> Vec<T> {
        self.lock().drain(..).collect()
    }

    /// Messages pushed so far.
    pub fn pushed(&self) -> u64 {
        self.pushed.load(Ordering::Relaxed)
    }

    /// Messages evicted by newer ones so far.
    pub fn evicted(&self) -> u64 {
        self.evicted.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_queue_keeps_the_newest_and_counts_the_rest() {
        let queue = KeepLast::new(3);
        for k in 0..8 {
            queue.push(k);
        }
        assert_eq!((queue.pushed(), queue.evicted()), (8, 5));
        assert_eq!(queue.pop_timeout(Duration::ZERO), Some(5));
        assert_eq!(queue.drain(), [6, 7]);
        assert_eq!(queue.pop_timeout(Duration::from_millis(1)), None);
    }

    #[test]
    fn a_waiting_loop_wakes_when_a_message_arrives() {
        let queue = std::sync::Arc::new(KeepLast::new(2));
        let pusher = {
            let queue = queue.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                queue.push("cloud");
            })
        };
        // Bounded: a lost wake-up fails after 10 s instead of hanging.
        assert_eq!(queue.pop_timeout(Duration::from_secs(10)), Some("cloud"));
        pusher.join().unwrap();
    }
}
