#!/usr/bin/env bash
# Creates (once) a venv with the independent bag writer the kfmap-bag container tests
# use (rosbags, with numpy and lz4), and prints its python's path.
#
#   KFMAP_BAG_VENV  venv to use or create (default ${TMPDIR:-/tmp}/kfmap-bag-venv)
#   PYTHON          interpreter that creates the venv (default python3, >= 3.10)
set -euo pipefail

venv="${KFMAP_BAG_VENV:-${TMPDIR:-/tmp}/kfmap-bag-venv}"
python="${PYTHON:-python3}"
if ! "$venv/bin/python" -c "import rosbags, numpy, lz4" 2>/dev/null; then
    "$python" -m venv "$venv" >&2
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$venv/bin/python" -m pip install --quiet \
        "rosbags==0.11.9" numpy lz4 >&2
fi
echo "$venv/bin/python"
