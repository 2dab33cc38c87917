//! A fair work queue: one FIFO per client, served round-robin, so one client's burst
//! of large scans never starves another client's small requests.

use std::collections::{HashMap, VecDeque};
use std::sync::{Condvar, Mutex};

struct State<T> {
    queues: HashMap<u128, VecDeque<T>>,
    /// Clients with queued work, in serving order.
    turn: VecDeque<u128>,
    closed: bool,
}

/// Round-robin queue across clients.
pub struct FairQueue<T> {
    state: Mutex<State<T>>,
    ready: Condvar,
}

impl<T> Default for FairQueue<T> {
    fn default() -> Self {
        Self {
            state: Mutex::new(State {
                queues: HashMap::new(),
                turn: VecDeque::new(),
                closed: false,
            }),
            ready: Condvar::new(),
        }
    }
}

impl<T> FairQueue<T> {
    /// Queues `item` for `client`.
    pub fn push(&self, client: u128, item: T) {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let queue = s.queues.entry(client).or_default();
        queue.push_back(item);
        if queue.len() == 1 {
            s.turn.push_back(client);
        }
        drop(s);
        self.ready.notify_one();
    }

    /// The next item, the clients taking turns; blocks until one is queued; `None` once
    /// closed and empty.
    pub fn pop(&self) -> Option<T> {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(client) = s.turn.pop_front() {
                let queue = s
                    .queues
                    .get_mut(&client)
                    .expect("a client in turn has a queue");
                let item = queue.pop_front().expect("a client in turn has work");
                if queue.is_empty() {
                    s.queues.remove(&client);
                } else {
                    s.turn.push_back(client);
                }
                return Some(item);
            }
            if s.closed {
                return None;
            }
            s = self.ready.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Stops the queue: returns what was never started; `pop` then returns `None`.
    pub fn close(&self) -> Vec<T> {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.closed = true;
        s.turn.clear();
        let left = s.queues.drain().flat_map(|(_, q)| q).collect();
        drop(s);
        self.ready.notify_all();
        left
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clients_take_turns() {
        let q = FairQueue::default();
        for i in 0..5 {
            q.push(1, ("a", i));
        }
        q.push(2, ("b", 0));
        q.push(3, ("c", 0));
        let order: Vec<_> = (0..4).map(|_| q.pop().unwrap()).collect();
        assert_eq!(order, [("a", 0), ("b", 0), ("c", 0), ("a", 1)]);
        let left = q.close();
        assert_eq!(left.len(), 3);
        assert_eq!(q.pop(), None);
    }
}
