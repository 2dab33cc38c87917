#!/usr/bin/env bash
# Runs every cargo-fuzz target in fuzz/ for a bounded time and reports, per target,
# the executions libFuzzer made and what it found. Exits non-zero when any target
# crashes (panic, timeout, out-of-memory, sanitizer report) or does not build.
# Not part of CI: needs the nightly toolchain and cargo-fuzz.
#
# Usage: tools/fuzz.sh [SECONDS] [TARGET[=SECONDS]...]
#   SECONDS          time per target (default: $FUZZ_SECONDS, else 60)
#   TARGET=SECONDS   run only the named targets, each for its own time if given
#                    (default: every target of `cargo fuzz list`)
# Environment:
#   FUZZ_SECONDS     default time per target, seconds (60)
#   FUZZ_TIMEOUT     one input running longer than this is a crash, seconds (10)
#   FUZZ_RSS_MB      memory limit (RSS and single malloc) in MiB (2048)
#   FUZZ_LOG_DIR     where each target's full libFuzzer log goes (fuzz/target/fuzz-logs)
#   FUZZ_BUILD_ARGS  extra `cargo fuzz build` flags, e.g. "--sanitizer none"
#   FUZZ_ARGS        extra libFuzzer flags, e.g. "-fork=1 -ignore_crashes=1" to go on
#                    past a known crash (crashes still make the exit status non-zero)
#   KFMAP_FUZZ_PANIC_ONLY=1  targets check for panics only, not the readers'
#                    write/read round trips and invariants
# Examples:
#   tools/fuzz.sh                                  # every target, 60 s each
#   FUZZ_SECONDS=300 tools/fuzz.sh request         # one target, 5 minutes
#   tools/fuzz.sh 60 request=120 read_pcd=120 read_ply=120 trajectory
# A crash leaves its input in fuzz/artifacts/<target>/; reproduce it with
#   cargo +nightly fuzz run <target> fuzz/artifacts/<target>/<file>
# and minimize it with
#   cargo +nightly fuzz tmin <target> fuzz/artifacts/<target>/<file>
set -uo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
fuzz_dir="$root/fuzz"
seconds="${FUZZ_SECONDS:-60}"
timeout_s="${FUZZ_TIMEOUT:-10}"
rss_mb="${FUZZ_RSS_MB:-2048}"
log_dir="${FUZZ_LOG_DIR:-$fuzz_dir/target/fuzz-logs}"
read -r -a build_args <<<"${FUZZ_BUILD_ARGS:-}"
read -r -a fuzz_args <<<"${FUZZ_ARGS:-}"

die() {
    echo "fuzz.sh: $*" >&2
    exit 2
}

is_seconds() { [[ "$1" =~ ^[0-9]+$ && "$1" -gt 0 ]]; }

