//! Relocalization over a tile set, in three phases that run the steps of one search
//! over the merged map (docs/DESIGN.md#notes-tiles). *Places*: every tile searches its
//! core and answers its places unverified; the client keeps the best `candidates` of
//! them all, as one search keeps its best ([`choose_places`]). *Scores*: each tile
//! holding chosen places settles and scores them ([`best_scored`]). *Finish*: the tile
//! of the best score runs the final registration, and the client judges the verdict as
//! one server would ([`finish`]): `found` only if that place fits; another place
//! farther than `distinct-m` / `distinct-deg` from it is a runner-up, and a runner-up
//! within `ambiguity-margin` makes the answer `ambiguous`.

use kfmap_geometry::geometry::{Pose, rotation_distance, translation_distance};
use kfmap_map::place::{RelocalizeParams, RelocalizeStatus, another_place};
use kfmap_map::tiles::{PlaceRanking, TileGeometry, tile_id};
use kfmap_protocol::remote::{decode_answer, encode_answer};
use kfmap_protocol::{
    PLACES_FROM_RELIEF, ResponseHeader, StatusCode, WirePairing, WirePlace, place_from_wire,
    place_to_wire, pose_from_wire,
};

use kfmap_client::{ClientError, RemoteError};

/// What the first phase decided.
#[derive(Debug, PartialEq)]
pub(crate) enum Choice {
    /// The answer as it stands (a refusal, or no place proposed anywhere).
    Answer(Vec<u8>),
    /// The places to score: per tile (its index in the answers given), the ranks' bits,
    /// and every chosen (tile index, rank) in the order one search would rank them.
    Score {
        chosen: Vec<(usize, u64)>,
        order: Vec<(usize, usize)>,
        /// The slowest tile's search, microseconds.
        searched_us: f64,
    },
}

/// Decodes an answer frame; an error names the tile and the phase.
fn decoded(
    tile: &str,
    what: &str,
    frame: &[u8],
) -> Result<(ResponseHeader, Vec<WirePlace>), ClientError> {
    let (header, slots) = decode_answer(frame)
        .map_err(|e| RemoteError::BadAnswer(format!("tile {tile}'s {what}: {e}")))?;
    Ok((
        header,
        slots.into_iter().map(WirePlace::from_slot).collect(),
    ))
}

/// Rounding of a place's f32 wire pose, metres and degrees, well above f32's at a
/// site's coordinates and far below a voxel.
const WIRE_SLACK_M: f64 = 1e-3;
/// See [`WIRE_SLACK_M`].
const WIRE_SLACK_DEG: f64 = 1e-3;

/// A proposed place of the first phase: (hit ratio, tile id, answer index, rank, pose).
type Proposed<'a> = (f64, &'a str, usize, usize, Pose);

