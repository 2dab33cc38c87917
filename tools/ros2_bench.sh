#!/usr/bin/env bash
# kfmap-ros2 measured through Cyclone DDS (the tests' peer, tests/support/dds_peer.py)
# beside `kfmap localize` on the same scans and server (docs/DESIGN.md#notes-ros2).
# Runs itself inside a private network namespace (`unshare -rn`: only loopback,
# multicast on for discovery). Times are printed, never asserted.
#
#   tools/ros2_bench.sh latency [ROUNDS]   cloud -> pose p50 of the node against
#       `kfmap localize --no-imu` (its tracking call) on a simulated courtyard drive
#       (60 clouds of about 25 900 points), rounds alternating the two; the node's
#       clouds go out one at a time (the next once the last is answered).
#   tools/ros2_bench.sh soak [SECONDS [HZ [BEAMS]]]   clouds of about 100 000 points
#       (64 beams) at 10 Hz for 60 s by default, free-running (the peer never waits):
#       clouds sent, received, localized and skipped for newer ones, the statuses, the latency, and
#       the node's and the server's resident memory sampled every second.
#
# kfmap and kfmap-ros2 from target/release (cargo build --release --workspace).
# KEEP_LOGS=DIR copies the node's, server's and peer's outputs there.
set -euo pipefail
mode=${1:-latency}
here=$(cd "$(dirname "$0")/.." && pwd)
bin=${KFMAP_BIN:-$here/target/release}
if [ -z "${KFMAP_IN_NETNS:-}" ]; then
    exec unshare -rn env KFMAP_IN_NETNS=1 KFMAP_BIN="$bin" KEEP_LOGS="${KEEP_LOGS:-}" \
        bash "$0" "$@"
fi
ip link set lo up
ip link set lo multicast on
for tool in kfmap kfmap-ros2; do
    [ -x "$bin/$tool" ] || { echo "no $bin/$tool: cargo build --release --workspace" >&2; exit 2; }
