#!/usr/bin/env bash
# Prints the path of a Python interpreter that has `rosbags`, `numpy` and `lz4`, the
# independent bag writer of kfmap's bag tests (never a dependency of the crates):
# $KFMAP_BAG_PYTHON when set, else a venv at ${KFMAP_BAG_VENV:-${TMPDIR:-/tmp}/kfmap-bag-venv},
# created and filled from PyPI on first use (see py_venv.sh).
set -euo pipefail
VENV_DIR="${KFMAP_BAG_VENV:-}" exec "$(dirname "$0")/py_venv.sh" KFMAP_BAG_PYTHON kfmap-bag-venv \
    "rosbags, numpy, lz4" "rosbags==0.11.9" numpy lz4
