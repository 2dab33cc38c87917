use std::collections::{BTreeMap, HashSet};

use proptest::prelude::*;

use super::*;

/// Points at the centres of the given unit voxels.
fn cells(voxels: &[[i64; 3]]) -> Vec<[f64; 3]> {
    voxels.iter().map(|v| v.map(|c| c as f64 + 0.5)).collect()
}

/// A block of voxels `[x0, x0 + nx) x [0, ny) x {0}`.
fn block(x0: i64, nx: i64, ny: i64) -> Vec<[f64; 3]> {
    let v: Vec<[i64; 3]> = (x0..x0 + nx)
        .flat_map(|x| (0..ny).map(move |y| [x, y, 0]))
        .collect();
    cells(&v)
}

#[test]
fn threshold_with_keep_the_strongest_fallback() {
    let mut g = CovisibilityGraph::new(CovisOptions::default());
    g.set_keyframe(1, block(0, 5, 1)); // voxels x 0..5
    g.set_keyframe(2, block(0, 3, 1)); // shares 3 with 1
    g.set_keyframe(3, block(2, 30, 1)); // shares 3 with 1, 1 with 2
    // Keyframe 3 shares 3 voxels with 1 and 1 with 2: nothing reaches 15, so only its
    // strongest edge stays.
    assert_eq!(g.ordered_neighbours(3), vec![(1, 3)]);
    let mut h = CovisibilityGraph::new(CovisOptions::default());
    h.set_keyframe(10, block(0, 40, 1));
    h.set_keyframe(11, block(0, 20, 1)); // 20 shared
    h.set_keyframe(12, block(20, 16, 1)); // 16 shared with 10, 0 with 11
    h.set_keyframe(13, block(19, 2, 1)); // 2 with 10, 1 with 11, 1 with 12
    assert_eq!(h.ordered_neighbours(10), vec![(11, 20), (12, 16), (13, 2)]);
    assert_eq!(h.ordered_neighbours(13), vec![(10, 2)]);
    assert_eq!(h.best_covisible(10, 2), vec![11, 12]);
    assert_eq!(h.covisible_by_weight(10, 16), vec![11, 12]);
    assert_eq!(h.covisible_by_weight(10, 1), vec![11, 12, 13]);
    // Spanning tree: 11 and 12 under 10 (their strongest at first connection).
    assert_eq!(
        (h.parent(11), h.parent(12), h.parent(13), h.parent(10)),
        (Some(10), Some(10), Some(10), None)
    );
}

#[test]
fn essential_graph_is_tree_plus_strong_edges() {
    let mut g = CovisibilityGraph::new(CovisOptions {
        essential_min_weight: 100,
        ..CovisOptions::default()
    });
    g.set_keyframe(1, block(0, 200, 1));
    g.set_keyframe(2, block(0, 150, 1)); // 150 with 1
    g.set_keyframe(3, block(100, 120, 1)); // 100 with 1, 50 with 2
    let essential = g.essential_graph();
    // Tree: 2 -> 1, 3 -> 1. Strong: (1,2) 150, (1,3) 100; (2,3) 50 is not essential.
    assert_eq!(
        essential.into_iter().collect::<Vec<_>>(),
        vec![(1, 2), (1, 3)]
    );
    assert_eq!(g.weight(2, 3), 50);
}

#[test]
fn removal_reparents_children_greedily() {
    // Root 1; 2 under 1; 3 and 4 under 2. 3 is strongly covisible with 1; 4 only with 3.
    let mut g = CovisibilityGraph::new(CovisOptions {
        min_weight: 1,
        ..CovisOptions::default()
    });
    g.set_keyframe(1, block(0, 50, 1));
    g.set_keyframe(2, block(0, 100, 1));
    g.set_keyframe(3, block(30, 80, 1)); // 70 with 2, 20 with 1
    g.set_keyframe(4, block(95, 40, 1)); // 5 with 2, 15 with 3
    assert_eq!(
        (g.parent(2), g.parent(3), g.parent(4)),
        (Some(1), Some(2), Some(3))
    );
    g.set_keyframe(5, block(60, 50, 1)); // 40 with 2 (strongest), 50 with 3
    assert_eq!(g.parent(5), Some(3));
    g.remove_keyframe(3);
    // Orphans 4 and 5; candidates start as {2}: 5 (40) beats 4 (5) and joins 2; then 4's
    // strongest candidate edge is 5 (15 shared): it joins 5.
    assert_eq!(g.parent(5), Some(2));
    assert_eq!(g.parent(4), Some(5));
    assert!(g.children(3).is_empty() && g.parent(3).is_none());
}

