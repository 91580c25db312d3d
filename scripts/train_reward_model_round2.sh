#!/usr/bin/env bash
# Second RLHF round of the reward model, in one seeded command (about 25 min on 2 CPU cores), after
# `bash scripts/train_reward_model.sh` has built the round-1 database:
#   1. align the compact CTG against the round-1 reward model (30 epochs, alpha 3, no KL: the run whose agents
#      learned to speed, docs/explanation/alignment-log.md);
#   2. feedback campaigns on *train* scenes whose candidates come from that reward-hacking CTG (250 scenes) and
#      from the committed aligned CTG (150 scenes): the states a policy reaches under optimization;
#   3. the same synthetic annotators as round 1 label them;
#   4. `trafficrlhf rm train` on the pooled campaigns of both rounds (same recipe, same held-out val campaign).
# Environment: DB (round-1 database, copied, never modified), OUT (default out/reward/ctg_round2).
set -euo pipefail
cd "$(dirname "$0")/.."
DB1=${DB:-out/reward/ctg_no_collision.db}
WORK=${WORK:-out/reward/round2}
OUT=${OUT:-out/reward/ctg_round2}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
T=.venv/bin/trafficrlhf
[ -f "$DB1" ] || { echo "no round-1 database at $DB1: run scripts/train_reward_model.sh first" >&2; exit 2; }
mkdir -p "$WORK"
DB2="$WORK/feedback.db"
[ -f "$DB2" ] || cp "$DB1" "$DB2"

[ -f "$WORK/hacked/model.safetensors" ] || $T align --model ctg --reward-model reference_models/reward/ctg_no_collision \
  --alpha 3 --denoising-steps 4 --guidance no_collision --epochs 30 --contexts 16 --samples 8 \
  --failure-contexts 0.75 --failure-scenes 24 --credit agent --scenes 400 --threads 1 --quiet --out "$WORK/hacked"

campaign() {  # name checkpoint scenes seed
  $T feedback status --db "$DB2" --campaign "$1" >/dev/null 2>&1 || \
    $T feedback create --db "$DB2" --name "$1" --model ctg --guidance no_collision --model-option "checkpoint=$2" \
      --split train --scenes "$3" --candidates 5 --seconds 5 --seed "$4" | tail -1
  $T feedback label --synthetic --db "$DB2" --campaign "$1" --annotator synth-noisy --beta 20 --epsilon 0.1 --seed 0
  $T feedback label --synthetic --db "$DB2" --campaign "$1" --annotator oracle --beta 0 --epsilon 0 --seed 0
}
campaign ctg-rmhack-train "$WORK/hacked" 250 1
campaign ctg-aligned-train reference_models/aligned/ctg 150 2

$T rm train --db "$DB2" --campaign ctg-nc-train --campaign ctg-rmhack-train --campaign ctg-aligned-train \
  --annotator synth-noisy --val-fraction 0.1472 --seed 0 --ensemble 3 --no-bootstrap --half \
  --test-campaign ctg-nc-val --test-annotator oracle --out "$OUT" --quiet \
  --title "TrafficRLHF reward model, round 2: CTG, reward-hacking CTG and aligned CTG candidates on nuScenes" \
  --note "Built by \`bash scripts/train_reward_model_round2.sh\` on top of round 1 (scripts/train_reward_model.sh)."
echo "== ctg-nc-val (100 val scenes, never trained on)"
$T rm eval --model "$OUT" --db "$DB2" --campaign ctg-nc-val --annotator oracle
for c in ctg-rmhack-train ctg-aligned-train; do
  for m in reference_models/reward/ctg_no_collision "$OUT"; do
    echo "== $c, held-out contexts (the split rm train used), $m"
    $T rm eval --model "$m" --db "$DB2" --campaign "$c" --annotator oracle --val-fraction 0.1472 --subset val
  done
done
