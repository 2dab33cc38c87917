//! Exact k-nearest neighbourhoods of every point of a cloud at once ("all-kNN"), the
//! query pattern of covariance estimation. Queries are answered a leaf at a time: the
//! points of a small subtree share one bottom-up search (own subtree first, then the
//! siblings of its ancestors until every search ball fits). On small_gicp/target.ply it
//! is about 10 % faster than one kiddo query per point; [`crate::spatial::PointTree`]
//! answers single queries and is the tree baked maps hold.

use rayon::prelude::*;

use crate::spatial::build::{BoxNode, BoxTree};
use crate::spatial::{rank, rank_dist_sq, rank_item};

/// One neighbour of a query: its index in the input, squared distance (m^2) and
/// coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Found {
    /// Index of the neighbour in the input points.
    pub index: u32,
    /// Squared distance to the query, m^2.
    pub dist_sq: f32,
    /// The neighbour's coordinates (from the index's cache-friendly copy).
    pub point: [f32; 3],
}

/// Points per leaf: the unit of distance computation.
const LEAF: usize = 8;
/// Queries sharing one traversal: the points of the largest subtree of at most this many.
const GROUP: usize = 16;

/// A balanced kd-tree over a permuted copy of the points (median split, widest axis).
struct Index {
    points: Vec<[f32; 3]>,
    /// The same coordinates axis by axis, so distance loops vectorize.
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    original: Vec<u32>,
    nodes: Vec<BoxNode>,
}

impl Index {
    fn new(points: &[[f32; 3]]) -> Self {
        let BoxTree { nodes, order } = BoxTree::build(points, LEAF, 1);
        Self {
            points: order.iter().map(|o| o.1).collect(),
            xs: order.iter().map(|o| o.1[0]).collect(),
            ys: order.iter().map(|o| o.1[1]).collect(),
            zs: order.iter().map(|o| o.1[2]).collect(),
            original: order.iter().map(|o| o.0).collect(),
            nodes,
        }
    }
}

/// Squared distance between two boxes (0 when they overlap).
#[inline(always)]
fn box_box_dist_sq(a: &BoxNode, bmin: &[f32; 3], bmax: &[f32; 3]) -> f32 {
    let gx = (bmin[0] - a.max[0]).max(a.min[0] - bmax[0]).max(0.0);
    let gy = (bmin[1] - a.max[1]).max(a.min[1] - bmax[1]).max(0.0);
    let gz = (bmin[2] - a.max[2]).max(a.min[2] - bmax[2]).max(0.0);
    gx * gx + gy * gy + gz * gz
}

/// The best `k` candidates of one query, sorted by (squared distance, original index).
struct Best {
    /// [`rank`]s of (squared distance, original index): one compare orders them.
    ranks: Vec<u64>,
    /// Each candidate's slot in the index's permuted arrays.
    slots: Vec<u32>,
    k: usize,
    max_dist_sq: f32,
    /// Candidates beyond this squared distance cannot enter: `max_dist_sq` until `k`
    /// are held, then the k-th distance.
    bound: f32,
}

impl Best {
    fn bound(&self) -> f32 {
        self.bound
    }

    fn offer(&mut self, d2: f32, index: u32, slot: u32) {
        let new = rank(d2, index);
        let full = self.ranks.len() == self.k;
        if d2 >= self.max_dist_sq || (full && new >= self.ranks[self.k - 1]) {
            return;
        }
        if !full {
            self.ranks.push(new);
            self.slots.push(slot);
        }
        // Shift larger entries up one slot (cheaper than a memmove call for small k).
        let mut j = self.ranks.len() - 1;
        while j > 0 && new < self.ranks[j - 1] {
            self.ranks[j] = self.ranks[j - 1];
            self.slots[j] = self.slots[j - 1];
            j -= 1;
        }
        self.ranks[j] = new;
        self.slots[j] = slot;
        if self.ranks.len() == self.k {
            self.bound = rank_dist_sq(self.ranks[self.k - 1]);
        }
    }
}