done
python=$(bash "$here/tests/support/dds_venv.sh")
work=$(mktemp -d)
prefix="ros2bench$$"
pids=()
cleanup() {
    kill "${pids[@]}" 2>/dev/null || true
    wait 2>/dev/null || true
    if [ -n "${KEEP_LOGS:-}" ]; then
        mkdir -p "$KEEP_LOGS"
        cp "$work"/*.out "$work"/*.err "$work"/*.jsonl "$work"/*.tsv "$KEEP_LOGS"/ 2>/dev/null || true
    fi
    # iceoryx2 keeps a prefix's management segment after its last node.
    rm -rf "$work" /dev/shm/"$prefix"*
}
trap cleanup EXIT

# Waits (at most 60 s) for a line starting with $2 in file $1.
wait_ready() {
    for _ in $(seq 600); do
        grep -q "^$2" "$1" 2>/dev/null && return 0
        sleep 0.1
    done
    echo "no '$2' in $1 after 60 s:" >&2
    cat "$1" >&2
    exit 1
}

# The peer's manifest of dataset $1's scans (binary PCD, x y z first): each scan's
# points as a file, x y z published (the rest of each point rides along unread), the
# order $2 ("once", or "pingpong:N": N clouds forward then back, stamps always rising,
# so the drive stays continuous) at period $3 s, lockstep $4.
manifest() {
    "$python" - "$@" "$work" <<'EOF'
import json, os, sys
sim, order, period, lockstep, work = sys.argv[1:6]
rows = [l.split() for l in open(f"{sim}/poses_gt.txt") if not l.startswith("#")]
stamps = [float(r[0]) for r in rows]
names = sorted(os.listdir(f"{sim}/scans"))
files = []
for k, name in enumerate(names):
    raw = open(f"{sim}/scans/{name}", "rb").read()
    head, body = raw.split(b"DATA binary\n", 1)
    header = dict(l.split(None, 1) for l in head.decode().splitlines() if l and l[0] != "#")
    width = int(header["POINTS"])
    step = sum(int(s) for s in header["SIZE"].split())
    path = f"{work}/cloud{k}.bin"
    open(path, "wb").write(body[: width * step])
    files.append((path, width, step))
if order == "once":
    sequence = list(range(len(files)))
else:
    n = int(order.split(":")[1])
    cycle = list(range(len(files))) + list(range(len(files) - 2, 0, -1))
    sequence = [cycle[i % len(cycle)] for i in range(n)]
dt = stamps[1] - stamps[0]
clouds = [{
    "stamp": stamps[0] + i * dt, "frame_id": "lidar",
    "fields": [["x", 0, 7, 1], ["y", 4, 7, 1], ["z", 8, 7, 1]],
    "point_step": files[k][2], "width": files[k][1], "data": files[k][0],
} for i, k in enumerate(sequence)]
json.dump({"domain": 0, "wait_s": 60, "timeout_s": 30, "clouds": clouds,
           "period_s": float(period), "lockstep": lockstep == "1", "linger_s": 3.0},
          sys.stdout)
EOF
}

# The node on map "court" of this prefix; its pid in $node.
start_node() {
    printf '[server]\nmap-name = "court"\niceoryx-prefix = "%s"\n[qos]\npoints-depth = %s\n' \
        "$prefix" "${1:-5}" >"$work/ros2.toml"
    ROS_DISTRO=jazzy KFMAP_LOG=${KFMAP_LOG:-info} "$bin/kfmap-ros2" --config "$work/ros2.toml" \
        >"$work/node.out" 2>"$work/node.err" &
    node=$!
    pids+=("$node")
    wait_ready "$work/node.out" "ready:"
}

stop_node() {
    kill -TERM "$node"
    wait "$node" || true
}

case "$mode" in
latency)
    rounds=${2:-3}
    "$bin/kfmap" simulate --preset courtyard --seconds 6 --beams 16 --out "$work/sim" >/dev/null
    "$bin/kfmap" bake --dataset "$work/sim" --out "$work/court.kfmap" >/dev/null
    "$bin/kfmap" serve --map "$work/court.kfmap" --map-name court --iceoryx-prefix "$prefix" \
        >"$work/serve.out" 2>&1 &
    pids+=($!)
    wait_ready "$work/serve.out" "ready:"
    manifest "$work/sim" once 0 1 >"$work/latency.json"
    echo "round  kfmap localize p50 (ms)  kfmap-ros2 p50 (ms)  difference (ms)  node: prepare / publish p50 (ms)"
    for round in $(seq "$rounds"); do
        "$bin/kfmap" localize --map-name court --iceoryx-prefix "$prefix" --dataset "$work/sim" \
            --rate 0 --json-lines --no-imu >"$work/localize.jsonl" 2>/dev/null
        KFMAP_LOG=debug start_node
        timeout 300 "$python" "$here/tests/support/dds_peer.py" "$work/latency.json" \
            "$work/peer.jsonl" >"$work/peer.out" 2>"$work/peer.err"
        stop_node
        "$python" - "$work" "$round" <<'EOF'
import json, re, sys
work, round_ = sys.argv[1:3]
p50 = lambda v: sorted(v)[len(v) // 2]
local = [json.loads(l)["latency_ms"] for l in open(f"{work}/localize.jsonl") if '"index"' in l]
records = [json.loads(l) for l in open(f"{work}/peer.jsonl")]
node = [float(r["values"]["latency_ms"]) for r in records
        if r["topic"] == "diagnostics" and "latency_ms" in r["values"]]
steps = [dict((k, float(v)) for k, v in re.findall(r"(\w+_ms)=([\d.]+)", l))
         for l in open(f"{work}/node.err") if "localized" in l and "prepare_ms" in l]
prepare = p50([s["queued_ms"] + s["prepare_ms"] for s in steps])
publish = p50([s["publish_ms"] for s in steps])
print(f"{round_:>5}  {p50(local):>24.2f}  {p50(node):>19.2f}  {p50(node) - p50(local):>+15.2f}"
      f"  {prepare:.2f} / {publish:.2f}   ({len(local)} / {len(node)} clouds)")
EOF
    done
    ;;
soak)
    seconds=${2:-60}
    hz=${3:-10}
    beams=${4:-64}
    sim_seconds=10
    "$bin/kfmap" simulate --preset courtyard --seconds "$sim_seconds" --beams "$beams" \
        --out "$work/sim" >/dev/null
    # The map from a 16-beam drive of the same courtyard (a quicker bake).
    "$bin/kfmap" simulate --preset courtyard --seconds "$sim_seconds" --beams 16 \
        --out "$work/sim16" >/dev/null
    "$bin/kfmap" bake --dataset "$work/sim16" --out "$work/court.kfmap" >/dev/null
    "$bin/kfmap" serve --map "$work/court.kfmap" --map-name court --iceoryx-prefix "$prefix" \
        >"$work/serve.out" 2>&1 &
    server=$!
    pids+=("$server")
    wait_ready "$work/serve.out" "ready:"
    count=$((seconds * hz))
    period=$(python3 -c "print(1.0 / $hz)")
    manifest "$work/sim" "pingpong:$count" "$period" 0 >"$work/soak.json"
    points=$("$python" -c "import json; c=json.load(open('$work/soak.json'))['clouds']; print(sum(x['width'] for x in c) // len(c))")
    start_node 5
    rss() { awk '/^VmRSS/ {print $2}' "/proc/$1/status" 2>/dev/null || echo 0; }
    : >"$work/memory.tsv"
    (
        start=$(date +%s.%N)
        while kill -0 "$node" 2>/dev/null; do
            now=$(date +%s.%N)
            echo "$(python3 -c "print(f'{$now - $start:.1f}')") $(rss "$node") $(rss "$server")" \
                >>"$work/memory.tsv"
            sleep 1
        done
    ) &
    sampler=$!
    timeout $((seconds * 3 + 120)) "$python" "$here/tests/support/dds_peer.py" \
        "$work/soak.json" "$work/peer.jsonl" >"$work/peer.out" 2>"$work/peer.err"
    stop_node
    wait "$sampler" || true
    "$python" - "$work" "$count" "$hz" "$points" <<'EOF'
import json, re, sys
work, count, hz, points = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
records = [json.loads(l) for l in open(f"{work}/peer.jsonl")]
diag = [r for r in records if r["topic"] == "diagnostics" and "status" in r["values"]]
statuses = {}
for r in diag:
    statuses[r["values"]["status"]] = statuses.get(r["values"]["status"], 0) + 1
latency = sorted(float(r["values"]["latency_ms"]) for r in diag if "latency_ms" in r["values"])
stopped = [l for l in open(f"{work}/node.err") if l.startswith("stopped:")]
# Samples while the node ran (its /proc entry gone: 0).
memory = [m for m in (tuple(map(float, l.split())) for l in open(f"{work}/memory.tsv")
                      if l.strip()) if m[1] > 0]
print(f"clouds sent: {count} at {hz} Hz, about {points} points each")
print("node: " + (stopped[0].strip() if stopped else "no summary line"))
print(f"poses answered: {len(diag)} ({', '.join(f'{v} {k}' for k, v in sorted(statuses.items()))})")
if latency:
    q = lambda f: latency[min(len(latency) - 1, int(f * len(latency)))]
    print(f"cloud -> pose: p50 {q(0.5):.1f} ms, p90 {q(0.9):.1f} ms, p99 {q(0.99):.1f} ms, "
          f"max {latency[-1]:.1f} ms")
print("resident memory (MB), node / server:")
for t, node, server in memory:
    if abs(t - round(t / 10) * 10) < 0.6 or (t, node, server) == memory[-1]:
        print(f"  {t:6.1f} s  {node / 1024:8.1f}  {server / 1024:8.1f}")
warm = [m for m in memory if m[0] >= 10]
if warm:
    print(f"after 10 s: node {min(m[1] for m in warm) / 1024:.1f}-{max(m[1] for m in warm) / 1024:.1f} MB,"
          f" server {min(m[2] for m in warm) / 1024:.1f}-{max(m[2] for m in warm) / 1024:.1f} MB")
EOF
    ;;
*)
    echo "usage: tools/ros2_bench.sh latency [ROUNDS] | soak [SECONDS [HZ [BEAMS]]]" >&2
    exit 2
    ;;
esac
