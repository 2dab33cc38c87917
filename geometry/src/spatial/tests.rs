use std::num::NonZeroUsize;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;

/// Random points, an integer-spaced grid (many exact distance ties) and duplicates.
fn awkward_cloud(seed: u64) -> Vec<[f32; 3]> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut points: Vec<[f32; 3]> = (0..3000)
        .map(|_| {
            [
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
                rng.random_range(-1.0..1.0),
            ]
        })
        .collect();
    points.extend((0..600).map(|i| [(i % 30) as f32 * 0.25, (i / 30) as f32 * 0.25, 2.0]));
    points.extend(std::iter::repeat_n([1.0, 1.0, 1.0], 40));
    points
}

/// Oracle: every point by a full scan, sorted by (squared distance, index).
fn brute(points: &[[f32; 3]], q: &[f32; 3]) -> Vec<(u32, f32)> {
    let mut all: Vec<(u32, f32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let d = (p[0] - q[0]) * (p[0] - q[0])
                + (p[1] - q[1]) * (p[1] - q[1])
                + (p[2] - q[2]) * (p[2] - q[2]);
            (i as u32, d)
        })
        .collect();
    all.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    all
}

fn queries(points: &[[f32; 3]], seed: u64) -> Vec<[f32; 3]> {
    let mut rng = StdRng::seed_from_u64(seed);
    // Points themselves, grid nodes between points (ties) and random spots, some far out.
    let mut q: Vec<[f32; 3]> = points.iter().step_by(37).copied().collect();
    q.extend((0..100).map(|i| [(i % 10) as f32 * 0.5 + 0.125, (i / 10) as f32 * 0.5, 2.0]));
    q.extend((0..300).map(|_| {
        [
            rng.random_range(-9.0..9.0),
            rng.random_range(-9.0..9.0),
            rng.random_range(-4.0..4.0),
        ]
    }));
    q
}

#[test]
fn searches_match_a_full_scan_including_ties() {
    let points = awkward_cloud(3);
    for leaf in [1, 4, 16, 33] {
        let tree = build_tree_with_leaf(&points, leaf).unwrap();
        let tree = tree.view();
        for q in queries(&points, 4) {
            let want = brute(&points, &q);
            assert_eq!(tree.nearest_one(&q), want[0], "leaf {leaf}, query {q:?}");
            for k in [1, 7, 20] {
                let k_nz = NonZeroUsize::new(k).unwrap();
                assert_eq!(tree.nearest_n(&q, k_nz), want[..k].to_vec(), "k {k}");
            }
            for r2 in [0.01f32, 0.25, 2.0] {
                let inside: Vec<_> = want.iter().copied().filter(|h| h.1 <= r2).collect();
                assert_eq!(tree.within(&q, r2), inside, "radius^2 {r2}");
                // Bounded k-NN: the nearest 7 among those within, the bound inclusive.
                let seven = NonZeroUsize::new(7).unwrap();
                let bounded = tree.nearest_n_within(&q, seven, r2);
                assert_eq!(
                    bounded,
                    inside[..inside.len().min(7)].to_vec(),
                    "k 7 within {r2}"
                );
            }
        }
    }
}

#[test]
fn bounded_nearest_is_inclusive_and_can_find_nothing() {
    let points = [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [3.0, 0.0, 0.0]];
    let tree = build_tree(&points).unwrap();
    let tree = tree.view();
    assert_eq!(
        tree.nearest_one_within(&[1.0, 0.0, 0.0], 0.25),
        Some((1, 0.25))
    );
    assert_eq!(tree.nearest_one_within(&[1.0, 0.0, 0.0], 0.2499), None);
    // Two points tie at 0.25: the smaller item wins.
    assert_eq!(tree.nearest_one(&[0.25, 0.0, 0.0]), (0, 0.0625));
    let many = awkward_cloud(9);
    let big = build_tree(&many).unwrap();
    for q in queries(&many, 10) {
        let want = brute(&many, &q)[0];
        for bound in [want.1 * 0.5, want.1, want.1 * 2.0] {
            let expected = (want.1 <= bound).then_some(want);
            assert_eq!(big.view().nearest_one_within(&q, bound), expected);
            // With coordinates: the found point's own, as given to the tree.
            let at = expected.map(|(i, d)| (i, d, many[i as usize]));
            assert_eq!(big.view().nearest_one_within_at(&q, bound), at);
        }
    }
}

