#!/usr/bin/env bash
# Prints the path of a Python interpreter that has `cyclonedds` (Eclipse Cyclone DDS,
# the DDS of rmw_cyclonedds_cpp: the independent peer of kfmap-ros2's tests, never a
# dependency of the crates) and `numpy`: $KFMAP_DDS_PYTHON when set, else a venv at
# ${KFMAP_DDS_VENV:-${TMPDIR:-/tmp}/kfmap-dds-venv}, created and filled from PyPI on first
# use (under a lock: tests call this in parallel). Exits non-zero, saying why on stderr,
# when no such interpreter can be had.
set -euo pipefail
if [[ -n "${KFMAP_DDS_PYTHON:-}" ]]; then
    echo "$KFMAP_DDS_PYTHON"
    exit 0
fi
venv="${KFMAP_DDS_VENV:-${TMPDIR:-/tmp}/kfmap-dds-venv}"
python="${PYTHON:-python3}"
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock 9
if ! "$venv/bin/python" -c "import cyclonedds, numpy" 2>/dev/null; then
    rm -rf "$venv"
    "$python" -m venv "$venv" >&2
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$venv/bin/python" -m pip install --quiet \
        "cyclonedds==11.0.1" numpy >&2
fi
echo "$venv/bin/python"
