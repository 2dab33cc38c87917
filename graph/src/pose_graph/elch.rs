//! ELCH (explicit loop closing heuristic, as in PCL's registration design): a loop edge
//! says where its end vertex should be; the correction that puts it there is spread
//! over the graph, each vertex taking the share `d_start / (d_start + d_end)` of it by
//! graph distance (edge hops, the loop edge left out). A cheap initializer before the
//! optimizer, which then starts near the loop-closed solution.

use std::collections::{HashMap, VecDeque};

use super::{PoseEdge, PoseGraph, VertexId};
use kfmap_geometry::se3::{exp, log};

/// Why ELCH could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ElchError {
    /// The loop edge names a vertex the graph does not have.
    #[error("loop edge {from} -> {to}: vertex {missing} is not in the graph")]
    UnknownVertex {
        /// Loop start.
        from: VertexId,
        /// Loop end.
        to: VertexId,
        /// The missing one.
        missing: VertexId,
    },
    /// Start and end are not connected except by the loop edge.
    #[error("loop edge {from} -> {to}: no path joins its ends besides the loop edge itself")]
    Disconnected {
        /// Loop start.
        from: VertexId,
        /// Loop end.
        to: VertexId,
    },
}

/// Hops from `source` to every vertex, ignoring edges between `skip.0` and `skip.1`.
fn hops(graph: &PoseGraph, source: usize, skip: (usize, usize)) -> Vec<Option<usize>> {
    let mut neighbours: HashMap<usize, Vec<usize>> = HashMap::new();
    for e in graph.edges() {
        let (a, b) = (graph.index[&e.from], graph.index[&e.to]);
        if (a, b) == skip || (b, a) == skip {
            continue;
        }
        neighbours.entry(a).or_default().push(b);
        neighbours.entry(b).or_default().push(a);
    }
    let mut dist = vec![None; graph.len()];
    dist[source] = Some(0);
    let mut queue = VecDeque::from([source]);
    while let Some(v) = queue.pop_front() {
        let next = dist[v].expect("queued vertices have a distance") + 1;
        for &n in neighbours.get(&v).into_iter().flatten() {
            if dist[n].is_none() {
                dist[n] = Some(next);
                queue.push_back(n);
            }
        }
    }
    dist
}

/// Closes `loop_edge` by spreading its error over `graph` (poses only; the edge is not
/// added). Returns each vertex's share, in `graph.ids()` order.
pub fn elch(graph: &mut PoseGraph, loop_edge: &PoseEdge) -> Result<Vec<f64>, ElchError> {
    let find = |id: VertexId| {
        graph
            .index
            .get(&id)
            .copied()
            .ok_or(ElchError::UnknownVertex {
                from: loop_edge.from,
                to: loop_edge.to,
                missing: id,
            })
    };
    let (s, e) = (find(loop_edge.from)?, find(loop_edge.to)?);
    let from_start = hops(graph, s, (s, e));
    let from_end = hops(graph, e, (s, e));
    if from_start[e].is_none() {
        return Err(ElchError::Disconnected {
            from: loop_edge.from,
            to: loop_edge.to,
        });
    }
    // The correction, applied on the left, that moves the end to where the loop says.
    let target = graph.poses[s] * loop_edge.measurement;
    let correction = log(&(target * graph.poses[e].inverse()));
    let shares: Vec<f64> = from_start
        .iter()
        .zip(&from_end)
        .map(|(ds, de)| match (ds, de) {
            (Some(ds), Some(de)) if ds + de > 0 => *ds as f64 / (ds + de) as f64,
            (Some(_), None) => 0.0,
            (None, Some(_)) => 1.0,
            _ => 0.0,
        })
        .collect();
    for (pose, &w) in graph.poses.iter_mut().zip(&shares) {
        *pose = exp(&(correction * w)) * *pose;
    }
    Ok(shares)
}
