#!/usr/bin/env bash
# Prints the path of a Python interpreter for a test peer (never a dependency of the
# crates): `py_venv.sh OVERRIDE_VAR VENV_NAME IMPORTS PACKAGE...`. The interpreter named
# by the variable OVERRIDE_VAR when set; else a venv at $VENV_DIR (default
# ${TMPDIR:-/tmp}/VENV_NAME), created and filled with PACKAGE... from PyPI on first use,
# under a lock (tests call this in parallel), and rebuilt when `import IMPORTS` fails. Exits
# non-zero, saying why on stderr, when no such interpreter can be had.
set -euo pipefail
override="$1" name="$2" imports="$3"
shift 3
if [[ -n "${!override:-}" ]]; then
    echo "${!override}"
    exit 0
fi
venv="${VENV_DIR:-${TMPDIR:-/tmp}/$name}"
python="${PYTHON:-python3}"
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock 9
if ! "$venv/bin/python" -c "import $imports" 2>/dev/null; then
    rm -rf "$venv"
    "$python" -m venv "$venv" >&2
    PIP_DISABLE_PIP_VERSION_CHECK=1 "$venv/bin/python" -m pip install --quiet "$@" >&2
fi
echo "$venv/bin/python"
