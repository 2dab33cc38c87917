//! A gravity pool fed one IMU window at a time, as a server session receives them:
//! stamped poses arrive with the windows (and with localized scans), and each window is
//! pooled once a later pose exists, so its platform acceleration is removed exactly as
//! the offline pool does ([`super::fill_pool`]: velocities by central differences).

use std::cell::OnceCell;
use std::collections::{BTreeMap, VecDeque};

use super::{
    GravityAligner, GravityCorrection, GravityParams, ImuWindow, KfAccSample, MotionModel,
    compensated_sample,
};
use crate::KeyframeId;
use crate::geometry::Pose;
use crate::options::InvalidOption;

/// Stamped poses kept, at most (a minute at 10 Hz).
const MAX_POSES: usize = 600;
/// Pool members kept, at most (an hour of one-second windows): beyond it the oldest
/// member is forgotten, so a session's memory and answer time stay bounded however
/// long a client streams.
pub const MAX_MEMBERS: usize = 3600;
/// Windows held for a later pose, at most; the oldest is left out beyond this.
const MAX_PENDING: usize = 8;
/// Stamped windows shorter than this are joined with the next: the platform's
/// acceleration over a window is a velocity difference over its length, so the pose
/// noise in it shrinks as windows grow (at 7 Hz scan windows the served tilt was
/// 0.097 deg off on the simulated campus).
pub const MIN_WINDOW_SECONDS: f64 = 0.5;
/// Poses further apart than this (seconds) do not carry the platform's acceleration
/// between them: a window they bracket is left out.
const MAX_POSE_GAP: f64 = 1.0;

/// One window waiting for a pose after it.
#[derive(Debug, Clone)]
struct Pending {
    id: KeyframeId,
    /// The window covers `(t_prev, t_end]`.
    t_prev: f64,
    t_end: f64,
    pose: Pose,
    window: ImuWindow,
}

/// What the pool holds and what it concluded.
#[derive(Debug, Clone, Copy)]
pub struct LiveAnswer {
    /// The correction over the pool (`None`: too few members).
    pub correction: Option<GravityCorrection>,
    /// Pool members.
    pub members: usize,
    /// Members whose platform acceleration was removed.
    pub compensated: usize,
    /// Windows waiting for a later pose (or joining the next window).
    pub pending: usize,
    /// Stamped windows left out: no stamped poses bracketed them closely enough to
    /// remove the platform's acceleration (a raw mean of a moving platform, weighted
    /// by its steadiness, would pull the estimate off).
    pub skipped: usize,
}

/// A session's gravity pool.
#[derive(Debug, Clone)]
pub struct LiveGravity {
    aligner: GravityAligner,
    /// Pose of each pooled member, map frame.
    poses: BTreeMap<KeyframeId, Pose>,
    /// Whether each pooled member was compensated.
    compensated: BTreeMap<KeyframeId, bool>,
    /// Pooled member ids, oldest first.
    order: VecDeque<KeyframeId>,
    /// The correction over the pool as it is: most requests add a window that is still
    /// pending, and the joint estimate is the costly part of an answer.
    correction: OnceCell<Option<GravityCorrection>>,
    /// Stamped poses, oldest first.
    history: VecDeque<(f64, Pose)>,
    pending: VecDeque<Pending>,
    /// Stamped windows joined so far, shorter than [`MIN_WINDOW_SECONDS`].
    building: Option<Pending>,
    skipped: usize,
    /// End of the last window, seconds: the next window starts there.
    last_end: Option<f64>,
}

impl LiveGravity {
    /// An empty pool; the parameters are validated.
    pub fn new(params: GravityParams) -> Result<Self, InvalidOption> {
        Ok(Self {
            aligner: GravityAligner::new(params)?,
            poses: BTreeMap::new(),
            compensated: BTreeMap::new(),
            order: VecDeque::new(),
            correction: OnceCell::new(),
            history: VecDeque::new(),
            pending: VecDeque::new(),
            building: None,
            skipped: 0,
            last_end: None,
        })
    }

    /// A pose at time `t` (seconds, the IMU's clock): a localized scan, or the pose a
    /// window was sent with. Pools the windows it lets be compensated.
    pub fn add_pose(&mut self, t: f64, pose: Pose) {
        if !t.is_finite() {
            return;
        }
        let at = self.history.partition_point(|(s, _)| *s < t);
        match self.history.get_mut(at) {
            Some(same) if same.0 == t => *same = (t, pose),
            _ => self.history.insert(at, (t, pose)),
        }
        while self.history.len() > MAX_POSES {
            self.history.pop_front();
        }
        self.settle();
    }

