#!/usr/bin/env bash
# Installs the kfmap Python client into a venv and runs its tests against the release
# binary (build it first: cargo build --release). Exits non-zero when a test fails.
#
#   KFMAP_PY_VENV  venv to use or create (default ${TMPDIR:-/tmp}/kfmap-py-venv)
#   KFMAP_BIN      kfmap binary (default target/release/kfmap)
#   PYTHON         interpreter that creates the venv (default python3, >= 3.10)
#   extra arguments go to pytest, e.g. run_tests.sh -k localize
#
# The test server runs under an iceoryx2 prefix of this run only; whatever happens to
# pytest, the server is stopped and that prefix's shared memory removed on exit.
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
venv="${KFMAP_PY_VENV:-${TMPDIR:-/tmp}/kfmap-py-venv}"
python="${PYTHON:-python3}"
export KFMAP_BIN="${KFMAP_BIN:-$repo/target/release/kfmap}"
export KFMAP_TEST_PREFIX="kfpyci$$_"
work="$(mktemp -d "${TMPDIR:-/tmp}/kfmap-py-tests.XXXXXX")"
export KFMAP_TEST_PIDFILE="$work/server.pid"

cleanup() {
    local pid
    if [[ -s "$KFMAP_TEST_PIDFILE" ]]; then
        pid="$(cat "$KFMAP_TEST_PIDFILE")"
        if kill -0 "$pid" 2>/dev/null; then
            kill -TERM "$pid" 2>/dev/null || true
            for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
            kill -KILL "$pid" 2>/dev/null || true
        fi
    fi
    # iceoryx2 files of this run's prefix only: /dev/shm, and /tmp/iceoryx2 two levels
    # deep (node folders emptied by this go too).
    find /dev/shm -maxdepth 1 -name "*${KFMAP_TEST_PREFIX}*" -type f -delete 2>/dev/null || true
    if [[ -d /tmp/iceoryx2 ]]; then
        find /tmp/iceoryx2 -mindepth 1 -maxdepth 3 -name "*${KFMAP_TEST_PREFIX}*" ! -type d \
            -printf '%h\n' -delete 2>/dev/null | sort -u | while read -r dir; do
            [[ "$(dirname "$(dirname "$dir")")" == /tmp/iceoryx2 ]] && rmdir "$dir" 2>/dev/null || true
        done
    fi
    rm -rf "$work"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

if [[ ! -x "$KFMAP_BIN" ]]; then
    echo "run_tests.sh: no kfmap binary at $KFMAP_BIN (cargo build --release first)" >&2
    exit 2
fi
if [[ ! -x "$venv/bin/python" ]]; then
    "$python" -m venv "$venv"
fi
export PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
"$venv/bin/python" -m pip install --quiet "$repo/python[remote]" pytest
"$venv/bin/python" -m pytest -q -p no:cacheprovider --basetemp "$work/pytest" \
    "$repo/python/tests" --ignore "$repo/python/tests/test_remote.py" "$@"

# The remote tests (a gateway on Zenoh) run in a private network namespace: only `lo`,
# nothing can leave the machine. Without user namespaces they skip, except under CI.
if unshare -rn sh -c 'ip link set lo up' 2>/dev/null; then
    KFMAP_TEST_NETNS=1 unshare -rn sh -c 'ip link set lo up && exec "$@"' sh \
        "$venv/bin/python" -m pytest -q -p no:cacheprovider --basetemp "$work/pytest-remote" \
        "$repo/python/tests/test_remote.py" "$@"
elif [[ "${CI:-}" == "true" ]]; then
    echo "run_tests.sh: CI=true but no private network namespace (unshare -rn) for the remote tests" >&2
    exit 1
else
    echo "run_tests.sh: remote tests skipped: no private network namespace (unshare -rn)" >&2
fi
