//! A fair work queue: one FIFO per client, served round-robin, so one client's burst
//! of large scans never starves another client's small requests. It also hands out
//! the leader's turn: one idle worker at a time waits for requests and queues them
//! (leader/followers), so a request meets an awake worker with no thread hand-off.

use std::collections::{HashMap, VecDeque};
use std::sync::{Condvar, Mutex};

struct State<T> {
    queues: HashMap<u128, VecDeque<T>>,
    /// Clients with queued work, in serving order.
    turn: VecDeque<u128>,
    /// A worker is waiting for requests.
    led: bool,
    closed: bool,
    /// Items handed back by `push` after closing.
    turned_away: usize,
}

/// What a worker does next.
#[derive(Debug, PartialEq)]
pub enum Turn<T> {
    /// Answer this item.
    Work(T),
    /// Wait for requests and queue them, then [`FairQueue::resign`].
    Lead,
    /// The queue is closed: stop.
    Closed,
}

/// Round-robin queue across clients.
pub struct FairQueue<T> {
    state: Mutex<State<T>>,
    changed: Condvar,
}

impl<T> Default for FairQueue<T> {
    fn default() -> Self {
        Self {
            state: Mutex::new(State {
                queues: HashMap::new(),
                turn: VecDeque::new(),
                led: false,
                closed: false,
                turned_away: 0,
            }),
            changed: Condvar::new(),
        }
    }
}

impl<T> FairQueue<T> {
    /// Queues `item` for `client`; hands it back once the queue is closed.
    pub fn push(&self, client: u128, item: T) -> Result<(), T> {
        let mut s = self.lock();
        if s.closed {
            s.turned_away += 1;
            return Err(item);
        }
        let queue = s.queues.entry(client).or_default();
        queue.push_back(item);
        if queue.len() == 1 {
            s.turn.push_back(client);
        }
        drop(s);
        self.changed.notify_one();
        Ok(())
    }

    /// The next item, the clients taking turns; else the leader's turn when nobody
    /// leads; else blocks until one of them is free.
    pub fn next(&self) -> Turn<T> {
        let mut s = self.lock();
        loop {
            if s.closed {
                return Turn::Closed;
            }
            if let Some(item) = Self::pop(&mut s) {
                return Turn::Work(item);
            }
            if !s.led {
                s.led = true;
                return Turn::Lead;
            }
            s = self.changed.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Ends the leader's turn (another worker may take it).
    pub fn resign(&self) {
        self.lock().led = false;
        self.changed.notify_one();
    }

    /// Items `push` handed back since closing.
    pub fn turned_away(&self) -> usize {
        self.lock().turned_away
    }

    /// True once closed.
    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    /// Stops the queue: returns what was never started; `next` then returns `Closed`
    /// and `push` hands items back.
    pub fn close(&self) -> Vec<T> {
        let mut s = self.lock();
        s.closed = true;
        s.turn.clear();
        let left = s.queues.drain().flat_map(|(_, q)| q).collect();
        drop(s);
        self.changed.notify_all();
        left
    }

    fn pop(s: &mut State<T>) -> Option<T> {
        let client = s.turn.pop_front()?;
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
        Some(item)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clients_take_turns() {
        let q = FairQueue::default();
        for i in 0..5 {
            q.push(1, ("a", i)).unwrap();
        }
        q.push(2, ("b", 0)).unwrap();
        q.push(3, ("c", 0)).unwrap();
        let order: Vec<_> = (0..4).map(|_| q.next()).collect();
        let expected = [("a", 0), ("b", 0), ("c", 0), ("a", 1)].map(Turn::Work);
        assert_eq!(order, expected);
        let left = q.close();
        assert_eq!(left.len(), 3);
        assert_eq!(q.next(), Turn::Closed);
        assert_eq!(q.push(1, ("a", 9)), Err(("a", 9)));
        assert_eq!(q.turned_away(), 1);
    }

    #[test]
    fn one_worker_leads_at_a_time() {
        let q = FairQueue::<u32>::default();
        assert_eq!(q.next(), Turn::Lead);
        // A second idle worker waits until the leader resigns.
        std::thread::scope(|scope| {
            let follower = scope.spawn(|| q.next());
            std::thread::sleep(std::time::Duration::from_millis(20));
            assert!(!follower.is_finished(), "a second leader was made");
            q.resign();
            assert_eq!(follower.join().unwrap(), Turn::Lead);
        });
        // Queued work comes before leading.
        q.push(7, 1).unwrap();
        assert_eq!(q.next(), Turn::Work(1));
    }
}
