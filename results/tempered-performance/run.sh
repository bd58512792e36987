#!/usr/bin/env bash
# The default path's benchmark (README.md): each run times filter and PF-SEFI on
# the bootstrap and on the tempered filter, interleaved in one process, and
# measures PF-SEFI's precision at the truth on both over 4 seeds; the tempered
# rows' settings vary by run, to weigh the levers that change the move schedule.
# Run it on an idle machine; compare the ratios within a file.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=results/tempered-performance
cargo build --release --bench estimators
bench=$(ls -t target/release/deps/estimators-* | grep -v '\.d$' | head -1)
run() {
    local size=$1 name=$2
    shift 2
    nice -n 10 "$bench" --default-path --quick --no-memory --no-wait --size "$size" "$@" > "$out/$size-$name.txt"
}
run A default
run A lookback-only-moves-1 --lookback-only true --moves 1
run A moves-1 --moves 1
run A ess-0.3 --ess 0.3
run A lookback-only --lookback-only true
run A lookback-only-moves-1-ess-0.3 --lookback-only true --moves 1 --ess 0.3
run B default
run B lookback-only-moves-1-ess-0.3 --lookback-only true --moves 1 --ess 0.3
# (The z-*.txt files: the same runs of A and B default and lean, from the bench once it
# printed the score's z at the truth; `run` above now writes that into every file.)