/// Ranks every tile's proposed places (tile id, `FLAG_PLACES_ONLY` answer frame) and
/// keeps as many as one search verifies (the largest `detail` any tile reported), best
/// first, ties by tile id and rank so every client chooses alike. The keeping is one
/// search's: a place within the separation of a better one is the same place (tiles'
/// search regions overlap, so neighbours propose the same lattice placements), and a
/// place below `keep-ratio` of the best hit ratio is not kept (the server defaults of
/// `[relocalize.search]`). A tile's relief places ([`PLACES_FROM_RELIEF`]) count only
/// when no tile proposed from structure: one search of the whole map falls back to
/// relief only when its structure search found nothing.
/// `cores` (the geometry of a tile set whose tiles' searches overlap, else `None`)
/// names the tile whose core holds a place: a neighbour's copy of a place in an
/// answering tile's core is left out, the owner's kept (it holds the keyframes nearest
/// the place, as the halo check verifies). Tiles that share the search out
/// (`SearchShare`) propose each translation once; then `cores` is `None`.
pub(crate) fn choose_places(
    answers: &[(String, Vec<u8>)],
    cores: Option<&TileGeometry>,
    ranking: &PlaceRanking,
) -> Result<Choice, ClientError> {
    let mut structure: Vec<Proposed> = Vec::new();
    let mut relief: Vec<Proposed> = Vec::new();
    let mut keep = 0;
    let mut searched_us: f64 = 0.0;
    for (at, (tile, frame)) in answers.iter().enumerate() {
        let (header, slots) = decoded(tile, "proposed places", frame)?;
        // A ranking without a tile is not the one search it stands for.
        if StatusCode::from_code(header.status) != StatusCode::Ok {
            return Ok(Choice::Answer(frame.clone()));
        }
        if slots.len() != header.candidates as usize {
            return Err(RemoteError::BadAnswer(format!(
                "tile {tile} proposed {} places but sent {}",
                header.candidates,
                slots.len()
            ))
            .into());
        }
        keep = keep.max(header.detail.min(64) as usize);
        searched_us = searched_us.max(header.server_us);
        let into = if header.reasons & PLACES_FROM_RELIEF != 0 {
            &mut relief
        } else {
            &mut structure
        };
        for (rank, slot) in slots.into_iter().enumerate() {
            let pose = place_from_wire(&slot).ok_or_else(|| {
                RemoteError::BadAnswer(format!("tile {tile} proposed an invalid pose"))
            })?;
            into.push((slot.score, tile, at, rank, pose));
        }
    }
    let mut proposed = if structure.is_empty() {
        relief
    } else {
        structure
    };
    if let Some(cores) = cores {
        let answered = |id: &str| answers.iter().any(|(tile, _)| tile == id);
        proposed.retain(|(_, tile, _, _, pose)| {
            let t = pose.translation.vector;
            let (col, row) = cores.tile_of(t.x, t.y);
            let owner = tile_id(col, row);
            owner == *tile || !answered(&owner)
        });
    }
    proposed.sort_by(|a, b| {
        b.0.total_cmp(&a.0)
            .then_with(|| a.1.cmp(b.1))
            .then(a.3.cmp(&b.3))
    });
    let floor = proposed.first().map_or(0.0, |p| p.0) * ranking.keep_ratio;
    // Lattice placements lie exact multiples of the voxel apart, often exactly the
    // separation (2 m: distinct to the search); the wire's f32 must not make them one.
    let same_place = |a: &Pose, b: &Pose| {
        translation_distance(a, b) < ranking.separation_m - WIRE_SLACK_M
            && rotation_distance(a, b).to_degrees() < ranking.separation_deg - WIRE_SLACK_DEG
    };
    let mut places: Vec<Proposed> = Vec::with_capacity(keep);
    for place in proposed {
        if places.len() == keep || place.0 < floor {
            break;
        }
        if !places.iter().any(|kept| same_place(&kept.4, &place.4)) {
            places.push(place);
        }
    }
    if places.is_empty() {
        let (mut header, _) = decode_answer(&answers[0].1).expect("decoded above");
        header.relocalization = RelocalizeStatus::NotFound as u32;
        header.candidates = 0;
        header.place_scores = [0.0; 2];
        header.detail = 0;
        header.server_us = searched_us;
        return Ok(Choice::Answer(encode_answer(&header, &[])));
    }
    let order: Vec<(usize, usize)> = places.iter().map(|p| (p.2, p.3)).collect();
    let mut chosen: Vec<(usize, u64)> = Vec::new();
    for &(at, rank) in &order {
        match chosen.iter_mut().find(|(tile, _)| *tile == at) {
            Some((_, ranks)) => *ranks |= 1 << rank,
            None => chosen.push((at, 1 << rank)),
        }
    }
    Ok(Choice::Score {
        chosen,
        order,
        searched_us,
    })
}

