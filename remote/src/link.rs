//! The Zenoh link: requests as Zenoh queries to a `kfmap gateway` on another host,
//! which answers them through its local map server (docs/DESIGN.md#notes-remote).
//! Frames and keys are `kfmap_protocol::remote`'s; this module only moves them.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use kfmap_map::tiles::{Route, TileGeometry, TileIndex, TileRouter};
use kfmap_protocol::remote::{
    RemoteFailure, WHOLE_MAP_TILE, alive_pattern, check_key_chunk, encode_request,
    rpc_all_tiles_key, rpc_key, tile_index_key, tile_of_alive_key, tile_of_rpc_key,
};
use kfmap_protocol::{
    FLAG_FINISH_CHOSEN, FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN, RequestHeader, RequestKind,
};
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::SampleKind;

use kfmap_client::{ClientError, RemoteError, RemoteLink};

use crate::options::{RemoteOptions, zenoh_config};
use crate::tiled::Choice;

/// How a pending answer is watched: the token check runs this often, so a client learns
/// of a dead server within about this long after its gateway withdraws the token.
const WATCH_SLICE: Duration = Duration::from_millis(2);
/// How long a query that ended unanswered waits for the token to go (a dead gateway)
/// before it is read as a refusal.
const GONE_WAIT: Duration = Duration::from_millis(100);
/// Longest wait for the gateway's liveliness token when connecting.
const CONNECT_WAIT: Duration = Duration::from_secs(2);

/// An open remote link to a map: one tile (a map served whole, or the tile asked for),
/// or every tile of a tile set, each request routed by its pose guess.
pub(crate) struct ZenohLink {
    session: zenoh::Session,
    map_name: String,
    client_id: String,
    /// The tiles requests may go to (keys' tile chunks).
    tiles: Vec<String>,
    /// The tiles whose liveliness token is present (their servers answer).
    alive: Arc<Mutex<HashSet<String>>>,
    /// A tile set's index and the router over it (`None`: one tile).
    routing: Option<(TileIndex, TileRouter)>,
    _token_watch: zenoh::pubsub::Subscriber<()>,
}