/// Calls `f(i, neighbours)` for every point `i` with its `k` nearest neighbours (itself
/// included) strictly closer than `sqrt(max_dist_sq)`, sorted by distance, ties by
/// index; collects the results in point order. Deterministic for any thread count.
/// Points must be finite.
pub fn map_neighbourhoods<R, F>(points: &[[f32; 3]], k: usize, max_dist_sq: f32, f: F) -> Vec<R>
where
    R: Send,
    F: Fn(usize, &[Found]) -> R + Sync,
{
    if points.is_empty() || k == 0 {
        return points.iter().enumerate().map(|(i, _)| f(i, &[])).collect();
    }
    let index = Index::new(points);
    let groups = query_groups(&index);
    let per_leaf: Vec<Vec<(u32, R)>> = groups
        .par_iter()
        .map(|(group, ancestors)| {
            neighbourhoods_of_group(&index, *group, ancestors, k, max_dist_sq, &f)
        })
        .collect();
    let mut slots: Vec<Option<R>> = (0..points.len()).map(|_| None).collect();
    for (i, r) in per_leaf.into_iter().flatten() {
        slots[i as usize] = Some(r);
    }
    slots
        .into_iter()
        .map(|r| r.expect("every point is in one leaf"))
        .collect()
}

/// The nodes holding at most [`GROUP`] points whose parent holds more (or the root),
/// each with its ancestors from the root down to its parent.
fn query_groups(index: &Index) -> Vec<(usize, Vec<usize>)> {
    let mut groups = Vec::new();
    let mut stack = vec![(0usize, Vec::new())];
    while let Some((n, ancestors)) = stack.pop() {
        let node = &index.nodes[n];
        if node.right == 0 || (node.end - node.start) as usize <= GROUP {
            groups.push((n, ancestors));
        } else {
            let mut below = ancestors;
            below.push(n);
            stack.push((node.right as usize, below.clone()));
            stack.push((n + 1, below));
        }
    }
    groups
}

/// True when every query's search ball lies inside `node`'s box: nothing outside the
/// node can then improve any query.
fn balls_inside(node: &BoxNode, queries: &[[f32; 3]], best: &[Best]) -> bool {
    queries.iter().zip(best).all(|(q, b)| {
        (0..3).all(|a| {
            let (lo, hi) = (q[a] - node.min[a], node.max[a] - q[a]);
            lo >= 0.0 && hi >= 0.0 && lo * lo >= b.bound() && hi * hi >= b.bound()
        })
    })
}

/// Searches the subtree under `root` for better candidates of every query.
fn search(
    index: &Index,
    root: u32,
    queries: &[[f32; 3]],
    qmin: &[f32; 3],
    qmax: &[f32; 3],
    best: &mut [Best],
    stack: &mut Vec<u32>,
) {
    stack.clear();
    stack.push(root);
    // The loosest bound of the group; bounds only shrink when a leaf is processed.
    let mut worst = best.iter().map(Best::bound).fold(0.0f32, f32::max);
    while let Some(n) = stack.pop() {
        let candidate = &index.nodes[n as usize];
        if box_box_dist_sq(candidate, qmin, qmax) > worst {
            continue;
        }
        if candidate.right == 0 {
            let range = candidate.start as usize..candidate.end as usize;
            let (xs, ys, zs) = (
                &index.xs[range.clone()],
                &index.ys[range.clone()],
                &index.zs[range.clone()],
            );
            for (b, qp) in best.iter_mut().zip(queries) {
                if box_box_dist_sq(candidate, qp, qp) > b.bound() {
                    continue;
                }
                let mut d2s = [0.0f32; LEAF];
                for j in 0..xs.len() {
                    d2s[j] =
                        (xs[j] - qp[0]).powi(2) + (ys[j] - qp[1]).powi(2) + (zs[j] - qp[2]).powi(2);
                }
                for (j, &d2) in d2s[..xs.len()].iter().enumerate() {
                    if d2 <= b.bound() {
                        b.offer(
                            d2,
                            index.original[range.start + j],
                            (range.start + j) as u32,
                        );
                    }
                }
            }
            worst = best.iter().map(Best::bound).fold(0.0f32, f32::max);
            continue;
        }
        let (left, right) = (n + 1, candidate.right);
        let dl = box_box_dist_sq(&index.nodes[left as usize], qmin, qmax);
        let dr = box_box_dist_sq(&index.nodes[right as usize], qmin, qmax);
        // Nearer child last, so it is searched first.
        if dl <= dr {
            stack.extend([right, left]);
        } else {
            stack.extend([left, right]);
        }
    }
}