#[test]
fn the_runner_up_is_a_full_scan_s_second_and_distances_repeat_bit_for_bit() {
    let many = awkward_cloud(11);
    let tree = build_tree(&many).unwrap();
    for q in queries(&many, 12) {
        let want = brute(&many, &q);
        for bound in [want[0].1 * 0.5, want[0].1, want[1].1, want[2].1 * 3.0] {
            let (nearest, runner_up) = tree.view().nearest_two_within_at(&q, bound);
            let expected = (want[0].1 <= bound).then(|| {
                let item = want[0].0;
                (item, want[0].1, many[item as usize])
            });
            assert_eq!(nearest, expected, "query {q:?} within {bound}");
            let second = if want[1].1 <= bound { want[1].1 } else { bound };
            assert_eq!(
                runner_up.to_bits(),
                second.to_bits(),
                "query {q:?} within {bound}"
            );
        }
        // Re-measuring the point found gives the distance the search gave.
        let (item, d) = tree.view().nearest_one(&q);
        assert_eq!(
            point_dist_sq(&many[item as usize], &q).to_bits(),
            d.to_bits()
        );
    }
}

#[test]
fn refuses_empty_and_non_finite_input() {
    assert_eq!(build_tree(&[]).unwrap_err(), TreeError::Empty);
    assert_eq!(
        build_tree(&[[0.0; 3], [f32::NAN, 0.0, 0.0]]).unwrap_err(),
        TreeError::NonFinite(1)
    );
}

#[test]
fn the_same_tree_for_any_thread_count() {
    let points = awkward_cloud(5);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| build_tree(&points).unwrap());
    let b = build_tree(&points).unwrap();
    assert_eq!(a.nodes, b.nodes);
    assert_eq!(a.items, b.items);
}

#[test]
fn stored_arrays_are_checked_before_searching() {
    // One point more than a multiple of LANES, so some lanes are padding.
    let mut points = awkward_cloud(7);
    points.push([0.5, 0.5, 0.5]);
    let tree = build_tree(&points).unwrap();
    let (nodes, blocks, items) = (tree.nodes.clone(), tree.blocks.clone(), tree.items.clone());
    assert_eq!(
        TreeRef::from_parts(&nodes, &blocks, &items).map(|t| t.len()),
        Ok(points.len())
    );

    let malformed = |nodes: &[NodeWords], blocks: &[PointBlock], items: &[u32]| {
        matches!(
            TreeRef::from_parts(nodes, blocks, items),
            Err(TreeError::Malformed(_))
        )
    };
    let mut repeated = items.clone();
    repeated[1] = repeated[0];
    assert!(malformed(&nodes, &blocks, &repeated));
    assert!(malformed(&nodes, &blocks, &items[1..]));
    let mut out_of_range = items.clone();
    out_of_range[0] = points.len() as u32;
    assert!(malformed(&nodes, &blocks, &out_of_range));
    // An unused lane must be padding: NaN (never within a bound) and PAD_ITEM.
    let pad = items
        .iter()
        .position(|&i| i == PAD_ITEM)
        .expect("a padded lane");
    let mut pad_as_point = blocks.clone();
    for coordinates in &mut pad_as_point[pad / LANES] {
        coordinates[pad % LANES] = 0.0;
    }
    assert!(malformed(&nodes, &pad_as_point, &items));
    let mut used_pad = items.clone();
    used_pad[0] = PAD_ITEM;
    assert!(malformed(&nodes, &blocks, &used_pad));
    // A used lane holds a finite point, as build_tree requires.
    for bad in [f32::NAN, f32::INFINITY] {
        let mut non_finite = blocks.clone();
        non_finite[0][1][0] = bad;
        assert!(malformed(&nodes, &non_finite, &items), "{bad}");
    }

    let leaf = nodes.iter().position(|n| n[0] == LEAF_TAG).unwrap();
    let split = 0;
    let edits: [(usize, usize, u32); 8] = [
        (split, 0, 3),                  // axis 3
        (split, 1, nodes.len() as u32), // right child beyond the end
        (split, 1, 1),                  // right child is the left child
        (split, 2, f32::NAN.to_bits()),
        (leaf, 2, blocks.len() as u32 + 5), // blocks beyond the end
        (leaf, 3, 0),                       // no points
        (leaf, 3, 3 * LANES as u32),        // more points than lanes
        (leaf, 3, 1),                       // used lanes marked as padding
    ];
    for (node, word, value) in edits {
        let mut bad = nodes.clone();
        bad[node][word] = value;
        assert!(
            malformed(&bad, &blocks, &items),
            "node {node} word {word} = {value}"
        );
    }
    assert!(malformed(&nodes[..nodes.len() - 1], &blocks, &items));
    // A caterpillar of 50 splits (a leaf left, the next split right) is well formed
    // but nests deeper than any balanced tree.
    let mut chain: Vec<NodeWords> = Vec::new();
    for i in 0..50u32 {
        chain.push([0, 2 * i + 2, 0, 0]);
        chain.push([LEAF_TAG, i, i + 1, LANES as u32]);
    }
    chain.push([LEAF_TAG, 50, 51, LANES as u32]);
    let line = [[[0.0f32; LANES]; 3]; 51];
    let ids: Vec<u32> = (0..51 * LANES as u32).collect();
    assert!(matches!(
        TreeRef::from_parts(&chain, &line, &ids),
        Err(TreeError::Malformed(why)) if why.contains("deeper")
    ));
}