impl ZenohLink {
    /// Opens a Zenoh session to the gateways and waits for the map's tokens; learns the
    /// tile set (from a gateway's index) unless `remote.tile` names one tile.
    pub(crate) fn open(map_name: &str, remote: &RemoteOptions) -> Result<Self, ClientError> {
        let invalid = |e: kfmap_protocol::remote::FrameError| ClientError::Invalid(e.to_string());
        check_key_chunk("map name", map_name).map_err(invalid)?;
        if let Some(tile) = &remote.tile {
            check_key_chunk("tile", tile).map_err(invalid)?;
        }
        let client_id = match &remote.client_id {
            Some(id) => {
                check_key_chunk("client id", id).map_err(invalid)?;
                id.clone()
            }
            None => random_client_id(),
        };
        if remote.endpoints.is_empty() && remote.zenoh_config.is_none() {
            return Err(ClientError::Invalid(
                "a remote client needs a gateway endpoint, e.g. tcp/10.0.0.5:7447".into(),
            ));
        }
        let config = zenoh_config(remote.zenoh_config.as_deref(), &[], &remote.endpoints)?;
        let session = zenoh::open(config).wait().map_err(|e| {
            ClientError::from(RemoteError::Unreachable {
                endpoints: remote.endpoints.join(", "),
                reason: e.to_string(),
            })
        })?;
        let alive: Arc<Mutex<HashSet<String>>> = Arc::default();
        let pattern = alive_pattern(map_name);
        let (flags, name) = (alive.clone(), map_name.to_string());
        let token_watch = session
            .liveliness()
            .declare_subscriber(&pattern)
            .history(true)
            .callback(move |sample| {
                if let Some(tile) = tile_of_alive_key(&name, sample.key_expr().as_str()) {
                    let mut alive = flags.lock().expect("the token set");
                    if sample.kind() == SampleKind::Put {
                        alive.insert(tile.to_string());
                    } else {
                        alive.remove(tile);
                    }
                }
            })
            .wait()
            .map_err(|e| zenoh_failed(format!("watch {pattern}"), e))?;
        // The tokens alive now (the subscriber above keeps the set current after), asked
        // again until one shows or CONNECT_WAIT is spent: the session may not have
        // reached a gateway yet when the first ask goes out (a loaded host).
        let deadline = Instant::now() + CONNECT_WAIT;
        let present: Vec<String> = loop {
            let left = deadline
                .saturating_duration_since(Instant::now())
                .max(Duration::from_millis(50));
            let asked: Vec<String> = session
                .liveliness()
                .get(&pattern)
                .timeout(left)
                .wait()
                .map_err(|e| zenoh_failed(format!("look up {pattern}"), e))?
                .iter()
                .filter_map(|reply| {
                    let sample = reply.into_result().ok()?;
                    tile_of_alive_key(map_name, sample.key_expr().as_str()).map(str::to_string)
                })
                .collect();
            let mut known = alive.lock().expect("the token set");
            known.extend(asked);
            if !known.is_empty() || Instant::now() >= deadline {
                let mut present: Vec<String> = known.iter().cloned().collect();
                present.sort();
                break present;
            }
            drop(known);
            std::thread::sleep(Duration::from_millis(50));
        };
        let no_server = || {
            ClientError::NoServer(format!(
                "{map_name} (remote, at {})",
                remote.endpoints.join(", ")
            ))
        };
        let (tiles, routing) = match &remote.tile {
            Some(tile) => (vec![tile.clone()], None),
            None if present.is_empty() => return Err(no_server()),
            None if present.iter().all(|t| t == WHOLE_MAP_TILE) => {
                (vec![WHOLE_MAP_TILE.to_string()], None)
            }
            None => {
                let index = fetch_index(&session, map_name)?;
                let router = TileRouter::new(&index, TileRouter::default_hysteresis(&index));
                let tiles = index.tiles.iter().map(|t| t.id.clone()).collect();
                (tiles, Some((index, router)))
            }
        };
        let link = Self {
            session,
            map_name: map_name.to_string(),
            client_id,
            tiles,
            alive,
            routing,
            _token_watch: token_watch,
        };
        if !(0..link.tiles.len()).any(|i| link.tile_alive(i)) {
            return Err(no_server());
        }
        Ok(link)
    }

    /// True while a gateway announces a live server for tile `i`.
    fn tile_alive(&self, i: usize) -> bool {
        self.alive
            .lock()
            .expect("the token set")
            .contains(&self.tiles[i])
    }

    /// The tile set's core squares, when the map is served in tiles whose searches
    /// overlap: a cut by an older kfmap, whose index gives no search regions, so each
    /// tile searches its whole region and neighbours propose the same places. A cut
    /// with regions splits the search among the tiles (`SearchShare`).
    fn overlapping_cores(&self) -> Option<TileGeometry> {
        self.tile_index()
            .filter(|index| index.tiles.iter().all(|t| t.search_min.is_none()))
            .map(TileIndex::geometry)
    }

    /// The tile a request goes to.
    fn route(&mut self, header: &RequestHeader) -> Result<usize, ClientError> {
        let up: Vec<bool> = (0..self.tiles.len()).map(|i| self.tile_alive(i)).collect();
        let Some((_, router)) = &mut self.routing else {
            return Ok(0);
        };
        match router.route(header.pose[0], header.pose[1], |i| up[i]) {
            Route::Tile(i) => Ok(i),
            Route::Down(i) => Err(ClientError::NoServer(self.describe(i))),
            Route::NoneUp => Err(self.no_tile_answers()),
        }
    }

    /// The error when no tile of the set has a live server.
    fn no_tile_answers(&self) -> ClientError {
        ClientError::NoServer(format!(
            "{} (remote: no tile's server answers)",
            self.map_name
        ))
    }