/// Every scored place of the second phase, and what its answers add up to.
#[derive(Debug, PartialEq)]
pub(crate) struct Ranked {
    /// The best score's (tile id, rank): the first of equal scores in the search's
    /// order; `None` when no place settled.
    pub best: Option<(String, usize)>,
    /// Every settled place (pose, score), the best included.
    pub places: Vec<(String, usize, Pose, f64)>,
    /// Places chosen, registrations run, the slowest tile's time (microseconds).
    pub candidates: u32,
    pub registrations: u32,
    pub scored_us: f64,
}

/// Reads the `FLAG_SCORE_CHOSEN` answers (tile id, frame) of the places chosen in
/// `order` (tile id, rank) and finds the best score as one server would: places in the
/// search's order, the first of equal scores. A refusal is returned as the answer.
pub(crate) fn best_scored(
    order: &[(String, usize)],
    answers: &[(String, Vec<u8>)],
) -> Result<Result<Ranked, Vec<u8>>, ClientError> {
    let mut ranked = Ranked {
        best: None,
        places: Vec::new(),
        candidates: 0,
        registrations: 0,
        scored_us: 0.0,
    };
    for (tile, frame) in answers {
        let (header, slots) = decoded(tile, "scored places", frame)?;
        if StatusCode::from_code(header.status) != StatusCode::Ok {
            return Ok(Err(frame.clone()));
        }
        ranked.candidates += header.candidates;
        ranked.registrations += header.registrations;
        ranked.scored_us = ranked.scored_us.max(header.server_us);
        for slot in slots {
            let pose = place_from_wire(&slot).ok_or_else(|| {
                RemoteError::BadAnswer(format!("tile {tile} scored an invalid pose"))
            })?;
            ranked
                .places
                .push((tile.clone(), slot.rank as usize, pose, slot.score));
        }
    }
    let position = |tile: &str, rank: usize| {
        order
            .iter()
            .position(|(t, r)| t == tile && *r == rank)
            .unwrap_or(usize::MAX)
    };
    ranked
        .places
        .sort_by_key(|(tile, rank, _, _)| position(tile, *rank));
    if ranked
        .places
        .iter()
        .any(|(t, r, _, _)| position(t, *r) == usize::MAX)
    {
        return Err(
            RemoteError::BadAnswer("a tile scored a place that was not chosen".into()).into(),
        );
    }
    // The first of equal best scores, as a stable sort by score keeps it.
    let mut best: Option<&(String, usize, Pose, f64)> = None;
    for place in &ranked.places {
        if best.is_none_or(|b| place.3 > b.3) {
            best = Some(place);
        }
    }
    ranked.best = best.map(|(t, r, _, _)| (t.clone(), *r));
    Ok(Ok(ranked))
}

/// The answer when no chosen place settled: not found, as on one server.
pub(crate) fn nothing_settled(ranked: &Ranked, searched_us: f64) -> Vec<u8> {
    let header = ResponseHeader {
        relocalization: RelocalizeStatus::NotFound as u32,
        candidates: ranked.candidates,
        registrations: ranked.registrations,
        server_us: searched_us + ranked.scored_us,
        ..Default::default()
    };
    encode_answer(&header, &[])
}

