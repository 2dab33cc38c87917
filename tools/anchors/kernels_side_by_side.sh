#!/usr/bin/env bash
# The KD-tree and voxel-grid table of docs/BENCHMARKS.md, measured in one run:
# small_gicp before and after kfmap's criterion benches (keep small_gicp's better run).
# PYTHON: a venv outside the repository with `small-gicp numpy` (see small_gicp_cov.py).
# Needs ../shared/data (kitti00, small_gicp/target.ply).
set -euo pipefail
PYTHON=${PYTHON:-python3}
cd "$(dirname "$0")/../.."

anchor() {
    echo "== small_gicp 1.0.1 ($1)"
    (cd tools/anchors && "$PYTHON" small_gicp_knn.py && "$PYTHON" small_gicp_cov.py | grep '^filtered')
}

anchor before
echo "== kfmap (criterion: median of the middle column)"
cargo bench -p kfmap-geometry --bench kdtree -- 'leaf16_(scan|morton)_order|build_leaf16|floor' 2>&1 |
    grep -E '^nn |^kitti|time:'
cargo bench -p kfmap-geometry --bench geometry -- 'voxel' 2>&1 | grep -E '^target|time:'
anchor after
