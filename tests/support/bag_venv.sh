#!/usr/bin/env bash
# Prints the path of a Python interpreter that has `rosbags`, `numpy` and `lz4`, the
# independent bag writer of kfmap's bag tests (never a dependency of the crates):
# $KFMAP_BAG_PYTHON when set, else a venv at ${KFMAP_BAG_VENV:-${TMPDIR:-/tmp}/kfmap-bag-venv},
# created and filled from PyPI on first use (under a lock: tests call this in parallel).
# Exits non-zero, saying why on stderr, when no such interpreter can be had.
set -euo pipefail
if [[ -n "${KFMAP_BAG_PYTHON:-}" ]]; then
    echo "$KFMAP_BAG_PYTHON"
    exit 0
fi
venv="${KFMAP_BAG_VENV:-${TMPDIR:-/tmp}/kfmap-bag-venv}"
python="${PYTHON:-python3}"
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock 9
if ! "$venv/bin/python" -c "import rosbags, numpy, lz4" 2>/dev/null; then
    rm -rf "$venv"
    "$python" -m venv "$venv" >&2
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$venv/bin/python" -m pip install --quiet \
        "rosbags==0.11.9" numpy lz4 >&2
fi
echo "$venv/bin/python"
