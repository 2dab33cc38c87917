#!/usr/bin/env bash
# Prints the path of a Python interpreter that has `cyclonedds` (Eclipse Cyclone DDS,
# the DDS of rmw_cyclonedds_cpp: the independent peer of kfmap-ros2's tests, never a
# dependency of the crates), `numpy` and `mcap` (Foxglove's MCAP writer, to record the
# node's outputs as `ros2 bag record` would): $KFMAP_DDS_PYTHON when set, else a venv at
# ${KFMAP_DDS_VENV:-${TMPDIR:-/tmp}/kfmap-dds-venv}, created and filled from PyPI on first
# use (see py_venv.sh).
set -euo pipefail
VENV_DIR="${KFMAP_DDS_VENV:-}" exec "$(dirname "$0")/py_venv.sh" KFMAP_DDS_PYTHON kfmap-dds-venv \
    "cyclonedds, numpy, mcap" "cyclonedds==11.0.1" numpy "mcap==1.6.0"