    /// Sends a request frame to tile `i` and waits for the answer frame.
    fn call_tile(
        &self,
        i: usize,
        frame: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<u8>, ClientError> {
        let mut answers = self.ask_tiles(vec![(i, frame)], timeout)?;
        Ok(answers.pop().expect("one answer per request").1)
    }

    /// Relocalizes over every tile as one search over the merged map would, in three
    /// phases (`crate::tiled`): every tile's places at once (`QueryTarget::All`); the
    /// best of them all scored by the tiles holding them; the best score finished by
    /// its tile.
    fn call_every_tile(
        &self,
        header: &RequestHeader,
        payload: &[f32],
        timeout: Duration,
    ) -> Result<Vec<u8>, ClientError> {
        let started = Instant::now();
        let left = || timeout.saturating_sub(started.elapsed());
        let phase = |flag: u32, ranks: u64| {
            let mut h = *header;
            h.flags |= flag;
            h.keyframe_or_scan_id = ranks;
            encode_request(&h, payload)
        };
        let places = self.ask_every_tile(phase(FLAG_PLACES_ONLY, 0), timeout)?;
        let placed = started.elapsed();
        // The servers' ranking as their gateway published it (defaults from a gateway
        // that predates it).
        let ranking = self
            .tile_index()
            .and_then(|index| index.ranking)
            .unwrap_or_default();
        let (chosen, order, searched_us) = match crate::tiled::choose_places(
            &places,
            self.overlapping_cores().as_ref(),
            &ranking,
        )? {
            Choice::Answer(frame) => return Ok(frame),
            Choice::Score {
                chosen,
                order,
                searched_us,
            } => (chosen, order, searched_us),
        };
        let requests = chosen
            .into_iter()
            .map(|(at, ranks)| {
                let tile = self.tile_number(&places[at].0)?;
                Ok((tile, phase(FLAG_SCORE_CHOSEN, ranks)))
            })
            .collect::<Result<Vec<_>, ClientError>>()?;
        let order: Vec<(String, usize)> = order
            .into_iter()
            .map(|(at, rank)| (places[at].0.clone(), rank))
            .collect();
        let scored = self.ask_tiles(requests, left())?;
        let scored_at = started.elapsed();
        let ranked = match crate::tiled::best_scored(&order, &scored)? {
            Ok(ranked) => ranked,
            Err(refusal) => return Ok(refusal),
        };
        let Some((tile, rank)) = &ranked.best else {
            return Ok(crate::tiled::nothing_settled(&ranked, searched_us));
        };
        let request = (
            self.tile_number(tile)?,
            phase(FLAG_FINISH_CHOSEN, 1 << rank),
        );
        let finished = self.ask_tiles(vec![request], left())?;
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        tracing::debug!(
            "relocalize over {} tiles: places {:.1} ms, scores {:.1} ms ({} tiles), finish {:.1} ms",
            places.len(),
            ms(placed),
            ms(scored_at - placed),
            scored.len(),
            ms(started.elapsed() - scored_at)
        );
        crate::tiled::finish(&finished[0].1, &ranked, searched_us, &ranking)
    }

    /// The index of tile `id` in this link's tiles.
    fn tile_number(&self, id: &str) -> Result<usize, ClientError> {
        self.tiles.iter().position(|t| t == id).ok_or_else(|| {
            RemoteError::BadAnswer(format!(
                "an answer came from tile {id:?}, which is not in {}'s tile index",
                self.map_name
            ))
            .into()
        })
    }

    /// Sends request frames to tiles (each its own) at once and waits for every answer
    /// frame (tile id, frame).
    fn ask_tiles(
        &self,
        requests: Vec<(usize, Vec<u8>)>,
        timeout: Duration,
    ) -> Result<Vec<(String, Vec<u8>)>, ClientError> {
        let mut pending = Vec::with_capacity(requests.len());
        for (i, frame) in requests {
            if !self.tile_alive(i) {
                return Err(ClientError::NoServer(self.describe(i)));
            }
            let key = rpc_key(&self.map_name, &self.tiles[i], &self.client_id);
            let replies = self
                .session
                .get(&key)
                .payload(frame)
                .target(QueryTarget::BestMatching)
                .consolidation(ConsolidationMode::None)
                .timeout(timeout)
                .wait()
                .map_err(|e| zenoh_failed(format!("send to {key}"), e))?;
            pending.push((i, key, replies));
        }
        let deadline = Instant::now() + timeout;
        let mut answers = Vec::with_capacity(pending.len());
        while let Some((i, key, replies)) = pending.first() {
            match replies.recv_timeout(WATCH_SLICE) {
                Ok(Some(reply)) => {
                    answers.push((self.tiles[*i].clone(), self.answer(*i, reply)?));
                    pending.remove(0);
                    continue;
                }
                Err(_) => return Err(self.ended_unanswered(*i, key)),
                Ok(None) => {}
            }
            if let Some((i, _, _)) = pending.iter().find(|(i, _, _)| !self.tile_alive(*i)) {
                return Err(ClientError::Disconnected(self.describe(*i)));
            }
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    map_name: self.describe(*i),
                    waited: timeout,
                });
            }
        }
        Ok(answers)
    }

    /// Sends one request frame to every tile at once (`QueryTarget::All`) and waits for
    /// the answers (tile id, frame) of every tile alive when it was sent.
    fn ask_every_tile(
        &self,
        frame: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<(String, Vec<u8>)>, ClientError> {
        let expected = (0..self.tiles.len())
            .filter(|&i| self.tile_alive(i))
            .count();
        if expected == 0 {
            return Err(self.no_tile_answers());
        }
        let key = rpc_all_tiles_key(&self.map_name, &self.client_id);
        let replies = self
            .session
            .get(&key)
            .payload(frame)
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(timeout)
            .wait()
            .map_err(|e| zenoh_failed(format!("send to {key}"), e))?;
        let deadline = Instant::now() + timeout;
        let mut answers: Vec<(String, Vec<u8>)> = Vec::new();
        let mut failures: Vec<ClientError> = Vec::new();
        while answers.len() + failures.len() < expected && Instant::now() < deadline {
            match replies.recv_timeout(WATCH_SLICE) {
                Ok(Some(reply)) => match reply.into_result() {
                    Ok(sample) => {
                        let tile = tile_of_rpc_key(&self.map_name, sample.key_expr().as_str())
                            .unwrap_or("?")
                            .to_string();
                        answers.push((tile, sample.payload().to_bytes().into_owned()));
                    }
                    Err(error) => failures.push(self.failure(None, &error)),
                },
                Ok(None) => {}
                Err(_) => break,
            }
        }
        if answers.len() < expected {
            // A ranking without every tile is not the one search it stands for.
            return Err(failures.pop().unwrap_or_else(|| ClientError::Timeout {
                map_name: format!(
                    "{} (remote, {} of {expected} tiles answered)",
                    self.map_name,
                    answers.len()
                ),
                waited: timeout,
            }));
        }
        Ok(answers)
    }

    /// Why a query ended with no reply: the gateway's session closed (its token goes
    /// with it, within a few milliseconds), or, while the token stays, the gateway
    /// refused to see the query (an access control list denying this client's key).
    fn ended_unanswered(&self, i: usize, key: &str) -> ClientError {
        let deadline = Instant::now() + GONE_WAIT;
        while Instant::now() < deadline {
            if !self.tile_alive(i) {
                return ClientError::Disconnected(self.describe(i));
            }
            std::thread::sleep(WATCH_SLICE);
        }
        RemoteError::Denied {
            map: self.describe(i),
            key: key.to_string(),
        }
        .into()
    }

    fn answer(&self, i: usize, reply: zenoh::query::Reply) -> Result<Vec<u8>, ClientError> {
        match reply.into_result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(error) => Err(self.failure(Some(i), &error)),
        }
    }

    /// The client error a gateway's error reply stands for (`i`: the tile asked).
    fn failure(&self, i: Option<usize>, error: &zenoh::query::ReplyError) -> ClientError {
        let text = error
            .payload()
            .try_to_string()
            .unwrap_or_default()
            .into_owned();
        let (failure, message) = RemoteFailure::parse(&text);
        let name = i.map_or_else(
            || format!("{} (remote)", self.map_name),
            |i| self.describe(i),
        );
        match failure {
            RemoteFailure::NoServer => ClientError::NoServer(name),
            RemoteFailure::Disconnected => ClientError::Disconnected(name),
            RemoteFailure::Timeout => ClientError::Timeout {
                map_name: name,
                waited: Duration::ZERO,
            },
            RemoteFailure::Gateway => RemoteError::Gateway {
                map: name,
                message: message.to_string(),
            }
            .into(),
        }
    }

    fn describe(&self, i: usize) -> String {
        format!("{} (remote, tile {})", self.map_name, self.tiles[i])
    }
}