/// Neighbourhoods of the points under `group`: its own subtree first, then the sibling
/// subtrees of its ancestors, nearest first, stopping once every search ball fits
/// inside the subtree searched so far (bottom-up all-kNN).
fn neighbourhoods_of_group<R, F>(
    index: &Index,
    group: usize,
    ancestors: &[usize],
    k: usize,
    max_dist_sq: f32,
    f: &F,
) -> Vec<(u32, R)>
where
    F: Fn(usize, &[Found]) -> R,
{
    let node = &index.nodes[group];
    let range = node.start as usize..node.end as usize;
    let queries = &index.points[range.clone()];
    let (qmin, qmax) = (node.min, node.max);
    let mut best: Vec<Best> = queries
        .iter()
        .map(|_| Best {
            ranks: Vec::with_capacity(k),
            slots: Vec::with_capacity(k),
            k,
            max_dist_sq,
            bound: max_dist_sq,
        })
        .collect();
    let mut stack: Vec<u32> = Vec::with_capacity(64);
    search(
        index,
        group as u32,
        queries,
        &qmin,
        &qmax,
        &mut best,
        &mut stack,
    );
    let mut current = group;
    for &parent in ancestors.iter().rev() {
        if balls_inside(&index.nodes[current], queries, &best) {
            break;
        }
        let right = index.nodes[parent].right as usize;
        let sibling = if current == parent + 1 {
            right
        } else {
            parent + 1
        };
        search(
            index,
            sibling as u32,
            queries,
            &qmin,
            &qmax,
            &mut best,
            &mut stack,
        );
        current = parent;
    }
    let mut scratch: Vec<Found> = Vec::with_capacity(k);
    range
        .zip(best)
        .map(|(q, b)| {
            scratch.clear();
            scratch.extend(b.ranks.iter().zip(&b.slots).map(|(&r, &slot)| Found {
                index: rank_item(r),
                dist_sq: rank_dist_sq(r),
                point: index.points[slot as usize],
            }));
            let original = index.original[q];
            (original, f(original as usize, &scratch))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// Oracle: the `k` nearest strictly within `r2` by a full scan, ties by index.
    fn brute_knn(points: &[[f32; 3]], q: [f32; 3], k: usize, r2: f32) -> Vec<u32> {
        let mut all: Vec<(f32, u32)> = points
            .iter()
            .enumerate()
            .map(|(j, p)| {
                (
                    (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2),
                    j as u32,
                )
            })
            .filter(|&(d2, _)| d2 < r2)
            .collect();
        all.sort_by(|a, b| a.partial_cmp(b).unwrap());
        all.iter().take(k).map(|&(_, j)| j).collect()
    }

    #[test]
    fn matches_brute_force_including_ties_and_duplicates() {
        let mut rng = StdRng::seed_from_u64(5);
        // Random points plus an integer grid (many exact ties) plus duplicates.
        let mut points: Vec<[f32; 3]> = (0..1500)
            .map(|_| {
                [
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-1.0..1.0),
                ]
            })
            .collect();
        points.extend((0..400).map(|i| [(i % 20) as f32 * 0.25, (i / 20) as f32 * 0.25, 2.0]));
        points.extend(std::iter::repeat_n([1.0, 1.0, 1.0], 30));
        for (k, r2) in [(20, 1.0f32), (5, 0.04), (40, 100.0)] {
            let got = map_neighbourhoods(&points, k, r2, |_, nb| {
                nb.iter().map(|n| n.index).collect::<Vec<u32>>()
            });
            let coords = map_neighbourhoods(&points, k, r2, |_, nb| {
                nb.iter().all(|n| n.point == points[n.index as usize])
            });
            assert!(coords.iter().all(|&ok| ok));
            for (i, q) in points.iter().enumerate() {
                let want = brute_knn(&points, *q, k, r2);
                assert_eq!(got[i], want, "point {i}, k {k}");
            }
        }
    }

    #[test]
    fn large_clouds_built_in_parallel_match_brute_force() {
        // Above 2 * PARALLEL_BUILD points the index is built on several threads.
        let mut rng = StdRng::seed_from_u64(9);
        let points: Vec<[f32; 3]> = (0..40_000)
            .map(|_| {
                [
                    rng.random_range(-20.0..20.0),
                    rng.random_range(-20.0..20.0),
                    rng.random_range(-0.5..0.5),
                ]
            })
            .collect();
        let got = map_neighbourhoods(&points, 20, 1.0, |_, nb| {
            nb.iter().map(|n| n.index).collect::<Vec<u32>>()
        });
        for i in (0..points.len()).step_by(397) {
            let want = brute_knn(&points, points[i], 20, 1.0);
            assert_eq!(got[i], want, "point {i}");
        }
    }

    #[test]
    fn empty_and_tiny_inputs() {
        assert!(map_neighbourhoods(&[], 20, 1.0, |_, nb| nb.len()).is_empty());
        assert_eq!(
            map_neighbourhoods(&[[0.0; 3], [0.5, 0.0, 0.0]], 20, 1.0, |_, nb| nb.len()),
            vec![2, 2]
        );
    }
}
