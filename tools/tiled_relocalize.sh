#!/usr/bin/env bash
# Relocalization over a tile set against the merged map, through the commands a user
# types (docs/DESIGN.md#notes-tiles): simulates the courtyard drive the tiled test
# uses, bakes it into tiles of --tile-size metres (default 10; the test's) with the
# merged map kept, serves the tiles on four emulated hosts (a `kfmap serve --tiles
# --only` + `kfmap gateway` pair each, own iceoryx2 prefix and port) and the merged map
# on a fifth server, then relocalizes every 24th scan with `kfmap relocalize --remote`
# over the tiles and with `kfmap relocalize` on the merged map, and prints both
# latencies. Runs itself inside a private network namespace (`unshare -rn`: only
# loopback). Times are printed, never asserted; every host shares this machine's cores.
#
#   tools/tiled_relocalize.sh [TILE_SIZE_M [ROUNDS]]   (kfmap from target/release)
#
# KFMAP_LOG=debug logs every request; KEEP_LOGS=DIR copies the servers' and gateways'
# logs there before the work folder is removed.
set -euo pipefail
tile_size=${1:-10}
rounds=${2:-3}
here=$(cd "$(dirname "$0")/.." && pwd)
kfmap=${KFMAP:-$here/target/release/kfmap}
if [ -z "${KFMAP_IN_NETNS:-}" ]; then
    exec unshare -rn env KFMAP_IN_NETNS=1 KFMAP="$kfmap" KFMAP_LOG="${KFMAP_LOG:-}" \
        KEEP_LOGS="${KEEP_LOGS:-}" bash "$0" "$tile_size" "$rounds"
fi
ip link set lo up
work=$(mktemp -d)
prefix="tiledreloc$$"
pids=()
cleanup() {
    kill "${pids[@]}" 2>/dev/null || true
    wait 2>/dev/null || true
    if [ -n "${KEEP_LOGS:-}" ]; then cp "$work"/*.out "$KEEP_LOGS"/ 2>/dev/null || true; fi
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

"$kfmap" simulate --preset courtyard --seconds 36 --beams 16 --speed 8 --out "$work/sim" >/dev/null
"$kfmap" bake --dataset "$work/sim" --out "$work/tiles" --tile-size "$tile_size" --halo 10 \
    --keep-merged | grep "tiles of"
mapfile -t ids < <(sed -n 's/^id = "\(.*\)"/\1/p' "$work/tiles/tiles.toml")
for h in 0 1 2 3; do
    only=$(for ((i = h; i < ${#ids[@]}; i += 4)); do printf '%s,' "${ids[$i]}"; done)
    only=${only%,}
    [ -n "$only" ] || continue
    "$kfmap" serve --tiles "$work/tiles" --only "$only" --map-name court \
        --iceoryx-prefix "$prefix$h" >"$work/serve$h.out" 2>&1 &
    pids+=($!)
    wait_ready "$work/serve$h.out" "ready:"
    printf '[gateway]\nrequest-timeout-s = 120.0\n' >"$work/gateway$h.toml"
    "$kfmap" gateway --config "$work/gateway$h.toml" --tiles "$work/tiles" --only "$only" \
        --map-name court --iceoryx-prefix "$prefix$h" \
        --listen "tcp/127.0.0.1:$((17460 + h))" >"$work/gateway$h.out" 2>&1 &
    pids+=($!)
    wait_ready "$work/gateway$h.out" "ready: gateway"
    endpoints+=("tcp/127.0.0.1:$((17460 + h))")
done
"$kfmap" serve --map "$work/tiles/merged.kfmap" --map-name merged \
    --iceoryx-prefix "${prefix}m" >"$work/merged.out" 2>&1 &
pids+=($!)
wait_ready "$work/merged.out" "ready:"

mapfile -t scans < <(ls "$work"/sim/scans/* | awk 'NR % 24 == 1')
remote=$(IFS=,; echo "${endpoints[*]}")
# Rounds alternate the tiles and the merged map, so that a drift of this machine's
# speed (up to 2x between hours) falls on both alike.
for round in $(seq "$rounds"); do
    "$kfmap" relocalize --remote "$remote" --map-name court --timeout 120 --json "${scans[@]}" \
        >"$work/tiled$round.jsonl"
    "$kfmap" relocalize --map-name merged --iceoryx-prefix "${prefix}m" --timeout 120 --json \
        "${scans[@]}" >"$work/merged$round.jsonl"
done
python3 - "$work" "$rounds" "${#ids[@]}" <<'EOF'
import json, sys
work, rounds, tiles = sys.argv[1], int(sys.argv[2]), sys.argv[3]
def read(path):
    return [json.loads(l) for l in open(path)]
totals = []
for r in range(1, rounds + 1):
    tiled, merged = read(f"{work}/tiled{r}.jsonl"), read(f"{work}/merged{r}.jsonl")
    same = sum(a["status"] == b["status"] for a, b in zip(tiled, merged))
    found = sum(b["status"] == "found" for b in merged)
    t = sum(a["latency_ms"] for a in tiled)
    m = sum(b["latency_ms"] for b in merged)
    totals.append((t, m))
    print(f"round {r}: {len(tiled)} scans over {tiles} tiles ({found} found on the merged map), "
          f"{same} with the merged map's status; {t:.0f} ms against {m:.0f} ms ({t / m:.2f}x)")
t, m = sum(a for a, _ in totals), sum(b for _, b in totals)
print(f"{rounds} rounds: {t:.0f} ms over the tiles against {m:.0f} ms on the merged map ({t / m:.2f}x)")
EOF
