//! The registration framework (docs/DESIGN.md#registration, after PCL's design): algorithms
//! apart from data. Clouds are never moved; only their poses change.

use nalgebra::{Matrix6, Vector6};
use serde::{Deserialize, Serialize};

use kfmap_geometry::geometry::{Pose, to_point, transform_point};
use kfmap_geometry::options::{InvalidOption, ensure_distance, ensure_ratio};
use kfmap_geometry::registration::{
    Fitness, PreparedCloud, RegistrationError, RegistrationParams, RegistrationResult,
    RobustKernel, align,
};
use kfmap_graph::pose_graph::{GraphError, GraphParams, GraphReport, PoseEdge, PoseGraph};
use kfmap_map::covis::{CovisOptions, CovisibilityGraph};

/// Clouds this close in sequence to an accepted loop's newer end share its loop.
const LOOP_NEIGHBOURHOOD: usize = 5;

/// Index of a cloud added to a [`GlobalRegistration`].
pub type CloudId = usize;

/// Why a global registration step failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GlobalError {
    /// A cloud id that was never added.
    #[error("cloud {0} is unknown")]
    UnknownCloud(CloudId),
    /// Pairwise registration failed.
    #[error(transparent)]
    Registration(#[from] RegistrationError),
    /// The pose graph could not be optimized.
    #[error(transparent)]
    Graph(#[from] GraphError),
}

/// Aligns a source cloud onto a target cloud.
pub trait PairwiseRegistration: Sync {
    /// `T_target_source` from `initial`.
    fn register(
        &self,
        target: &PreparedCloud,
        source: &PreparedCloud,
        initial: &Pose,
    ) -> Result<RegistrationResult, RegistrationError>;
}

impl PairwiseRegistration for RegistrationParams {
    fn register(
        &self,
        target: &PreparedCloud,
        source: &PreparedCloud,
        initial: &Pose,
    ) -> Result<RegistrationResult, RegistrationError> {
        align(target, source, initial, self)
    }
}

/// What verifying one loop candidate found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopVerdict {
    /// `T_older_newer` as registered.
    pub pose: Pose,
    /// How the newer cloud lies on the older one at that pose.
    pub fitness: Fitness,
    /// The fine registration converged.
    pub converged: bool,
    /// The scene does not constrain some direction.
    pub degenerate: bool,
    /// Passed every gate: the loop becomes a graph edge.
    pub accepted: bool,
}

/// One loop candidate and its verdict (`None`: the registration could not run).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopCheck {
    /// The older cloud.
    pub older: CloudId,
    /// The newer cloud.
    pub newer: CloudId,
    /// The verification.
    pub verdict: Option<LoopVerdict>,
}

/// Finds and verifies loop closures among posed clouds.
pub trait LoopDetection {
    /// Candidate pairs `(older, newer)` at the current poses.
    fn candidates(&self, poses: &[Pose]) -> Vec<(CloudId, CloudId)>;
    /// Registers `newer` onto `older` from `guess` (`T_older_newer`) and judges whether
    /// the pair really overlaps; `None` when the registration could not run.
    fn verify(
        &self,
        older: &PreparedCloud,
        newer: &PreparedCloud,
        guess: &Pose,
    ) -> Option<LoopVerdict>;
}

/// Optimizes a pose graph in place.
pub trait GraphOptimizer {
    /// Moves the graph's poses to minimize its error.
    fn optimize(&self, graph: &mut PoseGraph) -> Result<GraphReport, GraphError>;
}

impl GraphOptimizer for GraphParams {
    fn optimize(&self, graph: &mut PoseGraph) -> Result<GraphReport, GraphError> {
        graph.optimize(self)
    }
}

/// Registers a set of clouds into one frame.
pub trait GlobalRegistration {
    /// Adds a cloud with an optional pose guess (map frame); returns its id.
    fn add_cloud(
        &mut self,
        cloud: PreparedCloud,
        pose_guess: Option<Pose>,
    ) -> Result<CloudId, GlobalError>;
    /// `T_to_from`: maps points of cloud `from` into cloud `to`'s frame.
    fn transform(&self, from: CloudId, to: CloudId) -> Result<Pose, GlobalError>;
    /// Refines every pose (loops, optimization); returns what it did.
    fn compute(&mut self) -> Result<GlobalReport, GlobalError>;
}

/// What [`GlobalRegistration::compute`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct GlobalReport {
    /// Loop candidates examined.
    pub loops_found: usize,
    /// Every candidate verified, accepted or not, with its fitness (the accepted ones
    /// became graph edges: [`accepted_loops`]).
    pub loop_checks: Vec<LoopCheck>,
    /// The pose-graph optimization.
    pub graph: GraphReport,
}

/// The accepted loops `(older, newer)` among `checks`.
pub fn accepted_loops(checks: &[LoopCheck]) -> Vec<(CloudId, CloudId)> {
    checks
        .iter()
        .filter(|c| c.verdict.is_some_and(|v| v.accepted))
        .map(|c| (c.older, c.newer))
        .collect()
}