#[test]
fn leaves_fill_their_blocks() {
    // Splits at multiples of LANES: with leaves of LEAF_SIZE only the last block can be
    // part empty.
    for n in [1usize, 7, 8, 9, 100, 3640, 50_001] {
        let points: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                [
                    (i * 7919 % 1000) as f32,
                    (i * 104_729 % 997) as f32,
                    i as f32,
                ]
            })
            .collect();
        let tree = build_tree(&points).unwrap();
        assert_eq!(tree.blocks.len(), n.div_ceil(LANES), "{n} points");
        assert_eq!(tree.items.iter().filter(|&&i| i != PAD_ITEM).count(), n);
    }
}

#[test]
fn a_stored_tree_that_passes_the_check_never_answers_outside_its_points() {
    // Random edits of a valid tree's words, lanes and ids: each is refused, or every
    // search on it stays in range (no panic, no id outside 0..len).
    let points = awkward_cloud(13);
    let tree = build_tree_with_leaf(&points, 12).unwrap();
    let mut rng = StdRng::seed_from_u64(14);
    let probes = queries(&points, 15);
    let mut accepted = 0;
    for _ in 0..3000 {
        let (mut nodes, mut blocks, mut items) =
            (tree.nodes.clone(), tree.blocks.clone(), tree.items.clone());
        match rng.random_range(0..3) {
            0 => {
                let n = rng.random_range(0..nodes.len());
                nodes[n][rng.random_range(0..4)] = match rng.random_range(0..3) {
                    0 => rng.random(),
                    1 => rng.random_range(0..nodes.len() as u32 + 2),
                    _ => rng.random_range(-10.0f32..10.0).to_bits(),
                };
            }
            1 => {
                let b = rng.random_range(0..blocks.len());
                blocks[b][rng.random_range(0..3)][rng.random_range(0..LANES)] =
                    [f32::NAN, 1e30, rng.random_range(-10.0..10.0)][rng.random_range(0..3)];
            }
            _ => {
                let i = rng.random_range(0..items.len());
                items[i] = [PAD_ITEM, rng.random_range(0..points.len() as u32 + 2)]
                    [rng.random_range(0..2)];
            }
        }
        let Ok(stored) = TreeRef::from_parts(&nodes, &blocks, &items) else {
            continue;
        };
        accepted += 1;
        let n = stored.len() as u32;
        for q in probes.iter().step_by(7) {
            assert!(stored.nearest_one_within(q, 4.0).is_none_or(|(i, _)| i < n));
            let k = NonZeroUsize::new(5).unwrap();
            assert!(stored.nearest_n(q, k).iter().all(|&(i, _)| i < n));
            assert!(stored.within(q, 1.0).iter().all(|&(i, _)| i < n));
        }
    }
    // Some edits keep a tree (a coordinate moved, a split bound changed).
    assert!(accepted > 100, "{accepted} accepted");
}

#[test]
fn search_cost_counts_the_work_of_a_search() {
    // One leaf: the root is the leaf, its blocks are all read.
    let few: Vec<[f32; 3]> = (0..LEAF_SIZE).map(|i| [i as f32, 0.0, 0.0]).collect();
    let one_leaf = build_tree(&few).unwrap();
    let cost = one_leaf.view().nearest_one_cost(&[3.2, 0.0, 0.0]);
    assert_eq!(
        cost,
        SearchCost {
            nodes: 1,
            blocks: LEAF_SIZE.div_ceil(LANES)
        }
    );
    // Far from a large cloud, a search reads more than a leaf but far less than all.
    let points = awkward_cloud(11);
    let tree = build_tree(&points).unwrap();
    let cost = tree.view().nearest_one_cost(&[0.3, 0.2, 0.1]);
    assert!(
        cost.blocks >= 1 && cost.blocks < tree.blocks.len() / 4,
        "{cost:?}"
    );
    assert!(
        cost.nodes > 1 && cost.nodes < tree.nodes.len() / 4,
        "{cost:?}"
    );
}
