"""Session fixtures: a simulated dataset, its baked map and a ``kfmap serve`` of it under
an iceoryx2 prefix of this test run only, removed with its shared memory at the end.

Environment: ``KFMAP_BIN`` (default ``<repo>/target/release/kfmap``); optionally
``KFMAP_TEST_PREFIX`` (the iceoryx2 prefix) and ``KFMAP_TEST_PIDFILE`` (where the
server's pid is written), which ``run_tests.sh`` sets so it can clean up even after
pytest itself was killed.
"""

from __future__ import annotations

import atexit
import os
import signal
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

import kfmap

REPO = Path(__file__).resolve().parents[2]
READY_TIMEOUT_S = 60.0
# Roll and pitch (deg) of the world of ``tilted_dataset`` against the dataset's frame.
TILT_DEG = (4.0, -3.0)


@dataclass(frozen=True)
class Server:
    """A running ``kfmap serve`` and what it serves."""

    bin: Path
    map_name: str
    prefix: str
    map_path: Path
    dataset: Path
    process: subprocess.Popen


def remove_prefix_files(prefix: str) -> list[Path]:
    """Removes every iceoryx2 file whose name contains ``prefix``: /dev/shm, and
    /tmp/iceoryx2 two folder levels deep; a node folder emptied by it goes too."""
    removed: list[Path] = []
    for root, depth in ((Path("/dev/shm"), 0), (Path("/tmp/iceoryx2"), 2)):
        stack = [(root, depth)]
        while stack:
            folder, left = stack.pop()
            try:
                entries = list(folder.iterdir())
            except OSError:
                continue
            for entry in entries:
                if prefix in entry.name and not entry.is_dir():
                    try:
                        entry.unlink()
                        removed.append(entry)
                    except OSError:
                        continue
                    if folder.parent.parent == root:  # root/nodes/<node>/file
                        try:
                            folder.rmdir()  # only succeeds when empty
                        except OSError:
                            pass
                elif left > 0 and entry.is_dir():
                    stack.append((entry, left - 1))
    return removed


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5)


@pytest.fixture(scope="session")
def kfmap_bin() -> Path:
    path = Path(os.environ.get("KFMAP_BIN", REPO / "target" / "release" / "kfmap"))
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.exit(f"kfmap binary not found at {path}; build it or set KFMAP_BIN", 2)
    return path


@pytest.fixture(scope="session")
def dataset(kfmap_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s courtyard drive (``kfmap simulate``) with its baked map ``map.kfmap``."""
    out = tmp_path_factory.mktemp("kfmap-data")
    data = out / "dataset"
    run = dict(check=True, capture_output=True, text=True, timeout=300)
    subprocess.run(
        [kfmap_bin, "simulate", "--preset", "courtyard", "--seconds", "3", "--out", data],
        **run,
    )
    subprocess.run([kfmap_bin, "bake", "--dataset", data, "--out", out / "map.kfmap"], **run)
    return data


@pytest.fixture(scope="session")
def tilted_dataset(kfmap_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10 s courtyard drive (16 beams, 1.5 s to simulate) in a world tilted roll 4 /
    pitch -3 deg against the dataset's frame (``--tilt-deg``; gravity in that frame in
    ``meta.toml``), not baked: its poses and IMU windows feed a session's gravity pool on
    the test server (10 s: the pool takes a stamped window per 0.5 s and needs 10)."""
    data = tmp_path_factory.mktemp("kfmap-tilted") / "dataset"
    subprocess.run(
        [kfmap_bin, "simulate", "--preset", "courtyard", "--seconds", "10", "--beams", "16",
         f"--tilt-deg={TILT_DEG[0]},{TILT_DEG[1]}", "--out", data],
        check=True, capture_output=True, text=True, timeout=300,
    )
    return data


@pytest.fixture(scope="session")
def server(kfmap_bin: Path, dataset: Path) -> Server:
    pid = os.getpid()
    prefix = os.environ.get("KFMAP_TEST_PREFIX") or f"kfpytest{pid}_"
    map_name = f"pytest-{pid}"
    map_path = dataset.parent / "map.kfmap"
    log = open(dataset.parent / "serve.log", "w")
    process = subprocess.Popen(
        [kfmap_bin, "serve", "--map", map_path, "--map-name", map_name,
         "--iceoryx-prefix", prefix],
        stdout=subprocess.PIPE, stderr=log, text=True, cwd=dataset.parent,
    )
    pidfile = os.environ.get("KFMAP_TEST_PIDFILE")
    if pidfile:
        Path(pidfile).write_text(str(process.pid))

    def cleanup() -> None:
        _stop(process)
        remove_prefix_files(prefix)

    atexit.register(cleanup)  # also on an interrupted run
    ready = threading.Event()

    def drain() -> None:  # wait for "ready:", then keep the pipe from filling
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            log.flush()
            if line.startswith("ready:"):
                ready.set()

    threading.Thread(target=drain, daemon=True).start()
    if not ready.wait(READY_TIMEOUT_S) or process.poll() is not None:
        cleanup()
        pytest.exit(f"kfmap serve did not get ready; see {log.name}", 2)
    try:
        yield Server(kfmap_bin, map_name, prefix, map_path, dataset, process)
    finally:
        cleanup()
        atexit.unregister(cleanup)
        log.close()


@pytest.fixture
def client(server: Server):
    """A fresh client (its own server session) of the test server."""
    with kfmap.Client(server.map_name, iceoryx_prefix=server.prefix, timeout=30.0) as c:
        yield c