    /// The IMU window of keyframe (or scan) `id`, which ends at the pose `pose` taken at
    /// `stamp` (`None`: unstamped, pooled raw at once, as before protocol 4). It covers
    /// the time since the previous window. Stamped windows are joined until they span
    /// [`MIN_WINDOW_SECONDS`]; the first one only starts the clock (it has no start).
    pub fn add_window(
        &mut self,
        id: KeyframeId,
        window: ImuWindow,
        pose: Pose,
        stamp: Option<f64>,
    ) {
        let Some(last_sample) = window.samples().last().map(|s| s.t) else {
            return;
        };
        let Some(t_end) = stamp else {
            let first_sample = window.samples()[0].t;
            let raw = Pending {
                id,
                t_prev: first_sample,
                t_end: last_sample,
                pose,
                window,
            };
            self.pool_raw(raw);
            return;
        };
        let Some(t_prev) = self.last_end.filter(|&t| t < t_end) else {
            // No start: nothing to remove its platform acceleration over.
            self.last_end = Some(t_end);
            self.skipped += 1;
            self.add_pose(t_end, pose);
            return;
        };
        self.last_end = Some(t_end);
        let joined = match self.building.take() {
            Some(b) => Pending {
                id,
                t_prev: b.t_prev,
                t_end,
                pose,
                window: ImuWindow::new([b.window.samples(), window.samples()].concat()),
            },
            None => Pending {
                id,
                t_prev,
                t_end,
                pose,
                window,
            },
        };
        if joined.t_end - joined.t_prev >= MIN_WINDOW_SECONDS - 1e-6 {
            self.pending.push_back(joined);
        } else {
            self.building = Some(joined);
        }
        while self.pending.len() > MAX_PENDING {
            self.pending.pop_front();
            self.skipped += 1;
        }
        self.add_pose(t_end, pose);
    }

    /// The pool's state and correction.
    pub fn answer(&self) -> LiveAnswer {
        LiveAnswer {
            correction: *self
                .correction
                .get_or_init(|| self.aligner.estimate_global_correction(&self.poses)),
            members: self.aligner.size(),
            compensated: self.compensated.values().filter(|c| **c).count(),
            pending: self.pending.len() + self.building.is_some() as usize,
            skipped: self.skipped,
        }
    }

    /// Pools every pending window a later pose now brackets.
    fn settle(&mut self) {
        let Some(&(latest, _)) = self.history.back() else {
            return;
        };
        while self.pending.front().is_some_and(|p| p.t_end < latest) {
            let window = self.pending.pop_front().expect("checked");
            if !self.aligner.params().motion_compensation {
                self.pool_raw(window);
                continue;
            }
            let sample = self
                .motion_around(window.t_prev, window.t_end)
                .and_then(|m| compensated_sample(&window.window, window.t_prev, &window.pose, &m));
            match sample {
                Some(sample) => self.insert(&window, sample, true),
                None => self.skipped += 1,
            }
        }
    }

    /// The motion of the stamped poses, when they cover `[t0, t1]` with two poses on
    /// each side (velocities at both ends by central differences: a one-sided one errs
    /// by half the acceleration times the pose spacing) and no gap over
    /// [`MAX_POSE_GAP`].
    fn motion_around(&self, t0: f64, t1: f64) -> Option<MotionModel> {
        let from = self
            .history
            .partition_point(|(t, _)| *t <= t0)
            .checked_sub(2)?;
        let to = self.history.partition_point(|(t, _)| *t < t1) + 1;
        if to >= self.history.len() {
            return None;
        }
        let around = self.history.range(from..=to);
        if around
            .clone()
            .zip(around.clone().skip(1))
            .any(|(a, b)| b.0 - a.0 > MAX_POSE_GAP)
        {
            return None;
        }
        // Central differences are local: the poses around the window decide its motion.
        MotionModel::new(around.copied())
    }

    /// Adds `window`'s raw mean to the pool.
    fn pool_raw(&mut self, p: Pending) {
        if let Some(sample) = KfAccSample::from_window(&p.window) {
            self.insert(&p, sample, false);
        }
    }

    fn insert(&mut self, p: &Pending, sample: KfAccSample, compensated: bool) {
        self.correction = OnceCell::new();
        self.aligner.on_new_keyframe_raw(p.id, sample);
        if self.poses.insert(p.id, p.pose).is_none() {
            self.order.push_back(p.id);
        }
        self.compensated.insert(p.id, compensated);
        while self.order.len() > MAX_MEMBERS {
            let oldest = self.order.pop_front().expect("longer than the cap");
            self.aligner.on_keyframe_dropped(oldest);
            self.poses.remove(&oldest);
            self.compensated.remove(&oldest);
        }
    }
}
