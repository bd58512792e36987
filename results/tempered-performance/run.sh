#!/usr/bin/env bash
# The default path's benchmark and the tempered filter's settings weighed against
# it (README.md): each run times filter and PF-SEFI on the bootstrap and the
# tempered filter, interleaved, and measures PF-SEFI's precision at the truth on
# both, so every ratio below compares like with like within one run.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=results/tempered-performance
cargo build --release --bench estimators
run() {
    local name=$1
    shift
    nice -n 10 cargo bench --bench estimators -- --default-path "$@" > "$out/$name.txt"
}
run default
run moves-1 --moves 1
run lookback-only --lookback-only true
run lookback-only-moves-1 --lookback-only true --moves 1
run ess-0.3 --ess 0.3
