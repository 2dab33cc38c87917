#!/bin/sh
# One Fast DDS interop run inside a private network namespace (only lo, multicast on
# unless LO_MULTICAST=0): `kfmap serve` with MAP, `kfmap-ros2` with NODE_CONFIG, and
# fdpeer (built by build.sh) with the given arguments. Binaries from target/release.
#   MAP=m.kfmap tools/fastdds/run.sh OUTDIR [fdpeer args...]
# Environment:
#   MAP=FILE            the map `kfmap serve` serves, as "c" (required)
#   NODE_CONFIG=FILE    the node's config (default tools/fastdds/ros2.toml)
#   PEER_ENV="FASTRTPS_DEFAULT_PROFILES_FILE=tools/fastdds/xml/big_buffers.xml"
#   PEER_FIRST=1        start the peer before the node (else the node first)
#   LATE_PEER=ARGS      after the peer ends, a second fdpeer with ARGS (a late joiner)
#   RUN_TIMEOUT=S       bound on the whole run (default 180)
# Writes OUTDIR/{serve,node,peer,late}.{out,log}, udp_snmp.txt (RcvbufErrors: datagrams
# dropped for a full socket buffer), node_mem.txt; prints the peers' summary lines.
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
REPO=$(cd "$HERE/../.." && pwd)
BIN=$REPO/target/release
PEER=${FASTDDS_BUILD:-${TMPDIR:-/tmp}/kfmap-fastdds}/bin/fdpeer
[ -n "${MAP:-}" ] || { echo "run.sh: set MAP to a baked map" >&2; exit 2; }
[ -x "$PEER" ] || { echo "run.sh: $PEER missing: run tools/fastdds/build.sh" >&2; exit 2; }
OUT=$1; shift
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
PEER_ARGS="$*"
NODE_CONFIG=${NODE_CONFIG:-$HERE/ros2.toml}
export BIN PEER OUT PEER_ARGS NODE_CONFIG MAP
exec timeout -k 5 "${RUN_TIMEOUT:-180}" unshare -rn sh -c '
set -u
ip link set lo up
[ "${LO_MULTICAST:-1}" = 1 ] && ip link set lo multicast on
cd "$OUT"
wait_line() { # file prefix seconds
  i=0; while ! grep -q "^$2" "$1" 2>/dev/null; do
    i=$((i+1)); [ $i -gt $(($3*20)) ] && { echo "timeout waiting for $1" >&2; return 1; }; sleep 0.05; done; }
"$BIN/kfmap" serve --map "$MAP" --map-name c --iceoryx-prefix fd_ >serve.out 2>serve.log &
SERVE=$!
wait_line serve.out ready: 60 || { cat serve.log; kill $SERVE; exit 1; }
start_node() {
  ROS_DISTRO=jazzy "$BIN/kfmap-ros2" --config "$NODE_CONFIG" >node.out 2>node.log &
  NODE=$!
  wait_line node.out ready: 30 || { cat node.log; exit 1; }
}
if [ "${PEER_FIRST:-0}" = 1 ]; then
  env ${PEER_ENV:-} timeout 150 "$PEER" $PEER_ARGS >peer.out 2>peer.log &
  PEER_PID=$!
  sleep 2
  start_node
else
  start_node
  sleep 1
  env ${PEER_ENV:-} timeout 150 "$PEER" $PEER_ARGS >peer.out 2>peer.log &
  PEER_PID=$!
fi
wait $PEER_PID; echo "peer exit $?" >>peer.log
if [ -n "${LATE_PEER:-}" ]; then
  env ${PEER_ENV:-} timeout 150 "$PEER" $LATE_PEER >late.out 2>late.log || echo "late exit $?" >>late.log
fi
grep "^Udp:" /proc/net/snmp >udp_snmp.txt
ps -o pid,rss,vsz,args -p $NODE >node_mem.txt 2>/dev/null || true
kill -TERM $NODE; i=0; while kill -0 $NODE 2>/dev/null && [ $i -lt 100 ]; do sleep 0.1; i=$((i+1)); done
kill -KILL $NODE 2>/dev/null || true
kill -TERM $SERVE; wait $SERVE 2>/dev/null || true
grep -h "\"summary\"" peer.out late.out 2>/dev/null || true
'
