#!/bin/sh
# Builds fdpeer, the Fast DDS interop peer of kfmap-ros2, from ros2_msgs.idl and
# fdpeer.cpp into $FASTDDS_BUILD (default ${TMPDIR:-/tmp}/kfmap-fastdds; nothing is
# written into the repository).
# Needs (Debian bookworm): apt-get install -y libfastrtps-dev fastddsgen g++
# (Fast DDS 2.9.1, Fast CDR 1.0.26, fastddsgen 2.3.0). About 7 s on 2 cores.
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
BUILD=${FASTDDS_BUILD:-${TMPDIR:-/tmp}/kfmap-fastdds}
for tool in fastddsgen g++; do
    command -v "$tool" >/dev/null || { echo "build.sh: $tool not found (apt-get install -y libfastrtps-dev fastddsgen g++)" >&2; exit 1; }
done
mkdir -p "$BUILD/gen" "$BUILD/obj" "$BUILD/bin"
if [ ! -f "$BUILD/gen/ros2_msgs.cxx" ] || [ "$HERE/ros2_msgs.idl" -nt "$BUILD/gen/ros2_msgs.cxx" ]; then
    cp "$HERE/ros2_msgs.idl" "$BUILD/gen/"
    (cd "$BUILD/gen" && fastddsgen -replace ros2_msgs.idl >/dev/null)
fi
CXX="nice -n 10 g++ -std=c++17 -O2 -g0 -I$BUILD/gen"
for f in ros2_msgs ros2_msgsPubSubTypes; do
    if [ ! -f "$BUILD/obj/$f.o" ] || [ "$BUILD/gen/$f.cxx" -nt "$BUILD/obj/$f.o" ]; then
        $CXX -c "$BUILD/gen/$f.cxx" -o "$BUILD/obj/$f.o"
    fi
done
# Rebuilt when the source is newer than the binary (4 CPU-s of every test run otherwise).
if [ ! -x "$BUILD/bin/fdpeer" ] || [ "$HERE/fdpeer.cpp" -nt "$BUILD/bin/fdpeer" ] \
    || [ "$BUILD/obj/ros2_msgs.o" -nt "$BUILD/bin/fdpeer" ]; then
    $CXX -Wall -c "$HERE/fdpeer.cpp" -o "$BUILD/obj/fdpeer.o"
    $CXX "$BUILD/obj/fdpeer.o" "$BUILD/obj/ros2_msgs.o" "$BUILD/obj/ros2_msgsPubSubTypes.o" \
        -o "$BUILD/bin/fdpeer" -lfastrtps -lfastcdr -lpthread
fi
echo "$BUILD/bin/fdpeer"
