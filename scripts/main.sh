#!/usr/bin/env bash
# Set everything up, then run the RLHF loop at small scale on the bundled nuScenes data (../shared/data, or
# TRAFFICRLHF_DATA): the 4 s CTG proposes 5 futures for train contexts, stand-in annotators pick the most
# realistic, a reward model learns from those choices and is probed, CTG's steering head is aligned briefly against
# it, and the base, this run and the committed aligned CTG are evaluated in closed loop on the first 100
# long-enough val scenes with seeds 0-2 (the report gives each model's change against the base with an interval).
# Everything lands in out/main/ (OUT to change it); out/main/report.md is the summary.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
OUT=${OUT:-out/main}
T=.venv/bin/trafficrlhf
rm -rf "$OUT" && mkdir -p "$OUT"
step() { echo; echo "== [$(date +%H:%M:%S)] $*"; }
step "1-4/5 the RLHF loop (scripts/main.toml): candidates from ctg-4s on train contexts, stand-in annotators, a reward model with probes, a brief alignment"
$T rlhf --config scripts/main.toml --out "$OUT/loop"
$T feedback render --db "$OUT/loop/feedback.sqlite" --campaign round0 --with-log --out "$OUT/candidates.png"
step "5/5 closed-loop evaluation on 100 val scenes, seeds 0-2: base, this run, the committed aligned CTG"
$T evaluate --checkpoint ctg-4s --guidance no_collision --scenes 100 --seeds 0,1,2 --render-worst 1 --out "$OUT/eval_base"
$T evaluate --checkpoint "$OUT/loop/round_0/aligned" --guidance no_collision --scenes 100 --seeds 0,1,2 --render-worst 1 \
  --reward-model "$OUT/loop/round_0/reward_model" --out "$OUT/eval_this_run"
$T evaluate --checkpoint ctg-aligned --guidance no_collision --scenes 100 --seeds 0,1,2 --render-worst 1 --out "$OUT/eval_committed"
$T compare "$OUT"/eval_base/seed_* "$OUT"/eval_this_run/seed_* "$OUT"/eval_committed/seed_* | tee "$OUT/comparison.md"
$T report "$OUT" --run "base=$OUT/eval_base" --run "this run=$OUT/eval_this_run" \
  --run "committed aligned=$OUT/eval_committed" --reward-model "$OUT/loop/round_0/reward_model" --align "$OUT/loop/round_0/aligned" \
  --title "TrafficRLHF loop on nuScenes (small scale)"
echo "main job done: $OUT/report.md"
