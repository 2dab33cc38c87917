//! A fair work queue: one FIFO per client; the next request comes from the client
//! that used the least of the workers' time lately (decayed with a 5 s half-life), so
//! a client flooding the server with large scans waits behind one that asks now and
//! then, and never starves it. It also hands out
//! the leader's turn: one idle worker at a time waits for requests and queues them
//! (leader/followers), so a request meets an awake worker with no thread hand-off.

use std::collections::{HashMap, VecDeque};
use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

/// Half-life of a client's recorded use of the workers.
const USAGE_HALF_LIFE: Duration = Duration::from_secs(5);

/// Workers' seconds a client used, decayed to `at`.
#[derive(Clone, Copy)]
struct Usage {
    seconds: f64,
    at: Instant,
}

impl Usage {
    fn now(self, now: Instant) -> f64 {
        let age = now.saturating_duration_since(self.at).as_secs_f64();
        self.seconds * 0.5f64.powf(age / USAGE_HALF_LIFE.as_secs_f64())
    }
}

struct State<T> {
    queues: HashMap<u128, VecDeque<T>>,
    /// Clients with queued work, in arrival order (ties in usage go to the first).
    turn: VecDeque<u128>,
    /// Recent use of the workers per client (forgotten once negligible).
    usage: HashMap<u128, Usage>,
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
                usage: HashMap::new(),
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

    /// Records that `client`'s request kept a worker busy for `spent`.
    pub fn charge(&self, client: u128, spent: Duration) {
        let now = Instant::now();
        let mut s = self.lock();
        let used = s.usage.get(&client).map_or(0.0, |u| u.now(now));
        s.usage.insert(
            client,
            Usage {
                seconds: used + spent.as_secs_f64(),
                at: now,
            },
        );
        // Forget clients whose use has decayed to nothing (dead or idle ones).
        s.usage.retain(|_, u| u.now(now) > 1e-6);
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
        let now = Instant::now();
        let used = |c: &u128| s.usage.get(c).map_or(0.0, |u| u.now(now));
        let (at, _) = s
            .turn
            .iter()
            .enumerate()
            .min_by(|(i, a), (j, b)| used(a).total_cmp(&used(b)).then(i.cmp(j)))?;
        let client = s.turn.remove(at).expect("found above");
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
    fn a_client_that_used_the_workers_less_goes_first() {
        let q = FairQueue::default();
        q.charge(1, Duration::from_millis(900));
        q.charge(2, Duration::from_millis(10));
        q.push(1, "heavy").unwrap();
        q.push(1, "heavy again").unwrap();
        q.push(2, "light").unwrap();
        q.push(3, "new").unwrap();
        let order: Vec<_> = (0..4).map(|_| q.next()).collect();
        let expected = ["new", "light", "heavy", "heavy again"].map(Turn::Work);
        assert_eq!(order, expected);
        // Use decays: by 5 s later half of it is left (the oracle: 0.5^(t / half-life)).
        let now = Instant::now();
        let u = Usage {
            seconds: 1.0,
            at: now,
        };
        assert!((u.now(now + USAGE_HALF_LIFE) - 0.5).abs() < 1e-12);
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
