#!/usr/bin/env bash
# Runs our estimator benchmark and, right after it on the same cores, the
# jit-compiled JAX peer of ../shared/peers/jax (SPEC §10), and prints both.
# The peer is a benchmark only: nothing in the build or the tests needs it.
#
#   bash benches/side_by_side.sh            # about 12 minutes on 2 cores
#
# The peer's virtualenv lives outside shared/ (read-only): $JAX_PEER_VENV,
# default $HOME/jax-peer, created on first use from the peer's pinned
# requirements. Run it on an otherwise idle machine (pause background jobs with
# `kill -STOP`), and compare ratios, not absolute times.
set -euo pipefail
cd "$(dirname "$0")/.."
peer=../shared/peers/jax
venv=${JAX_PEER_VENV:-$HOME/jax-peer}
out=${OUT:-target/side-by-side}
mkdir -p "$out"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install -q -r "$peer/requirements.txt"
fi
lscpu | grep -E "Model name|^CPU\(s\)" | tee "$out/cpu.txt"
cargo bench --bench estimators | tee "$out/ours.txt"
"$venv/bin/python" "$peer/bench.py" --configs A_T25,B_T50 --out "$out/jax.jsonl"
"$venv/bin/python" "$peer/summarize.py" "$out/jax.jsonl" | tee "$out/jax.md"
echo "written: $out/ours.txt, $out/jax.jsonl, $out/jax.md"
