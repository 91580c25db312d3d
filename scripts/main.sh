#!/usr/bin/env bash
# Set everything up, then run the RLHF loop at small scale on the bundled nuScenes data (../shared/data, or
# TRAFFICRLHF_DATA): the 4 s CTG proposes 5 futures for train contexts, a stand-in annotator picks the most
# realistic, a reward model learns from those choices, CTG is aligned briefly against it, and the base, this run
# and the committed aligned CTG are evaluated in closed loop on the first 100 long-enough val scenes.
# Everything lands in out/main/ (OUT to change it); out/main/report.md is the summary.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
OUT=${OUT:-out/main}
CONTEXTS=${CONTEXTS:-16}
T=.venv/bin/trafficrlhf
rm -rf "$OUT" && mkdir -p "$OUT"
step() { echo; echo "== [$(date +%H:%M:%S)] $*"; }
step "1/5 candidates: ctg-4s proposes 5 futures (4 s, no-collision guidance) for $CONTEXTS train contexts"
$T feedback create --db "$OUT/feedback.sqlite" --name train --model ctg --model-option 'checkpoint="ctg-4s"' \
  --guidance no_collision --split train --scenes "$CONTEXTS" --seconds 4 --seed 0
step "2/5 labels: a stand-in annotator picks the most realistic candidate of each context"
$T feedback label --db "$OUT/feedback.sqlite" --campaign train --synthetic --annotator stand-in --seed 0
$T feedback render --db "$OUT/feedback.sqlite" --campaign train --with-log --out "$OUT/candidates.png"
step "3/5 reward model: Bradley-Terry on the choices (N-1 pairs each)"
$T rm train --db "$OUT/feedback.sqlite" --campaign train --out "$OUT/reward_model" --epochs 30 --seed 0 --quiet
step "4/5 alignment: PPO on the imitation loss + alpha x the learned reward (a short run)"
$T align --model ctg --checkpoint ctg-4s --reward-model "$OUT/reward_model" --guidance no_collision --epochs 4 \
  --scenes 40 --seed 0 --quiet --out "$OUT/aligned"
step "5/5 closed-loop evaluation on 100 val scenes: base, this run, the committed aligned CTG"
$T evaluate --checkpoint ctg-4s --guidance no_collision --scenes 100 --render-worst 1 --out "$OUT/eval_base"
$T evaluate --checkpoint "$OUT/aligned" --guidance no_collision --scenes 100 --render-worst 1 \
  --reward-model "$OUT/reward_model" --out "$OUT/eval_this_run"
$T evaluate --checkpoint ctg-aligned --guidance no_collision --scenes 100 --render-worst 1 --out "$OUT/eval_committed"
$T compare "$OUT/eval_base" "$OUT/eval_this_run" "$OUT/eval_committed" | tee "$OUT/comparison.md"
$T report "$OUT" --run "base=$OUT/eval_base" --run "this run=$OUT/eval_this_run" \
  --run "committed aligned=$OUT/eval_committed" --reward-model "$OUT/reward_model" --align "$OUT/aligned" \
  --title "TrafficRLHF loop on nuScenes (small scale)"
echo "main job done: $OUT/report.md"
