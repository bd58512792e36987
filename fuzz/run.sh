#!/usr/bin/env bash
# Runs every fuzz target (or the ones named after SECONDS) for SECONDS each,
# at low priority (nice 10), JOBS targets at a time (default 1: one after the
# other), seeded from seeds/<target>/ and growing corpus/<target>/. libFuzzer
# runs in fork mode and goes on past a crash, hang (over 10 s) or
# out-of-memory (over 2 GB), leaving each such input in artifacts/<target>/.
# Each target's log is logs/<target>.log; its last `#N: cov: ... ft: ...`
# line holds the executions, coverage and features reached.
#
#   fuzz/run.sh SECONDS [TARGET...]      (JOBS=2 fuzz/run.sh ... for two at a time)
set -u
cd "$(dirname "$0")"
seconds=${1:?usage: fuzz/run.sh SECONDS [TARGET...]}
shift
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(params checkpoint report dataset kitti_labels kitti_detections kitti_calib kitti_poses)
fi
jobs=${JOBS:-1}
# Built once, then the binaries are run directly: sources edited during a run
# do not rebuild (or break) the targets still to come. NOBUILD=1 runs the
# binaries already built.
[ -n "${NOBUILD:-}" ] || cargo +nightly fuzz build -O || exit 1
bin=target/x86_64-unknown-linux-gnu/release
mkdir -p logs

run_one() {
    local t=$1
    mkdir -p "corpus/$t" "artifacts/$t"
    cp -n seeds/"$t"/* "corpus/$t/" 2>/dev/null
    nice -n 10 "$bin/$t" "corpus/$t" \
        -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -max_len=65536 \
        -fork=1 -ignore_crashes=1 -ignore_ooms=1 -ignore_timeouts=1 \
        -artifact_prefix="artifacts/$t/" >"logs/$t.log" 2>&1
    echo "== $t ($seconds s): $(grep -E '^#[0-9]+' "logs/$t.log" | tail -1)"
    ls "artifacts/$t"
}

for t in "${targets[@]}"; do
    while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do
        wait -n
    done
    run_one "$t" &
done
wait
