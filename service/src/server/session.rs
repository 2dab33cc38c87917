//! Per-client state: each client's active-set cache and gravity pool are its own.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use kfmap_client::Tracker;
use kfmap_geometry::gravity::{GravityParams, LiveAnswer, LiveGravity};
use kfmap_map::map::{MergedSubmap, NearestMemos};
use kfmap_map::place::{Proposal, Scored};
use nalgebra::Vector3;

/// One client's state.
pub struct Session {
    /// Exact mode: the merged submap of this client's last active set.
    pub merged: Option<Arc<MergedSubmap>>,
    /// Approximate mode: what this client's last pairings found, point by point, so
    /// the next iteration of a registration recalls most of them.
    pub memos: NearestMemos,
    /// Gravity pool of this client's IMU windows, with its stamped poses (windows'
    /// and localized scans') to remove the platform's acceleration.
    pub gravity: LiveGravity,
    /// The places (and scores) of the last scan relocalized in phases over a tile set,
    /// for the phase that follows.
    pub last_places: Option<ProposedFor>,
    /// The tracker hosted for this client (`Track`), locked for a whole request while
    /// the session itself is locked per request of the tracker's.
    pub hosted: Arc<Mutex<HostedTracker>>,
    /// Map generation the cache belongs to.
    generation: u64,
}

impl Session {
    /// A fresh session on map `generation`.
    pub fn new(generation: u64) -> Self {
        Self {
            merged: None,
            memos: NearestMemos::default(),
            last_places: None,
            hosted: Arc::default(),
            gravity: LiveGravity::new(GravityParams::default())
                .expect("default gravity parameters are valid"),
            generation,
        }
    }

    /// Drops the merged-submap cache when the map was reloaded since it was built.
    pub fn follow(&mut self, generation: u64) {
        if generation != self.generation {
            self.merged = None;
            self.memos.clear();
            self.last_places = None;
            self.generation = generation;
        }
    }
}

/// A session's hosted tracker (`Track`, answered by `super::track`).
#[derive(Default)]
pub struct HostedTracker {
    /// The tracker, once a `Track` or `TrackImu` request made it.
    pub tracker: Option<Tracker>,
    /// True once a `Track` request started the tracker (one made for IMU samples that
    /// came first is replaced by the first scan's, keeping its gyro).
    pub started_by_scan: bool,
}

/// A search's places, their scores once asked, and the scan (and the map's up, when
/// the client gave its tilt) they belong to.
pub struct ProposedFor {
    /// The scan's points as sent.
    pub points: Vec<[f32; 3]>,
    /// The map's z in the sensor frame, when levelled by the client.
    pub map_up: Option<Vector3<f64>>,
    /// The search's places, best first.
    pub proposal: Proposal,
    /// The chosen places' scores, once a `FLAG_SCORE_CHOSEN` request asked.
    pub scored: Option<Scored>,
}

/// A session and when it was opened.
type Opened = (Instant, Arc<Mutex<Session>>);

/// Sessions by client node id.
#[derive(Default)]
pub struct Sessions {
    by_client: Mutex<HashMap<u128, Opened>>,
}

impl Sessions {
    /// The session of `client`, created on first use.
    pub fn get(&self, client: u128, generation: u64) -> Arc<Mutex<Session>> {
        let mut map = self.by_client.lock().unwrap_or_else(|e| e.into_inner());
        map.entry(client)
            .or_insert_with(|| {
                (
                    Instant::now(),
                    Arc::new(Mutex::new(Session::new(generation))),
                )
            })
            .1
            .clone()
    }

    /// Drops the sessions of clients not in `alive`, a listing of the live nodes taken
    /// at `listed`; a session opened since is kept (its client may have started after
    /// the listing). Returns how many were dropped.
    pub fn retain_alive(&self, alive: &std::collections::HashSet<u128>, listed: Instant) -> usize {
        let mut map = self.by_client.lock().unwrap_or_else(|e| e.into_inner());
        let before = map.len();
        map.retain(|client, (opened, _)| alive.contains(client) || *opened >= listed);
        before - map.len()
    }

    /// Each session's gravity pool, by client id (`None` for a session busy answering
    /// a request: a status report does not wait for it).
    pub fn gravity(&self) -> Vec<(u128, Option<LiveAnswer>)> {
        let sessions: Vec<(u128, Arc<Mutex<Session>>)> = {
            let map = self.by_client.lock().unwrap_or_else(|e| e.into_inner());
            map.iter().map(|(c, (_, s))| (*c, s.clone())).collect()
        };
        let mut out: Vec<_> = sessions
            .into_iter()
            .map(|(client, session)| {
                let pool = session.try_lock().ok().map(|s| s.gravity.answer());
                (client, pool)
            })
            .collect();
        out.sort_by_key(|(client, _)| *client);
        out
    }

    /// Open sessions.
    pub fn len(&self) -> usize {
        self.by_client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .len()
    }

    /// True without sessions.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The client node id carried in a request header.
pub fn client_of(words: [u64; 2]) -> u128 {
    (words[0] as u128) << 64 | words[1] as u128
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sessions of clients missing from a listing are dropped, unless opened after the
    /// listing was taken (their client may have started since); listed ones are kept.
    #[test]
    fn sessions_of_unlisted_clients_are_dropped_unless_opened_since_the_listing() {
        let sessions = Sessions::default();
        sessions.get(1, 0);
        sessions.get(2, 0);
        let listed = Instant::now();
        sessions.get(3, 0);
        let alive: std::collections::HashSet<u128> = [1].into();
        assert_eq!(sessions.retain_alive(&alive, listed), 1);
        let kept: Vec<u128> = sessions.gravity().iter().map(|(c, _)| *c).collect();
        assert_eq!(kept, [1, 3]);
        // The next listing, taken after client 3 opened its session, drops it.
        std::thread::sleep(std::time::Duration::from_millis(2));
        assert_eq!(sessions.retain_alive(&alive, Instant::now()), 1);
        assert_eq!(sessions.len(), 1);
    }
}