if [[ $# -gt 0 ]] && is_seconds "$1"; then
    seconds="$1"
    shift
fi
is_seconds "$seconds" || die "time per target must be a positive number of seconds, got '$seconds'"
is_seconds "$timeout_s" || die "FUZZ_TIMEOUT must be a positive number of seconds, got '$timeout_s'"
is_seconds "$rss_mb" || die "FUZZ_RSS_MB must be a positive number of MiB, got '$rss_mb'"

# The tools this needs, with a message saying how to get each.
command -v cargo >/dev/null 2>&1 || die "cargo is not installed (https://rustup.rs)"
if ! cargo +nightly --version >/dev/null 2>&1; then
    die "the nightly toolchain is missing (cargo-fuzz needs it): rustup toolchain install nightly"
fi
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    die "cargo-fuzz is missing: cargo install cargo-fuzz"
fi
[[ -f "$fuzz_dir/Cargo.toml" ]] || die "no fuzz/Cargo.toml under $root"

cd "$root" || die "cannot enter $root"
fuzz() { cargo +nightly fuzz "$@"; }

mapfile -t all_targets < <(fuzz list --fuzz-dir "$fuzz_dir")
[[ ${#all_targets[@]} -gt 0 ]] || die "cargo fuzz list found no targets in $fuzz_dir"

targets=()
declare -A target_seconds=()
if [[ $# -eq 0 ]]; then
    targets=("${all_targets[@]}")
else
    for arg in "$@"; do
        name="${arg%%=*}"
        if [[ "$arg" == *=* ]]; then
            is_seconds "${arg#*=}" || die "bad time in '$arg' (want TARGET=SECONDS)"
            target_seconds[$name]="${arg#*=}"
        fi
        printf '%s\n' "${all_targets[@]}" | grep -qx -- "$name" ||
            die "unknown target '$name'; targets: ${all_targets[*]}"
        targets+=("$name")
    done
fi

echo "== building ${#all_targets[@]} fuzz targets (cargo +nightly fuzz build ${build_args[*]})"
if ! fuzz build --fuzz-dir "$fuzz_dir" "${build_args[@]}"; then
    echo "fuzz.sh: the fuzz targets do not build" >&2
    exit 2
fi

# Run the binaries just built rather than `cargo fuzz run`, which rebuilds first: every
# target then fuzzes the same build of the sources, and the time is fuzzing time.
host=$(rustc +nightly -vV | sed -n 's/^host: //p')
profile=release
for a in "${build_args[@]}"; do
    case "$a" in
    -D | --dev) profile=debug ;;
    --target=*) host="${a#--target=}" ;;
    esac
done
bin_dir="$fuzz_dir/target/$host/$profile"
export ASAN_OPTIONS="${ASAN_OPTIONS:-detect_odr_violation=0}"

mkdir -p "$log_dir" || die "cannot create $log_dir"
summary=()
failed=()
for target in "${targets[@]}"; do
    s="${target_seconds[$target]:-$seconds}"
    corpus="$fuzz_dir/corpus/$target"
    log="$log_dir/$target.log"
    mkdir -p "$corpus"
    echo
    echo "== $target: ${s} s (corpus $corpus, log $log)"
    start=$(date +%s)
    artifacts="$fuzz_dir/artifacts/$target"
    mkdir -p "$artifacts"
    [[ -x "$bin_dir/$target" ]] || die "built target not found: $bin_dir/$target"
    marker="$log_dir/$target.start"
    : >"$marker"
    "$bin_dir/$target" -artifact_prefix="$artifacts/" \
        -max_total_time="$s" -print_final_stats=1 -timeout="$timeout_s" \
        -rss_limit_mb="$rss_mb" -malloc_limit_mb="$rss_mb" "${fuzz_args[@]}" "$corpus" >"$log" 2>&1
    rc=$?
    wall=$(($(date +%s) - start))
    # libFuzzer's last status line ("#N DONE cov: ..." or the line of the crash) and
    # its final stats.
    # (-fork prints "#N: cov: ... oom/timeout/crash: a/b/c" lines instead.)
    grep -E '^#[0-9]+([[:space:]]+DONE|: cov:)' "$log" | tail -n 1
    grep -E '^(stat::|Done [0-9]+ runs)' "$log"
    execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -n 1)
    if [[ -z "$execs" ]]; then
        execs=$(grep -oE '^#[0-9]+' "$log" | tail -n 1 | tr -d '#')
    fi
    rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -n 1)
    if [[ -z "$rate" && "$execs" =~ ^[0-9]+$ && $wall -gt 0 ]]; then
        rate=$((execs / wall))
    fi
    units=$(find "$corpus" -type f | wc -l)
    # With -fork and -ignore_crashes libFuzzer exits 0 after crashes: count what it
    # wrote to the artifacts directory during this run too.
    mapfile -t new_artifacts < <(find "$artifacts" -type f -newer "$marker" \
        \( -name 'crash-*' -o -name 'oom-*' -o -name 'timeout-*' -o -name 'leak-*' \))
    if [[ $rc -eq 0 && ${#new_artifacts[@]} -eq 0 ]]; then
        status="ok"
    else
        kind=$(grep -oE 'ERROR: libFuzzer: [a-z-]+|panicked at [^ ]+|ERROR: AddressSanitizer: [a-z-]+' "$log" | head -n 1)
        artifact=$(grep -oE '(Test unit|artifact) written to [^ ]+' "$log" | head -n 1 | awk '{print $NF}')
        [[ -z "$artifact" && ${#new_artifacts[@]} -gt 0 ]] && artifact="${new_artifacts[0]}"
        status="CRASH (exit $rc, ${#new_artifacts[@]} new input(s)${kind:+: $kind})"
        failed+=("$target")
        echo "-- $target crashed; the end of its log:"
        grep -E -A 12 'panicked at|ERROR: (libFuzzer|AddressSanitizer|LeakSanitizer)' "$log" | head -n 40
        [[ -n "$artifact" ]] && echo "-- input: $artifact"
        [[ -n "$artifact" ]] && echo "-- reproduce: cargo +nightly fuzz run $target $artifact"
    fi
    summary+=("$(printf '%-12s %12s execs %6s s %10s exec/s %6s corpus  %s' \
        "$target" "${execs:-?}" "$wall" "${rate:-?}" "$units" "$status")")
done

echo
echo "== summary (time per target: default ${seconds} s)"
printf '%s\n' "${summary[@]}"
if [[ ${#failed[@]} -gt 0 ]]; then
    echo "fuzz.sh: ${#failed[@]} target(s) crashed: ${failed[*]} (inputs in fuzz/artifacts/)" >&2
    exit 1
fi
echo "fuzz.sh: no crashes"