/// Loop candidates by distance: poses closer than `max_distance` but at least
/// `min_separation` clouds apart in sequence; once a loop is accepted for a cloud, the
/// covisible neighbours of its partner are skipped (their constraint would repeat it).
/// Verified by a coarse-to-fine registration and fitness gates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct DistanceLoopDetection {
    /// Metres between the two poses, at most.
    pub max_distance: f64,
    /// Clouds apart in sequence, at least.
    pub min_separation: usize,
    /// Fine registration (distances, iterations; clouds come prepared).
    pub registration: RegistrationParams,
    /// Share of the newer cloud's points that must find a partner.
    pub min_inlier_ratio: f64,
    /// RMS correspondence distance at most, metres. Clouds voxelized at 0.5 m (the
    /// odometry's) leave 0.29-0.34 m between correctly aligned real scans (`balm_os0`),
    /// because their points sample the same surfaces at different places.
    pub max_rmse: f64,
}

impl Default for DistanceLoopDetection {
    fn default() -> Self {
        Self {
            max_distance: 10.0,
            min_separation: 30,
            registration: RegistrationParams::default(),
            min_inlier_ratio: 0.6,
            max_rmse: 0.4,
        }
    }
}

impl DistanceLoopDetection {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        self.registration.validate()?;
        ensure_distance("max-distance", self.max_distance)?;
        ensure_ratio("min-inlier-ratio", self.min_inlier_ratio)?;
        ensure_distance("max-rmse", self.max_rmse)
    }
}

impl LoopDetection for DistanceLoopDetection {
    fn candidates(&self, poses: &[Pose]) -> Vec<(CloudId, CloudId)> {
        let mut pairs = Vec::new();
        for (newer, pn) in poses.iter().enumerate() {
            let older_end = newer.saturating_sub(self.min_separation);
            let best = (0..older_end)
                .map(|older| {
                    let d = (poses[older].translation.vector - pn.translation.vector).norm();
                    (d, older)
                })
                .filter(|(d, _)| *d < self.max_distance)
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((_, older)) = best {
                pairs.push((older, newer));
            }
        }
        pairs
    }

    fn verify(
        &self,
        older: &PreparedCloud,
        newer: &PreparedCloud,
        guess: &Pose,
    ) -> Option<LoopVerdict> {
        // Coarse first: drift can be metres, beyond the fine correspondence distance.
        let coarse = RegistrationParams {
            max_correspondence_distance: self.max_distance.min(5.0),
            max_iterations: 30,
            kernel: RobustKernel::Cauchy { delta: 1.0 },
            ..self.registration
        };
        let rough = align(older, newer, guess, &coarse).ok()?;
        let fine = align(older, newer, &rough.pose, &self.registration).ok()?;
        let accepted = fine.converged
            && !fine.degenerate
            && fine.fitness.inlier_ratio >= self.min_inlier_ratio
            && fine.fitness.rmse <= self.max_rmse;
        Some(LoopVerdict {
            pose: fine.pose,
            fitness: fine.fitness,
            converged: fine.converged,
            degenerate: fine.degenerate,
            accepted,
        })
    }
}

/// Sequential registration (each cloud against the previous one, from the guessed
/// relative pose), loop detection, and pose-graph optimization.
pub struct PairwiseGlobalRegistration<P, L, G> {
    /// Consecutive-cloud registration.
    pub pairwise: P,
    /// Loop closure.
    pub loops: L,
    /// Graph optimization.
    pub optimizer: G,
    /// Information of consecutive and loop edges over `(omega, v)`.
    pub edge_information: Matrix6<f64>,
    /// Kernel of loop edges.
    pub loop_kernel: RobustKernel,
    /// Register consecutive clouds; when false, consecutive edges take the relative
    /// pose of the guesses (e.g. scan-to-map odometry, better than keyframe-to-keyframe).
    pub register_consecutive: bool,
    /// A loop's newer cloud is verified against the older cloud merged with this many
    /// sequence neighbours on each side (0: the older cloud alone).
    pub loop_submap_neighbours: usize,
    clouds: Vec<PreparedCloud>,
    guesses: Vec<Option<Pose>>,
    poses: Vec<Pose>,
    edges: Vec<PoseEdge>,
}

