//! The worker side: answer one request, send the response, release the request, then
//! wake the clients (in that order: a client woken before the request is released can
//! find its slot still taken and stall).

use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use iceoryx2::port::notifier::Notifier;
use kfmap_geometry::gravity::LiveAnswer;
use kfmap_map::archive::ArchiveError;
use kfmap_map::tiles::PlaceRanking;
use kfmap_protocol::log_limit::warn_limited;
use kfmap_protocol::transport::Transport;
use kfmap_protocol::{
    Rejection, RequestHeader, RequestKind, ResponseHeader, StatusCode, WireCovOptions, WireRanking,
    WireSessionGravity, check_version, write_text,
};
use tracing::{debug, info, warn};

use super::answer::{Answer, AnswerPairings};
use super::budget::{Budget, Reservation, worst_case};
use super::dispatch::answer;
use super::limits::{Limits, PAIRING_BYTES};
use super::ports::{ClientPorts, Request, Sender};
use super::session::{Sessions, client_of};
use super::state::MapSlot;
use super::stats::Stats;
use super::unread::UnreadAnswers;

/// Free space `/dev/shm` keeps beyond an answer's segment: other processes' ports.
const SHM_HEADROOM: u64 = 16 << 20;

/// A received request, when it arrived, and its share of the budget (given back when
/// the job is dropped, after the response is sent).
pub struct Job {
    request: Request,
    received: Instant,
    reservation: Option<Reservation>,
    /// The process it came from: its turn in the queue and the workers' time it uses.
    pub process: u128,
}

impl Job {
    /// Wraps a request received now.
    pub fn new(request: Request) -> Self {
        Self {
            request,
            received: Instant::now(),
            reservation: None,
            process: 0,
        }
    }

    /// The job of `process`, holding `reservation` until it is answered.
    pub fn holding(self, process: u32, reservation: Reservation) -> Self {
        Self {
            reservation: Some(reservation),
            process: process as u128,
            ..self
        }
    }
}

/// What every worker shares.
pub struct WorkerContext<'a> {
    /// The map.
    pub slot: &'a MapSlot,
    /// Client sessions.
    pub sessions: &'a Sessions,
    /// Counters.
    pub stats: &'a Stats,
    /// Request limits.
    pub limits: Limits,
    /// Wakes clients after a response.
    pub notifier: &'a Notifier<Transport>,
    /// Served map name.
    pub map_name: &'a str,
    /// Server start.
    pub started: Instant,
    /// Open reloaded maps without bytechecks.
    pub trust: bool,
    /// Memory and request slots held by requests queued or in flight.
    pub budget: Arc<Budget>,
    /// Which node and process sent a request.
    pub ports: ClientPorts<'a>,
    /// Large answers sent and not yet read.
    pub unread: &'a UnreadAnswers,
    /// Pairings of the largest answer sent so far: the response segment holds that
    /// much, so only a larger answer can make it grow.
    pub largest_answer: AtomicUsize,
}

