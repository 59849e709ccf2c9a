#!/usr/bin/env bash
# The coarse stages' length against the default's 300 + 300 (docs/benchmarks/training.md, "The coarse
# stages' length"): `gvae train` of the plush (two seeds) and of two validation scenes with the coarse
# stages at COUNTS, the last stage as the default trains it (1,000 planned, then to convergence).
# Usage: bash tools/coarse_stage_trials.sh RUNS SCENES "150 150" "600 600" ...   (four runs at once)
set -euo pipefail
runs=$1; scenes=$2; shift 2
mkdir -p "$runs"
for counts in "$@"; do
    name=${counts// /_}
    for seed in 0 1; do
        .venv/bin/gvae train ../shared/captures/plush --out "$runs/plush_s${seed}_$name" --test-every 8 --downscale 4 \
            --threads 1 --seed "$seed" --iterations $counts 1000 --converge > "$runs/plush_s${seed}_$name.log" 2>&1 &
    done
    for scene in chair tableware; do
        .venv/bin/gvae train "$scenes/$scene" --out "$runs/${scene}_$name" --threads 1 --iterations $counts 1000 \
            --converge > "$runs/${scene}_$name.log" 2>&1 &
    done
    wait
done
