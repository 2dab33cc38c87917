//! Relocalization over a tile set: every tile searches its own map at once, and the
//! answers are ranked as one search over the merged map ranks its places
//! (docs/DESIGN.md#notes-tiles). The best-scoring place wins (and is `found` only if it
//! fits, as its tile's final registration found); another tile's
//! place farther than `distinct-m` / `distinct-deg` from it is a runner-up (the same
//! place seen from two tiles' overlapping halos is not), and a runner-up within
//! `ambiguity-margin` of the best makes the answer `ambiguous`, as on one server.

use kfmap_protocol::remote::{decode_answer, encode_answer};
use kfmap_protocol::{ResponseHeader, StatusCode, pose_from_wire};
use kfmap_shared::geometry::{rotation_distance, translation_distance};
use kfmap_shared::place::{RelocalizeParams, RelocalizeStatus};

use crate::ClientError;

/// One tile's decoded answer.
struct TileAnswer {
    header: ResponseHeader,
    pairings: Vec<kfmap_protocol::WirePairing>,
}

impl TileAnswer {
    fn status(&self) -> Option<RelocalizeStatus> {
        RelocalizeStatus::from_code(self.header.relocalization)
    }

    /// Found or ambiguous: its place fits the scan.
    fn fits(&self) -> bool {
        matches!(
            self.status(),
            Some(RelocalizeStatus::Found | RelocalizeStatus::Ambiguous)
        )
    }

    fn score(&self) -> f64 {
        self.header.place_scores[0]
    }
}

/// Merges the answer frames of every tile (tile id, frame) into one answer frame.
pub(crate) fn merge_relocalizations(answers: &[(String, Vec<u8>)]) -> Result<Vec<u8>, ClientError> {
    let mut decoded = Vec::with_capacity(answers.len());
    for (tile, frame) in answers {
        let (header, pairings) = decode_answer(frame).map_err(|e| {
            ClientError::Remote(format!("tile {tile}'s relocalization answer: {e}"))
        })?;
        decoded.push(TileAnswer { header, pairings });
    }
    // Refusals (a bad scan is refused by every tile alike) are answered as they came.
    let (ok, refused): (Vec<_>, Vec<_>) = decoded
        .into_iter()
        .partition(|a| StatusCode::from_code(a.header.status) == StatusCode::Ok);
    let Some(best) = ok
        .iter()
        .enumerate()
        .max_by(|(_, a), (_, b)| a.score().total_cmp(&b.score()))
        .map(|(i, _)| i)
    else {
        let first = &refused[0];
        return Ok(encode_answer(&first.header, &first.pairings));
    };
    let params = RelocalizeParams::default();
    let winner = &ok[best];
    let mut header = winner.header;
    let best_pose = pose_from_wire(&header.pose);
    let distinct = |a: &TileAnswer| match (best_pose, pose_from_wire(&a.header.pose)) {
        (Some(p), Some(q)) => {
            translation_distance(&p, &q) > params.distinct_m
                || rotation_distance(&p, &q).to_degrees() > params.distinct_deg
        }
        _ => true,
    };
    let others = ok
        .iter()
        .enumerate()
        .filter(|&(i, a)| i != best && a.score() > 0.0 && distinct(a))
        .map(|(_, a)| a.score())
        .fold(0.0, f64::max);
    header.place_scores[1] = header.place_scores[1].max(others);
    header.candidates = ok.iter().map(|a| a.header.candidates).sum();
    // The tiles searched in parallel: the answer took as long as the slowest.
    header.server_us = ok.iter().map(|a| a.header.server_us).fold(0.0, f64::max);
    if winner.fits() {
        let close = header.place_scores[1] + params.ambiguity_margin >= header.place_scores[0];
        let status = if close {
            RelocalizeStatus::Ambiguous
        } else {
            RelocalizeStatus::Found
        };
        header.relocalization = status as u32;
    }
    Ok(encode_answer(&header, &winner.pairings))
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_protocol::pose_to_wire;
    use kfmap_shared::geometry::Pose;
    use nalgebra::{Translation3, UnitQuaternion};

    fn answer(status: RelocalizeStatus, score: f64, runner_up: f64, x: f64) -> Vec<u8> {
        let mut h = ResponseHeader::refusal(7, StatusCode::Ok, "");
        h.relocalization = status as u32;
        h.place_scores = [score, runner_up];
        h.candidates = 5;
        h.server_us = 1000.0 * score;
        let pose = Pose::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::identity());
        h.pose = pose_to_wire(&pose);
        encode_answer(&h, &[])
    }

    fn merged(answers: Vec<Vec<u8>>) -> ResponseHeader {
        let named: Vec<(String, Vec<u8>)> = answers
            .into_iter()
            .enumerate()
            .map(|(i, a)| (format!("t{i}"), a))
            .collect();
        decode_answer(&merge_relocalizations(&named).unwrap())
            .unwrap()
            .0
    }

    #[test]
    fn the_best_fitting_place_wins_and_a_distinct_close_second_makes_it_ambiguous() {
        use RelocalizeStatus::*;
        // The same place seen from two tiles' halos: found, not ambiguous.
        let h = merged(vec![
            answer(Found, 0.80, 0.2, 10.0),
            answer(Found, 0.79, 0.1, 10.3),
        ]);
        assert_eq!(h.relocalization, Found as u32);
        assert_eq!(h.place_scores, [0.80, 0.2]);
        assert_eq!(h.candidates, 10);
        assert_eq!(h.server_us, 800.0);
        // Another place elsewhere scoring within the margin: ambiguous.
        let h = merged(vec![
            answer(Found, 0.80, 0.2, 10.0),
            answer(Found, 0.78, 0.1, 60.0),
        ]);
        assert_eq!(h.relocalization, Ambiguous as u32);
        assert_eq!(h.place_scores, [0.80, 0.78]);
        // The best score wins even when its registration does not fit, as in one search.
        let h = merged(vec![
            answer(NotFound, 0.9, 0.0, 60.0),
            answer(Found, 0.6, 0.1, 10.0),
        ]);
        assert_eq!(h.relocalization, NotFound as u32);
        assert_eq!(pose_from_wire(&h.pose).unwrap().translation.x, 60.0);
        // A tile whose own runner-up was close stays ambiguous.
        let h = merged(vec![
            answer(Ambiguous, 0.7, 0.68, 5.0),
            answer(Found, 0.2, 0.0, 90.0),
        ]);
        assert_eq!(h.relocalization, Ambiguous as u32);
        // Nothing fits anywhere: not found.
        let h = merged(vec![
            answer(NotFound, 0.3, 0.0, 1.0),
            answer(NotFound, 0.0, 0.0, 0.0),
        ]);
        assert_eq!(h.relocalization, NotFound as u32);
    }
}