impl WorkerContext<'_> {
    /// Answers `job` and wakes the clients.
    pub fn handle(&self, job: Job) {
        self.stats.started();
        let header = *job.request.user_header();
        let computed = std::panic::catch_unwind(AssertUnwindSafe(|| {
            self.compute(&header, job.request.payload())
        }));
        let answer = computed.unwrap_or_else(|_| {
            Answer::rejected(
                header.request_id,
                &Rejection::new(
                    StatusCode::Internal,
                    "internal error while answering; see the server log",
                ),
            )
        });
        let status = answer.header.status;
        self.respond(job, &header, &answer);
        self.stats.finished();
        debug!(
            kind = header.kind,
            points = header.point_count,
            pairings = answer.pairings.len(),
            status,
            server_us = answer.header.server_us,
            "answered"
        );
    }

    fn compute(&self, header: &RequestHeader, payload: &[f32]) -> Answer {
        match RequestKind::from_code(header.kind) {
            Some(RequestKind::Status) => self.status(header),
            Some(RequestKind::Reload) => self.reload_answer(header),
            Some(RequestKind::Track | RequestKind::TrackImu) => {
                let map = self.slot.current();
                let session = self
                    .sessions
                    .get(client_of(header.client_node), map.generation);
                super::track::answer(map, session, header, payload, &self.limits)
            }
            _ => {
                let map = self.slot.current();
                let session = self
                    .sessions
                    .get(client_of(header.client_node), map.generation);
                let mut session = session.lock().unwrap_or_else(|e| e.into_inner());
                answer(&map, &mut session, header, payload, &self.limits)
            }
        }
    }

    /// Sends `answer`, releases the request, records the latency, wakes the clients.
    fn respond(&self, job: Job, header: &RequestHeader, answer: &Answer) {
        let Job {
            request,
            received,
            reservation,
            ..
        } = job;
        let refused;
        let answer = match self.fits_shared_memory(answer) {
            Ok(()) => answer,
            Err(rejection) => {
                warn_limited("shared memory full", &rejection.message);
                refused = Answer::rejected(header.request_id, &rejection);
                &refused
            }
        };
        if let Err(e) = send(&request, answer) {
            // A client that stopped waiting (or died) makes this at will: rate-limited.
            warn_limited(
                "response not sent",
                &format!("could not send a response ({e}); sending the error instead"),
            );
            let error = Answer::rejected(
                header.request_id,
                &Rejection::new(
                    StatusCode::Internal,
                    format!("the answer could not be sent: {e}"),
                ),
            );
            let _ = send(&request, &error);
        }
        let bytes = answer.pairings.len() as u64 * PAIRING_BYTES;
        self.unread.hold(request, reservation, bytes);
        self.stats
            .record(header.kind, received.elapsed().as_secs_f64() as f32 * 1e6);
        let _ = self.notifier.notify();
    }

    /// Refuses an answer that would grow the response segment beyond what `/dev/shm`
    /// can back: a segment grows by powers of two up to twice the answer, and a write
    /// to a tmpfs page that cannot be backed kills the writer with SIGBUS. Answers no
    /// larger than one sent before need no look at `/dev/shm`.
    fn fits_shared_memory(&self, answer: &Answer) -> Result<(), Rejection> {
        let pairings = answer.pairings.len();
        if pairings <= self.largest_answer.load(Ordering::Relaxed) {
            return Ok(());
        }
        let bytes = pairings as u64 * PAIRING_BYTES;
        let needed = 2 * bytes + SHM_HEADROOM;
        match super::shared_memory_free() {
            Some(free) if free < needed => Err(Rejection::new(
                StatusCode::Busy,
                format!(
                    "/dev/shm has {} MiB free; this answer ({} MiB) could need {} MiB of shared memory there; free space in /dev/shm (in a container, raise --shm-size) or ask for less",
                    free >> 20,
                    bytes >> 20,
                    needed >> 20
                ),
            )),
            _ => {
                self.largest_answer.fetch_max(pairings, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    /// Answers a request that was queued but never started when shutting down.
    pub fn refuse_shutting_down(&self, job: Job) {
        self.refuse(
            job,
            &Rejection::new(
                StatusCode::ShuttingDown,
                "the server is shutting down; the request was not started",
            ),
        );
    }

    /// Answers `job` with `rejection` without working on it.
    pub fn refuse(&self, job: Job, rejection: &Rejection) {
        let header = *job.request.user_header();
        self.stats.started();
        self.respond(
            job,
            &header,
            &Answer::rejected(header.request_id, rejection),
        );
        self.stats.finished();
    }

    /// Takes `request` in: checks who sent it and reserves its worst case. The job to
    /// queue, or `None` when it was refused already.
    pub fn admit(&self, request: Request) -> Option<Job> {
        let header = *request.user_header();
        let job = Job::new(request);
        let claimed = client_of(header.client_node);
        let owner = match self.ports.sender(job.request.origin()) {
            Sender::Served(owner) if owner.node == claimed => owner,
            Sender::OverProcessLimit(owner) if owner.node == claimed => {
                let limit = self.ports.per_process();
                let message = format!(
                    "process {} has {limit} other client ports open, max-clients-per-process ({limit}, server.toml); requests through its further ports are refused until some close",
                    owner.process
                );
                warn_limited("client ports over max-clients-per-process", &message);
                self.refuse(job, &Rejection::new(StatusCode::Busy, message));
                return None;
            }
            found => {
                let sender = match found {
                    Sender::Served(o) | Sender::OverProcessLimit(o) => {
                        format!("node {:032x}", o.node)
                    }
                    Sender::Unregistered => "an unregistered port".to_string(),
                };
                self.refuse(
                    job,
                    &Rejection::new(
                        StatusCode::NotYourSession,
                        format!(
                            "client_node {claimed:032x} in the header is not the node of the port that sent the request ({sender}); a client may only use its own session"
                        ),
                    ),
                );
                return None;
            }
        };
        let points = (job.request.payload().len() / 3) as u64;
        let kind = RequestKind::from_code(header.kind);
        let reserved = worst_case(kind, &header, points, self.budget.limits())
            .and_then(|cost| self.budget.reserve(owner.process, cost));
        match reserved {
            Ok(reservation) => Some(job.holding(owner.process, reservation)),
            Err(rejection) => {
                self.refuse(job, &rejection);
                None
            }
        }
    }

    fn status(&self, request: &RequestHeader) -> Answer {
        if let Err(rejection) = check_version(request) {
            return Answer::rejected(request.request_id, &rejection);
        }
        let map = self.slot.current();
        let mut h = ResponseHeader {
            request_id: request.request_id,
            map_keyframes: map.keyframes as u64,
            map_points: map.points as u64,
            uptime_s: self.started.elapsed().as_secs_f64(),
            sessions: self.sessions.len() as u32,
            // Less this status request itself.
            in_flight: self.stats.in_flight().saturating_sub(1),
            pose: map.map_from_input,
            scan_covariance: WireCovOptions::from(&self.limits.scan_covariance),
            relocalize_ranking: WireRanking::from(&PlaceRanking::of(&self.limits.relocalize)),
            ..Default::default()
        };
        for (slot, f) in self.stats.figures().iter().enumerate() {
            h.counts[slot] = f.count;
            h.p50_us[slot] = f.p50_us;
            h.p99_us[slot] = f.p99_us;
        }
        h.map_name_len = write_text(&mut h.map_name, self.map_name);
        h.set_message(&map.path.display().to_string());
        for (slot, (client, pool)) in h.session_gravity.iter_mut().zip(self.sessions.gravity()) {
            *slot = session_gravity(client, pool.as_ref());
        }
        Answer {
            header: h,
            pairings: AnswerPairings::default(),
        }
    }

    fn reload_answer(&self, request: &RequestHeader) -> Answer {
        if let Err(rejection) = check_version(request) {
            return Answer::rejected(request.request_id, &rejection);
        }
        match self.reload() {
            Ok(message) => {
                let mut header = ResponseHeader {
                    request_id: request.request_id,
                    ..Default::default()
                };
                header.set_message(&message);
                Answer {
                    header,
                    pairings: AnswerPairings::default(),
                }
            }
            Err(failed) => Answer::rejected(
                request.request_id,
                &Rejection::new(StatusCode::Internal, failed.to_string()),
            ),
        }
    }

    /// Reopens the map file and switches to it; the message says what is served now.
    pub fn reload(&self) -> Result<String, ReloadFailed> {
        match self.slot.reload(None, self.trust) {
            Ok(map) => {
                let message = format!(
                    "reloaded {} (generation {}, {} keyframes, {} points)",
                    map.path.display(),
                    map.generation,
                    map.keyframes,
                    map.points
                );
                info!("{message}");
                Ok(message)
            }
            Err(e) => {
                let failed = ReloadFailed(e);
                warn!("{failed}");
                Err(failed)
            }
        }
    }
}

/// A map reload that failed: the server keeps serving the map it had.
#[derive(Debug, thiserror::Error)]
#[error("reload failed, still serving the previous map: {0}")]
pub struct ReloadFailed(pub ArchiveError);

/// Loans a response of the answer's size, writes the pairings straight into it (no
/// intermediate buffer) and sends it.
fn send(request: &Request, answer: &Answer) -> Result<(), String> {
    let mut response = request
        .loan_slice_uninit(answer.pairings.len())
        .map_err(|e| format!("{e:?}"))?;
    *response.user_header_mut() = answer.header;
    answer.pairings.write(response.payload_mut());
    // SAFETY: `write` initialized every element of the loan (it checks the count).
    let response = unsafe { response.assume_init() };
    response.send().map_err(|e| format!("{e:?}"))
}

/// One session's gravity pool as a status report lists it.
fn session_gravity(client: u128, pool: Option<&LiveAnswer>) -> WireSessionGravity {
    let client_node = [(client >> 64) as u64, client as u64];
    let Some(pool) = pool else {
        return WireSessionGravity {
            client_node,
            busy: 1,
            ..Default::default()
        };
    };
    let mut out = WireSessionGravity {
        client_node,
        members: pool.members as u32,
        compensated: pool.compensated as u32,
        pending: pool.pending as u32,
        skipped: pool.skipped as u32,
        ..Default::default()
    };
    if let Some(c) = &pool.correction {
        out.has_gravity = 1;
        out.inliers = c.estimate.health.inliers as u32;
        out.roll_pitch = [c.roll, c.pitch];
        out.spread_deg = c.estimate.health.spread_deg;
        out.accel_bias = c.estimate.accel_bias.mps2.into();
        out.gravity = c.estimate.g.into();
        out.bias_observable = c.estimate.accel_bias.observable as u32;
    }
    out
}