impl RemoteLink for ZenohLink {
    /// Sends the request (`header` routes it) as a frame and waits for the answer
    /// frame: to the tile the pose guess routes to, or, to relocalize over a tile
    /// set, to every tile at once, the answers ranked as one search would.
    fn call(
        &mut self,
        header: &RequestHeader,
        payload: &[f32],
        timeout: Duration,
    ) -> Result<Vec<u8>, ClientError> {
        if self.routing.is_some() && header.kind == RequestKind::Relocalize as u32 {
            return self.call_every_tile(header, payload, timeout);
        }
        let tile = self.route(header)?;
        self.call_tile(tile, encode_request(header, payload), timeout)
    }

    /// True while some tile's gateway announces a live server.
    fn alive(&self) -> bool {
        (0..self.tiles.len()).any(|i| self.tile_alive(i))
    }

    /// The tile set's index, when the map is served in tiles.
    fn tile_index(&self) -> Option<&TileIndex> {
        self.routing.as_ref().map(|(index, _)| index)
    }

    /// The tile the last routed request went to.
    fn current_tile(&self) -> Option<&str> {
        match &self.routing {
            Some((_, router)) => router.current().map(|i| self.tiles[i].as_str()),
            None => self.tiles.first().map(String::as_str),
        }
    }
}