#[test]
fn a_fallback_edge_survives_an_update_of_its_partner() {
    let mut g = CovisibilityGraph::new(CovisOptions::default());
    g.set_keyframe(1, block(0, 40, 1));
    g.set_keyframe(2, block(37, 10, 1)); // 3 shared with 1, nothing else: its fallback
    g.set_keyframe(3, block(0, 20, 1)); // 20 shared with 1: a thresholded edge
    assert_eq!(g.ordered_neighbours(2), vec![(1, 3)]);
    // Re-setting 1 (e.g. after a pose correction) finds 3 above the threshold; 2 still
    // shares 3 voxels with 1 and with no one else, so its fallback edge must stay.
    g.set_keyframe(1, block(0, 40, 1));
    assert_eq!(g.ordered_neighbours(2), vec![(1, 3)]);
    assert_eq!(g.ordered_neighbours(1), vec![(3, 20), (2, 3)]);
}

#[test]
fn removing_a_fallback_partner_reconnects_to_the_next_strongest() {
    let mut g = CovisibilityGraph::new(CovisOptions::default());
    g.set_keyframe(1, block(0, 40, 1));
    g.set_keyframe(2, block(37, 10, 1)); // 3 shared with 1, 1 with 4 (voxel 46)
    g.set_keyframe(5, block(50, 30, 1));
    g.set_keyframe(4, block(46, 30, 1)); // 26 with 5: 4 needs no fallback
    assert_eq!(g.ordered_neighbours(2), vec![(1, 3)]);
    g.remove_keyframe(1);
    assert_eq!(g.ordered_neighbours(2), vec![(4, 1)]);
    assert_eq!(g.ordered_neighbours(4), vec![(5, 26), (2, 1)]);
}

/// Forest check: following parents from any node ends at a root in < n steps, and
/// parent/children agree.
fn assert_forest(g: &CovisibilityGraph, alive: &HashSet<KeyframeId>) {
    for &id in alive {
        let mut at = id;
        let mut steps = 0;
        while let Some(p) = g.parent(at) {
            assert!(alive.contains(&p), "parent {p} of {at} was removed");
            assert!(g.children(p).contains(&at));
            at = p;
            steps += 1;
            assert!(steps <= alive.len(), "cycle through {id}");
        }
        for c in g.children(id) {
            assert_eq!(g.parent(c), Some(id));
        }
    }
}

#[derive(Debug, Clone)]
enum Op {
    Insert(Vec<[i64; 3]>),
    Move(usize, Vec<[i64; 3]>),
    Remove(usize),
    /// Through a snapshot and back (as a baked map is loaded).
    Reload,
}

/// Up to 40 voxels in a cube of `extent` voxels a side: small cubes make most pairs
/// strong, large ones leave many keyframes with only weak (fallback) partners.
fn voxels(extent: i64) -> impl Strategy<Value = Vec<[i64; 3]>> {
    prop::collection::vec(prop::array::uniform3(0..extent), 1..40)
}

fn op(extent: i64) -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => voxels(extent).prop_map(Op::Insert),
        1 => (any::<usize>(), voxels(extent)).prop_map(|(i, v)| Op::Move(i, v)),
        2 => any::<usize>().prop_map(Op::Remove),
        1 => Just(Op::Reload),
    ]
}

/// The graph of docs/DESIGN.md#covisibility computed from scratch: `a`-`b` is an edge when
/// they share at least `min_weight` voxels, or when one of them has no such partner
/// and the other is its strongest (ties: lower id).
fn brute_force_edges(
    sets: &BTreeMap<KeyframeId, HashSet<[i64; 3]>>,
    min_weight: u32,
) -> BTreeMap<(KeyframeId, KeyframeId), u32> {
    let shared = |a: KeyframeId, b: KeyframeId| sets[&a].intersection(&sets[&b]).count() as u32;
    let mut fallback: BTreeMap<KeyframeId, KeyframeId> = BTreeMap::new();
    for &a in sets.keys() {
        let partners: Vec<(KeyframeId, u32)> = sets
            .keys()
            .filter(|&&b| b != a)
            .map(|&b| (b, shared(a, b)))
            .filter(|&(_, w)| w > 0)
            .collect();
        if partners.iter().all(|&(_, w)| w < min_weight) {
            let mut best: Option<(KeyframeId, u32)> = None;
            for (b, w) in partners {
                if best.is_none_or(|(_, bw)| w > bw) {
                    best = Some((b, w));
                }
            }
            if let Some((b, _)) = best {
                fallback.insert(a, b);
            }
        }
    }
    let mut edges = BTreeMap::new();
    for &a in sets.keys() {
        for &b in sets.keys().filter(|&&b| b > a) {
            let w = shared(a, b);
            if w > 0
                && (w >= min_weight || fallback.get(&a) == Some(&b) || fallback.get(&b) == Some(&a))
            {
                edges.insert((a, b), w);
            }
        }
    }
    edges
}

