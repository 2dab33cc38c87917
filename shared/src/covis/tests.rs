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
}

fn voxels() -> impl Strategy<Value = Vec<[i64; 3]>> {
    prop::collection::vec(prop::array::uniform3(0i64..6), 5..60)
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => voxels().prop_map(Op::Insert),
        1 => (any::<usize>(), voxels()).prop_map(|(i, v)| Op::Move(i, v)),
        2 => any::<usize>().prop_map(Op::Remove),
    ]
}

proptest! {
    #[test]
    fn weights_stay_symmetric_exact_and_the_tree_a_forest(ops in prop::collection::vec(op(), 1..60)) {
        let mut g = CovisibilityGraph::new(CovisOptions { min_weight: 4, ..CovisOptions::default() });
        let mut sets: BTreeMap<KeyframeId, HashSet<[i64; 3]>> = BTreeMap::new();
        let mut next = 0u64;
        for op in ops {
            let touched = match op {
                Op::Insert(v) => {
                    next += 1;
                    sets.insert(next, v.iter().copied().collect());
                    g.set_keyframe(next, cells(&v));
                    Some(next)
                }
                Op::Move(i, v) if !sets.is_empty() => {
                    let id = *sets.keys().nth(i % sets.len()).unwrap();
                    sets.insert(id, v.iter().copied().collect());
                    g.set_keyframe(id, cells(&v));
                    Some(id)
                }
                Op::Remove(i) if !sets.is_empty() => {
                    let id = *sets.keys().nth(i % sets.len()).unwrap();
                    sets.remove(&id);
                    g.remove_keyframe(id);
                    None
                }
                _ => None,
            };
            // Every stored edge is symmetric and weighs the true shared-voxel count.
            for (&(a, b), &w) in &g.edges() {
                prop_assert_eq!(g.weight(a, b), g.weight(b, a));
                prop_assert_eq!(w as usize, sets[&a].intersection(&sets[&b]).count());
            }
            // The keyframe just updated follows the threshold rule exactly (oracle).
            if let Some(id) = touched {
                let shared: BTreeMap<KeyframeId, usize> = sets
                    .iter()
                    .filter(|&(&o, _)| o != id)
                    .map(|(&o, s)| (o, s.intersection(&sets[&id]).count()))
                    .filter(|&(_, c)| c > 0)
                    .collect();
                let strong: Vec<KeyframeId> = shared.iter().filter(|&(_, &c)| c >= 4).map(|(&o, _)| o).collect();
                let mut got: Vec<KeyframeId> = g.ordered_neighbours(id).into_iter().map(|(k, _)| k).collect();
                got.sort_unstable();
                if strong.is_empty() {
                    prop_assert!(got.len() == shared.len().min(1));
                } else {
                    prop_assert_eq!(got, strong);
                }
            }
            let alive: HashSet<KeyframeId> = sets.keys().copied().collect();
            assert_forest(&g, &alive);
            prop_assert_eq!(g.len(), sets.len());
        }
    }
}