/// The tile index a gateway of `map_name` answers (a map served in tiles has one).
fn fetch_index(session: &zenoh::Session, map_name: &str) -> Result<TileIndex, ClientError> {
    let key = tile_index_key(map_name);
    let deadline = Instant::now() + CONNECT_WAIT;
    // The gateway's index queryable may reach this session a moment after its tokens.
    while Instant::now() < deadline {
        let replies = session
            .get(&key)
            .timeout(CONNECT_WAIT)
            .wait()
            .map_err(|e| zenoh_failed(format!("ask {key}"), e))?;
        if let Some(sample) = replies.iter().find_map(|r| r.into_result().ok()) {
            let text = sample.payload().try_to_string().map_err(|e| {
                RemoteError::BadAnswer(format!("the tile index on {key} is not text: {e}"))
            })?;
            return TileIndex::parse(&text, std::path::Path::new(&key)).map_err(|e| {
                RemoteError::BadAnswer(format!("the gateway's tile index: {e}")).into()
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Err(RemoteError::NoIndex {
        map: map_name.to_string(),
        key,
        waited: CONNECT_WAIT,
    }
    .into())
}

/// A failed Zenoh operation on an open session.
fn zenoh_failed(what: String, reason: impl std::fmt::Display) -> ClientError {
    RemoteError::Zenoh {
        what,
        reason: reason.to_string(),
    }
    .into()
}

/// A client id unlikely to collide: process id and clock.
fn random_client_id() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!("c{:x}-{:x}", std::process::id(), nanos as u64)
}
