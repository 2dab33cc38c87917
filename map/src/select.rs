//! Choosing the active keyframes for a query pose (docs/DESIGN.md#keyframe-selection, as MOLA
//! `KeyframePointCloudMap`): the nearest by a translation + rotation metric, plus
//! "diverse" slots that prefer a different relative heading.

use serde::{Deserialize, Serialize};

use kfmap_geometry::KeyframeId;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::options::{InvalidOption, ensure};

/// Most keyframes one query searches: an active set, or the keyframes around a pose.
pub const MAX_KEYFRAMES: usize = 64;

/// Keyframes nearest a place by position that the tracker's explained share searches
/// by default (`explained-keyframes`): the map around the place whichever way its
/// keyframes faced. A tile cut checks that its halo holds them (the halo check).
pub const SURROUNDINGS: usize = 8;

/// Options of active-set selection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct SelectionOptions {
    /// Keyframes in the active set (at most).
    pub max_search_keyframes: usize,
    /// Of those, slots chosen for heading diversity (< max_search_keyframes).
    pub num_diverse_keyframes: usize,
    /// Metres of translation one radian of rotation counts as, m/rad.
    pub rotation_distance_weight: f64,
}

impl Default for SelectionOptions {
    fn default() -> Self {
        Self {
            max_search_keyframes: 3,
            num_diverse_keyframes: 1,
            rotation_distance_weight: 2.0,
        }
    }
}

impl SelectionOptions {
    /// The `count` keyframes nearest a pose by position, whichever way they face (no
    /// diverse slot, no weight on rotation): the surroundings of a place.
    pub const fn by_position(count: usize) -> Self {
        Self {
            max_search_keyframes: count,
            num_diverse_keyframes: 0,
            rotation_distance_weight: 0.0,
        }
    }

    /// Checks every option; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let m = self.max_search_keyframes;
        ensure(
            (1..=MAX_KEYFRAMES).contains(&m),
            "max-search-keyframes",
            m,
            &format!("an integer in [1, {MAX_KEYFRAMES}]"),
        )?;
        let d = self.num_diverse_keyframes;
        ensure(
            d < m,
            "num-diverse-keyframes",
            d,
            &format!("an integer below max-search-keyframes = {m}"),
        )?;
        let w = self.rotation_distance_weight;
        ensure(
            w.is_finite() && w >= 0.0,
            "rotation-distance-weight",
            w,
            "a finite weight >= 0 m/rad",
        )
    }
}

/// One keyframe's distance to the query pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// The keyframe.
    pub id: KeyframeId,
    /// `|t(T_kf^-1 T_q)|`, metres.
    pub dist: f64,
    /// `|Log(R(T_kf^-1 T_q))|`, radians.
    pub angle: f64,
    /// `dist + rotation_distance_weight * angle`.
    pub metric: f64,
}

/// Every keyframe ranked by metric, ascending; ties by id.
pub fn rank(
    keyframes: &[(KeyframeId, Pose)],
    query: &Pose,
    options: &SelectionOptions,
) -> Vec<Candidate> {
    let mut ranked: Vec<Candidate> = keyframes
        .iter()
        .map(|(id, pose)| {
            let rel = pose.inverse() * query;
            let (dist, angle) = (rel.translation.vector.norm(), rel.rotation.angle());
            Candidate {
                id: *id,
                dist,
                angle,
                metric: dist + options.rotation_distance_weight * angle,
            }
        })
        .collect();
    ranked.sort_by(|a, b| a.metric.total_cmp(&b.metric).then(a.id.cmp(&b.id)));
    ranked
}