impl<P: PairwiseRegistration, L: LoopDetection, G: GraphOptimizer>
    PairwiseGlobalRegistration<P, L, G>
{
    /// An empty registration; edges weigh 1 cm / 0.5 deg standard deviations.
    pub fn new(pairwise: P, loops: L, optimizer: G) -> Self {
        let (sigma_r, sigma_t) = (0.5f64.to_radians(), 0.01);
        let information = Matrix6::from_diagonal(&Vector6::new(
            1.0 / (sigma_r * sigma_r),
            1.0 / (sigma_r * sigma_r),
            1.0 / (sigma_r * sigma_r),
            1.0 / (sigma_t * sigma_t),
            1.0 / (sigma_t * sigma_t),
            1.0 / (sigma_t * sigma_t),
        ));
        Self {
            pairwise,
            loops,
            optimizer,
            edge_information: information,
            loop_kernel: RobustKernel::Cauchy { delta: 1.0 },
            register_consecutive: true,
            loop_submap_neighbours: 5,
            clouds: Vec::new(),
            guesses: Vec::new(),
            poses: Vec::new(),
            edges: Vec::new(),
        }
    }

    /// Current poses, by cloud id.
    pub fn poses(&self) -> &[Pose] {
        &self.poses
    }

    /// The graph's edges so far, between cloud ids: consecutive, then accepted loops.
    pub fn edges(&self) -> &[PoseEdge] {
        &self.edges
    }

    /// Cloud `centre` merged with its sequence neighbours, in `centre`'s frame: one
    /// sparse scan against another gave 0.4-0.5 m RMSE and no accepted loop on the
    /// simulated campus.
    fn loop_submap(&self, centre: CloudId) -> Result<PreparedCloud, RegistrationError> {
        let n = self.loop_submap_neighbours;
        let range = centre.saturating_sub(n)..(centre + n + 1).min(self.clouds.len());
        let to_centre = self.poses[centre].inverse();
        let points = range
            .flat_map(|id| {
                let pose = to_centre * self.poses[id];
                self.clouds[id]
                    .points
                    .iter()
                    .map(move |p| to_point(&transform_point(&pose, p)))
            })
            .collect();
        PreparedCloud::from_points(points, &RegistrationParams::default(), "loop submap")
    }
}

impl<P: PairwiseRegistration, L: LoopDetection, G: GraphOptimizer> GlobalRegistration
    for PairwiseGlobalRegistration<P, L, G>
{
    fn add_cloud(
        &mut self,
        cloud: PreparedCloud,
        pose_guess: Option<Pose>,
    ) -> Result<CloudId, GlobalError> {
        let id = self.clouds.len();
        let pose = match (id, self.poses.last(), self.guesses.last()) {
            (0, _, _) => pose_guess.unwrap_or_else(Pose::identity),
            (_, Some(prev), previous_guess) => {
                // The guessed motion since the previous cloud, else none.
                let relative = match (previous_guess, pose_guess) {
                    (Some(Some(a)), Some(b)) => a.inverse() * b,
                    _ => Pose::identity(),
                };
                let measured = if self.register_consecutive || pose_guess.is_none() {
                    self.pairwise
                        .register(&self.clouds[id - 1], &cloud, &relative)?
                        .pose
                } else {
                    relative
                };
                self.edges.push(PoseEdge::new(
                    (id - 1) as u64,
                    id as u64,
                    measured,
                    self.edge_information,
                ));
                prev * measured
            }
            _ => unreachable!("poses and clouds grow together"),
        };
        self.clouds.push(cloud);
        self.guesses.push(pose_guess);
        self.poses.push(pose);
        Ok(id)
    }

    fn transform(&self, from: CloudId, to: CloudId) -> Result<Pose, GlobalError> {
        let pose = |id: CloudId| self.poses.get(id).ok_or(GlobalError::UnknownCloud(id));
        Ok(pose(to)?.inverse() * pose(from)?)
    }

    fn compute(&mut self) -> Result<GlobalReport, GlobalError> {
        let candidates = self.loops.candidates(&self.poses);
        let mut covis = CovisibilityGraph::new(CovisOptions::default());
        for (id, (cloud, pose)) in self.clouds.iter().zip(&self.poses).enumerate() {
            let points = cloud.points.iter().map(|p| transform_point(pose, p).into());
            covis.set_keyframe(id as u64, points);
        }
        let mut accepted: Vec<(CloudId, CloudId)> = Vec::new();
        let mut checks = Vec::new();
        for &(older, newer) in &candidates {
            // A loop already joins this place: its partner's covisible neighbours repeat it.
            let repeats = accepted.iter().any(|&(o, n)| {
                newer.abs_diff(n) < LOOP_NEIGHBOURHOOD
                    && (o == older || covis.weight(o as u64, older as u64) > 0)
            });
            if repeats {
                continue;
            }
            let guess = self.poses[older].inverse() * self.poses[newer];
            let submap = self.loop_submap(older)?;
            let verdict = self.loops.verify(&submap, &self.clouds[newer], &guess);
            checks.push(LoopCheck {
                older,
                newer,
                verdict,
            });
            if let Some(v) = verdict.filter(|v| v.accepted) {
                let mut edge =
                    PoseEdge::new(older as u64, newer as u64, v.pose, self.edge_information);
                edge.kernel = self.loop_kernel;
                self.edges.push(edge);
                accepted.push((older, newer));
            }
        }
        let mut graph = PoseGraph::default();
        for (id, pose) in self.poses.iter().enumerate() {
            graph.add_pose(id as u64, *pose)?;
        }
        for edge in &self.edges {
            graph.add_edge(*edge)?;
        }
        let report = self.optimizer.optimize(&mut graph)?;
        for (id, pose) in self.poses.iter_mut().enumerate() {
            *pose = *graph.pose(id as u64).expect("every cloud is a vertex");
        }
        Ok(GlobalReport {
            loops_found: candidates.len(),
            loop_checks: checks,
            graph: report,
        })
    }
}