proptest! {
    #[test]
    fn the_graph_after_any_updates_is_the_graph_built_from_scratch(
        ops in (3i64..10).prop_flat_map(|extent| prop::collection::vec(op(extent), 1..60)),
        min_weight in 1u32..8,
    ) {
        let mut g = CovisibilityGraph::new(CovisOptions { min_weight, ..CovisOptions::default() });
        let mut sets: BTreeMap<KeyframeId, HashSet<[i64; 3]>> = BTreeMap::new();
        let mut next = 0u64;
        for op in ops {
            match op {
                Op::Insert(v) => {
                    next += 1;
                    sets.insert(next, v.iter().copied().collect());
                    g.set_keyframe(next, cells(&v));
                }
                Op::Move(i, v) if !sets.is_empty() => {
                    let id = *sets.keys().nth(i % sets.len()).unwrap();
                    sets.insert(id, v.iter().copied().collect());
                    g.set_keyframe(id, cells(&v));
                }
                Op::Remove(i) if !sets.is_empty() => {
                    let id = *sets.keys().nth(i % sets.len()).unwrap();
                    sets.remove(&id);
                    g.remove_keyframe(id);
                }
                Op::Reload => {
                    g = CovisibilityGraph::from_snapshot(*g.options(), &g.snapshot());
                    for (&id, set) in &sets {
                        g.restore_voxels(id, cells(&set.iter().copied().collect::<Vec<_>>()));
                    }
                }
                _ => {}
            }
            let oracle = brute_force_edges(&sets, min_weight);
            for &id in sets.keys() {
                let row = g.ordered_neighbours(id);
                for &(other, w) in &row {
                    prop_assert_eq!(g.weight(other, id), w, "edge {}-{} is one-sided", id, other);
                }
                let has_partner = sets
                    .iter()
                    .any(|(&o, s)| o != id && !s.is_disjoint(&sets[&id]));
                prop_assert!(!has_partner || !row.is_empty(), "{} shares voxels but has no edge", id);
            }
            prop_assert_eq!(g.edges(), oracle);
            let alive: HashSet<KeyframeId> = sets.keys().copied().collect();
            assert_forest(&g, &alive);
            prop_assert_eq!(g.len(), sets.len());
        }
    }
}

/// A snapshot restricted to some keyframes holds exactly the edges a graph built from
/// those keyframes alone finds at or above the threshold (weights count what two
/// keyframes share, whoever else is mapped), and no edge or tree link leaving them.
#[test]
fn a_restricted_snapshot_keeps_the_edges_among_its_keyframes() {
    let options = CovisOptions::default();
    let clouds: Vec<(KeyframeId, Vec<[f64; 3]>)> = (0..12)
        .map(|i| (i as KeyframeId, block(i * 7, 30, 2)))
        .collect();
    let mut whole = CovisibilityGraph::new(options);
    for (id, points) in &clouds {
        whole.set_keyframe(*id, points.clone());
    }
    let ids: Vec<KeyframeId> = vec![2, 3, 4, 5, 9];
    let snapshot = whole.snapshot();
    let part = snapshot.restricted_to(&ids);
    // The definition, filtered over everything: what the per-keyframe lookups must give.
    let inside = |id: &KeyframeId| ids.contains(id);
    assert_eq!(
        part,
        CovisSnapshot {
            keyframes: snapshot.keyframes.iter().copied().filter(inside).collect(),
            edges: (snapshot.edges.iter().copied())
                .filter(|(a, b, _)| inside(a) && inside(b))
                .collect(),
            parents: (snapshot.parents.iter().copied())
                .filter(|(c, p)| inside(c) && inside(p))
                .collect(),
            in_tree: snapshot.in_tree.iter().copied().filter(inside).collect(),
        }
    );
    assert!(!part.parents.is_empty());
    let mut alone = CovisibilityGraph::new(options);
    for (id, points) in clouds.iter().filter(|(id, _)| ids.contains(id)) {
        alone.set_keyframe(*id, points.clone());
    }
    let strong = |edges: &[(KeyframeId, KeyframeId, u32)]| -> Vec<(KeyframeId, KeyframeId, u32)> {
        edges
            .iter()
            .copied()
            .filter(|e| e.2 >= options.min_weight)
            .collect()
    };
    let alone = alone.snapshot();
    assert!(!strong(&alone.edges).is_empty());
    assert_eq!(strong(&part.edges), strong(&alone.edges));
    assert_eq!(part.keyframes, ids);
    assert!(part.edges.iter().all(|(a, b, _)| inside(a) && inside(b)));
    assert!(part.parents.iter().all(|(c, p)| inside(c) && inside(p)));
    assert!(part.in_tree.iter().all(inside));
}