/// The final answer from the best place's `FLAG_FINISH_CHOSEN` answer frame: its
/// registration and fit, the runner-up among every other scored place distinct from
/// where it settled, the verdict, the phases' counts and times, and every tile's scored
/// places in the pairings' slots (settled pose, score, rank in the search's order), as
/// one server answers them: a tracker keeps those near the best as hypotheses, a
/// look-alike in another tile included.
pub(crate) fn finish(
    frame: &[u8],
    ranked: &Ranked,
    searched_us: f64,
    ranking: &PlaceRanking,
) -> Result<Vec<u8>, ClientError> {
    let (mut header, _own_places) = decode_answer(frame)
        .map_err(|e| RemoteError::BadAnswer(format!("the best place's final answer: {e}")))?;
    if StatusCode::from_code(header.status) != StatusCode::Ok {
        return Ok(frame.to_vec());
    }
    let params = ranking.applied_to(RelocalizeParams::default());
    header.candidates = ranked.candidates;
    header.registrations += ranked.registrations;
    header.server_us += searched_us + ranked.scored_us;
    let fits = header.relocalization != RelocalizeStatus::NotFound as u32;
    if let (true, Some(settled), Some(best)) = (fits, pose_from_wire(&header.pose), &ranked.best) {
        let runner_up = ranked
            .places
            .iter()
            .filter(|(t, r, pose, _)| {
                (t, r) != (&best.0, &best.1) && another_place(pose, &settled, &params)
            })
            .map(|(_, _, _, score)| *score)
            .fold(0.0, f64::max);
        header.place_scores[1] = runner_up;
        let close = runner_up + params.ambiguity_margin >= header.place_scores[0];
        header.relocalization = if close {
            RelocalizeStatus::Ambiguous
        } else {
            RelocalizeStatus::Found
        } as u32;
    }
    let places: Vec<WirePairing> = ranked
        .places
        .iter()
        .enumerate()
        .map(|(rank, (_, _, pose, score))| place_to_wire(pose, *score, rank).to_slot())
        .collect();
    Ok(encode_answer(&header, &places))
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_protocol::pose_to_wire;
    use nalgebra::{Translation3, UnitQuaternion};

    fn at(x: f64, yaw_deg: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_deg.to_radians()),
        )
    }

    /// An answer frame carrying `places` (pose, score, rank).
    fn places(places: &[(Pose, f64, usize)], candidates: u32, detail: u64) -> Vec<u8> {
        let mut h = ResponseHeader::refusal(7, StatusCode::Ok, "");
        h.candidates = candidates;
        h.detail = detail;
        h.registrations = 2 * candidates;
        h.server_us = 100.0 * places.len() as f64;
        let slots: Vec<_> = places
            .iter()
            .map(|(pose, score, rank)| place_to_wire(pose, *score, *rank).to_slot())
            .collect();
        encode_answer(&h, &slots)
    }

    fn named(frames: Vec<Vec<u8>>) -> Vec<(String, Vec<u8>)> {
        frames
            .into_iter()
            .enumerate()
            .map(|(i, f)| (format!("t{i}"), f))
            .collect()
    }

    /// A `FLAG_PLACES_ONLY` answer with places of these hit ratios, each at its own
    /// spot (x = 100 times its hit ratio: distinct ratios are distinct places).
    fn proposed(hits: &[f64], detail: u64) -> Vec<u8> {
        let list: Vec<_> = hits
            .iter()
            .enumerate()
            .map(|(r, &h)| (at(100.0 * h, 0.0), h, r))
            .collect();
        places(&list, hits.len() as u32, detail)
    }

    #[test]
    fn places_are_kept_as_one_search_keeps_them_across_tiles() {
        // Two tiles propose the same lattice placement (their regions overlap): one
        // place, the better hit ratio's; a placement within the separation (2 m, 20
        // deg) of a better one is the same place; turned 30 deg it is another.
        let near = |x: f64, yaw: f64, hits: f64, rank: usize| (at(x, yaw), hits, rank);
        let answers = named(vec![
            places(&[near(0.0, 0.0, 0.9, 0), near(50.0, 0.0, 0.8, 1)], 2, 6),
            places(&[near(0.0, 0.0, 0.85, 0), near(1.5, 10.0, 0.84, 1)], 2, 6),
            places(&[near(0.0, 30.0, 0.83, 0), near(80.0, 0.0, 0.6, 1)], 2, 6),
        ]);
        // 0.6 is below keep-ratio (0.7) of the best 0.9.
        assert_eq!(chosen_order(&answers), vec![(0, 0), (2, 0), (0, 1)]);
        // Exactly the separation apart (lattice placements 2 m apart in z, through the
        // wire's f32 at a site's coordinates): two places, as the search keeps them.
        let mut up = at(1234.567, 0.0);
        let mut below = up;
        up.translation.vector.z = 3.0;
        below.translation.vector.z = 1.0;
        let answers = named(vec![places(&[(below, 0.9, 0), (up, 0.89, 1)], 2, 6)]);
        assert_eq!(chosen_order(&answers), vec![(0, 0), (0, 1)]);
        // With cores of 10 m, x0_y0 owns x in [0, 10): its copy of the place at the
        // origin stands, whatever a neighbour's hit ratio; a place in a core no tile
        // answered for (x1_y0) stays with whoever proposed it.
        let cores = TileGeometry {
            tile_size: 10.0,
            halo: 5.0,
        };
        let answers = vec![
            (
                "x-1_y0".to_string(),
                places(&[near(0.0, 0.0, 0.9, 0)], 1, 6),
            ),
            (
                "x0_y0".to_string(),
                places(&[near(0.0, 0.0, 0.85, 0)], 1, 6),
            ),
            (
                "x0_y-1".to_string(),
                places(&[near(12.0, 90.0, 0.8, 0)], 1, 6),
            ),
        ];
        let Choice::Score { order, .. } =
            choose_places(&answers, Some(&cores), &PlaceRanking::default()).unwrap()
        else {
            panic!("places to score expected");
        };
        assert_eq!(order, vec![(1, 0), (2, 0)]);
    }

    /// A tile's answer whose places come from its relief search.
    fn from_relief(hits: &[f64], detail: u64) -> Vec<u8> {
        let frame = proposed(hits, detail);
        let (mut h, slots) = decode_answer(&frame).unwrap();
        h.reasons = PLACES_FROM_RELIEF;
        encode_answer(&h, &slots)
    }

    fn chosen_order(answers: &[(String, Vec<u8>)]) -> Vec<(usize, usize)> {
        match choose_places(answers, None, &PlaceRanking::default()).unwrap() {
            Choice::Score { order, .. } => order,
            Choice::Answer(_) => panic!("places to score expected"),
        }
    }

    #[test]
    fn relief_places_stand_only_when_no_tile_proposed_from_structure() {
        // One search of the merged map proposes from structure when any tile can: the
        // tiles that fell back to relief (their structure search was empty) are left
        // out, however well their relief places hit.
        let answers = named(vec![
            from_relief(&[0.95, 0.9], 3),
            proposed(&[0.6], 3),
            from_relief(&[0.7], 3),
        ]);
        assert_eq!(chosen_order(&answers), vec![(1, 0)]);
        // No tile proposed from structure: every tile searched relief, as the merged
        // map's fallback does, and their places rank together.
        let answers = named(vec![from_relief(&[0.55, 0.5], 3), from_relief(&[0.7], 3)]);
        assert_eq!(chosen_order(&answers), vec![(1, 0), (0, 0), (0, 1)]);
    }

    #[test]
    fn the_best_places_of_every_tile_are_chosen_as_one_search_keeps_its_best() {
        // Brute force over every (tile, rank): the 3 best hit ratios overall.
        let hits = [vec![0.9, 0.5, 0.4], vec![0.8, 0.7], vec![0.3], vec![]];
        let answers = named(hits.iter().map(|h| proposed(h, 3)).collect());
        let Choice::Score {
            chosen,
            order,
            searched_us,
        } = choose_places(&answers, None, &PlaceRanking::default()).unwrap()
        else {
            panic!("places to score expected");
        };
        let mut all: Vec<(f64, usize, usize)> = hits
            .iter()
            .enumerate()
            .flat_map(|(t, h)| h.iter().enumerate().map(move |(r, &x)| (x, t, r)))
            .collect();
        all.sort_by(|a, b| b.0.total_cmp(&a.0));
        let expected: Vec<(usize, usize)> = all[..3].iter().map(|&(_, t, r)| (t, r)).collect();
        assert_eq!(order, expected);
        assert_eq!(chosen, vec![(0, 0b1), (1, 0b11)]);
        assert_eq!(searched_us, 300.0);
        // No place anywhere: not found at once, nothing to score.
        let Choice::Answer(frame) = choose_places(
            &named(vec![proposed(&[], 5)]),
            None,
            &PlaceRanking::default(),
        )
        .unwrap() else {
            panic!("an answer expected");
        };
        let h = decode_answer(&frame).unwrap().0;
        assert_eq!(h.relocalization, RelocalizeStatus::NotFound as u32);
        assert_eq!(h.candidates, 0);
        // A tile's refusal is the answer: a ranking without it is not one search.
        let refused = encode_answer(&ResponseHeader::refusal(7, StatusCode::Busy, "busy"), &[]);
        let answers = named(vec![proposed(&[0.9], 5), refused.clone()]);
        assert_eq!(
            choose_places(&answers, None, &PlaceRanking::default()).unwrap(),
            Choice::Answer(refused)
        );
        // A frame whose places disagree with its count is an error, not a guess.
        let mut broken = proposed(&[0.9, 0.8], 5);
        broken.truncate(broken.len() - 56);
        assert!(choose_places(&named(vec![broken]), None, &PlaceRanking::default()).is_err());
    }

    /// The final answer of a place at `settled` with `score`, as the finishing tile
    /// sends it (found when it fits, no runner-up).
    fn finished(settled: &Pose, score: f64, fits: bool) -> Vec<u8> {
        let mut h = ResponseHeader::refusal(7, StatusCode::Ok, "");
        h.relocalization = if fits {
            RelocalizeStatus::Found
        } else {
            RelocalizeStatus::NotFound
        } as u32;
        h.place_scores = [score, 0.0];
        h.registrations = 2;
        h.candidates = 1;
        h.server_us = 50.0;
        h.pose = pose_to_wire(settled);
        encode_answer(&h, &[])
    }

    /// Scores over two tiles: t0 ranks 0, 1; t1 rank 0; in the search's order t0/0,
    /// t1/0, t0/1.
    fn ranked(scores: [(Pose, f64); 3]) -> Ranked {
        let order = vec![("t0".into(), 0), ("t1".into(), 0), ("t0".into(), 1)];
        let [a, b, c] = scores;
        let answers = named(vec![
            places(&[(a.0, a.1, 0), (c.0, c.1, 1)], 2, 0),
            places(&[(b.0, b.1, 0)], 1, 0),
        ]);
        best_scored(&order, &answers).unwrap().unwrap()
    }

    #[test]
    fn the_best_score_is_finished_and_judged_against_every_distinct_place() {
        // The best score wins; equal scores go to the first in the search's order.
        let r = ranked([
            (at(0.0, 0.0), 0.6),
            (at(50.0, 0.0), 0.8),
            (at(90.0, 0.0), 0.8),
        ]);
        assert_eq!(r.best, Some(("t1".into(), 0)));
        assert_eq!((r.candidates, r.registrations, r.scored_us), (3, 6, 200.0));
        // A place far away within the margin: ambiguous (0.8 vs 0.8).
        let h = |frame: Vec<u8>| decode_answer(&frame).unwrap().0;
        let defaults = PlaceRanking::default();
        let out = h(finish(&finished(&at(50.1, 1.0), 0.8, true), &r, 1000.0, &defaults).unwrap());
        assert_eq!(out.relocalization, RelocalizeStatus::Ambiguous as u32);
        assert_eq!(out.place_scores, [0.8, 0.8]);
        assert_eq!((out.candidates, out.registrations), (3, 8));
        assert_eq!(out.server_us, 1000.0 + 200.0 + 50.0);
        // Every tile's scored places travel with the verdict, in the search's order, as
        // one server sends its scored places; the finishing tile's own (none here) do not.
        let frame = finish(&finished(&at(50.1, 1.0), 0.8, true), &r, 1000.0, &defaults).unwrap();
        let sent: Vec<(Pose, f64, u64)> = decode_answer(&frame)
            .unwrap()
            .1
            .into_iter()
            .map(|slot| {
                let place = WirePlace::from_slot(slot);
                (place_from_wire(&place).unwrap(), place.score, place.rank)
            })
            .collect();
        let expected = [
            (at(0.0, 0.0), 0.6),
            (at(50.0, 0.0), 0.8),
            (at(90.0, 0.0), 0.8),
        ];
        assert_eq!(sent.len(), expected.len());
        for (k, ((pose, score, rank), (want_pose, want_score))) in
            sent.iter().zip(&expected).enumerate()
        {
            assert!(translation_distance(pose, want_pose) < 1e-9, "place {k}");
            assert_eq!((*score, *rank as usize), (*want_score, k));
        }
        // The same place settled from two proposals (0.3 m apart) is no runner-up; the
        // runner-up is then the best distinct one (0.6), outside the margin: found.
        let r = ranked([
            (at(0.0, 0.0), 0.6),
            (at(50.0, 0.0), 0.8),
            (at(50.3, 2.0), 0.79),
        ]);
        // The best settled at (50, 0) with 0.8, fitting or not, judged with `ranking`.
        let judged = |r: &Ranked, fits: bool, ranking: &PlaceRanking| {
            h(finish(&finished(&at(50.0, 0.0), 0.8, fits), r, 0.0, ranking).unwrap())
        };
        let out = judged(&r, true, &defaults);
        assert_eq!(out.relocalization, RelocalizeStatus::Found as u32);
        assert_eq!(out.place_scores, [0.8, 0.6]);
        // The servers' own settings, as the gateway publishes them, decide: with an
        // ambiguity margin of 0.25 the same runner-up (0.6 against 0.8) is too close.
        let wide = PlaceRanking {
            ambiguity_margin: 0.25,
            ..PlaceRanking::default()
        };
        assert_eq!(
            judged(&r, true, &wide).relocalization,
            RelocalizeStatus::Ambiguous as u32
        );
        // Turned more than distinct-deg, it is another place: ambiguous.
        let r = ranked([
            (at(0.0, 0.0), 0.1),
            (at(50.0, 0.0), 0.8),
            (at(50.0, 10.0), 0.79),
        ]);
        assert_eq!(
            judged(&r, true, &defaults).relocalization,
            RelocalizeStatus::Ambiguous as u32
        );
        // Unless the servers count 15 deg as the same place (distinct-deg 15).
        let lenient = PlaceRanking {
            distinct_deg: 15.0,
            ..PlaceRanking::default()
        };
        assert_eq!(
            judged(&r, true, &lenient).relocalization,
            RelocalizeStatus::Found as u32
        );
        // The best place does not fit: not found, whatever the others scored.
        assert_eq!(
            judged(&r, false, &defaults).relocalization,
            RelocalizeStatus::NotFound as u32
        );
        // A refusal of a phase is the answer.
        let refused = encode_answer(&ResponseHeader::refusal(7, StatusCode::Busy, "busy"), &[]);
        assert_eq!(finish(&refused, &r, 0.0, &defaults).unwrap(), refused);
        let order = vec![("t0".to_string(), 0)];
        assert_eq!(
            best_scored(&order, &named(vec![refused.clone()])).unwrap(),
            Err(refused)
        );
        // A place nobody chose is an error, not a guess.
        let stray = named(vec![places(&[(at(0.0, 0.0), 0.5, 3)], 1, 0)]);
        assert!(best_scored(&order, &stray).is_err());
        // Nothing settled: not found, the counts kept.
        let none = best_scored(&order, &named(vec![places(&[], 1, 0)]))
            .unwrap()
            .unwrap();
        assert_eq!(none.best, None);
        let out = h(nothing_settled(&none, 10.0));
        assert_eq!(out.relocalization, RelocalizeStatus::NotFound as u32);
        assert_eq!((out.candidates, out.registrations), (1, 2));
    }
}