/// The active keyframes for `query`, in selection order: primary slots by metric, then
/// each diverse slot taking, among unselected keyframes within `max(3 * farthest
/// primary distance, 1 m)`, the one whose relative heading differs most from every
/// selected keyframe's (the first in metric order wins ties), or the next in metric
/// order when none is that near: the set never reaches across the site, so a tile
/// whose halo holds the nearest keyframes answers as the whole map does.
pub fn select_active(
    keyframes: &[(KeyframeId, Pose)],
    query: &Pose,
    options: &SelectionOptions,
) -> Vec<KeyframeId> {
    let ranked = rank(keyframes, query, options);
    let total = options.max_search_keyframes.min(ranked.len());
    if total == 0 {
        return Vec::new();
    }
    let diverse = options.num_diverse_keyframes.min(total - 1);
    let mut selected: Vec<Candidate> = ranked[..total - diverse].to_vec();
    let limit = (3.0 * selected.iter().map(|c| c.dist).fold(0.0, f64::max)).max(1.0);
    for _ in 0..diverse {
        let unselected = || {
            ranked
                .iter()
                .filter(|c| !selected.iter().any(|s| s.id == c.id))
        };
        let near: Vec<&Candidate> = unselected().filter(|c| c.dist <= limit).collect();
        let pool = if near.is_empty() {
            unselected().take(1).collect()
        } else {
            near
        };
        let spread = |c: &Candidate| {
            selected
                .iter()
                .map(|s| (c.angle - s.angle).abs())
                .fold(f64::INFINITY, f64::min)
        };
        // Strictly greater keeps the first in metric order on ties.
        let Some(best) = pool
            .into_iter()
            .fold(None::<&Candidate>, |best, c| match best {
                Some(b) if spread(c) <= spread(b) => Some(b),
                _ => Some(c),
            })
        else {
            break;
        };
        selected.push(*best);
    }
    selected.into_iter().map(|c| c.id).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn pose(x: f64, y: f64, yaw: f64) -> Pose {
        Pose::new(Vector3::new(x, y, 0.0), Vector3::new(0.0, 0.0, yaw))
    }

    #[test]
    fn primary_slots_follow_the_metric_with_ties_by_id() {
        let options = SelectionOptions {
            max_search_keyframes: 3,
            num_diverse_keyframes: 0,
            ..SelectionOptions::default()
        };
        // Metric = dist + 2 * angle. 7 and 3 tie at 1.0 (id 3 first); 5 is at 0.5.
        let kfs = vec![
            (7, pose(1.0, 0.0, 0.0)),
            (3, pose(0.0, -1.0, 0.0)),
            (5, pose(0.5, 0.0, 0.0)),
            (9, pose(0.2, 0.0, 0.5)),
        ];
        assert_eq!(
            select_active(&kfs, &Pose::identity(), &options),
            vec![5, 3, 7]
        );
        let ranked = rank(&kfs, &Pose::identity(), &options);
        assert_eq!(ranked[3].id, 9);
        assert!((ranked[3].metric - 1.2).abs() < 1e-12);
    }

    #[test]
    fn diverse_slot_prefers_a_different_heading() {
        let options = SelectionOptions::default(); // 3 slots, 1 diverse
        // Two close keyframes facing like the query, a close one turned 90 deg, a
        // slightly closer (by metric) one turned 10 deg.
        let kfs = vec![
            (1, pose(0.1, 0.0, 0.0)),
            (2, pose(0.2, 0.0, 0.0)),
            (3, pose(0.5, 0.0, 0.17)),
            (4, pose(0.6, 0.0, 1.57)),
        ];
        assert_eq!(
            select_active(&kfs, &Pose::identity(), &options),
            vec![1, 2, 4]
        );
        let plain = SelectionOptions {
            num_diverse_keyframes: 0,
            ..options
        };
        assert_eq!(
            select_active(&kfs, &Pose::identity(), &plain),
            vec![1, 2, 3]
        );
    }

    #[test]
    fn diverse_slot_falls_back_to_the_next_nearest_when_none_is_near() {
        let options = SelectionOptions {
            max_search_keyframes: 2,
            num_diverse_keyframes: 1,
            ..SelectionOptions::default()
        };
        // Primary: keyframe 1 at 0.1 m, so the limit is 1 m; every other one is farther.
        let kfs = vec![
            (1, pose(0.1, 0.0, 0.0)),
            (2, pose(5.0, 0.0, 0.0)),
            (3, pose(9.0, 0.0, 1.0)),
        ];
        assert_eq!(select_active(&kfs, &Pose::identity(), &options), vec![1, 2]);
        // With a near candidate present it wins even with less heading difference.
        let kfs = vec![
            (1, pose(0.1, 0.0, 0.0)),
            (2, pose(0.9, 0.0, 0.2)),
            (3, pose(9.0, 0.0, 1.0)),
        ];
        assert_eq!(select_active(&kfs, &Pose::identity(), &options), vec![1, 2]);
    }

    #[test]
    fn small_maps_and_validation() {
        let options = SelectionOptions::default();
        assert!(select_active(&[], &Pose::identity(), &options).is_empty());
        assert_eq!(
            select_active(&[(4, pose(3.0, 0.0, 0.0))], &Pose::identity(), &options),
            vec![4]
        );
        let bad = SelectionOptions {
            num_diverse_keyframes: 3,
            ..options
        };
        assert_eq!(bad.validate().unwrap_err().option, "num-diverse-keyframes");
    }
}
