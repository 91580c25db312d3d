#!/usr/bin/env bash
# The committed reward model, from scratch, in one seeded command (about 20 min on 2 shared cores):
#   1. feedback campaigns of the compact CTG with no-collision guidance, 5 candidates of 5 s per context:
#      every long-enough nuScenes *train* scene (469) for training, the first 100 long-enough *val* scenes as a
#      held-out test set;
#   2. synthetic labels: a noisy B-Pref-style annotator (beta 20, 10 % mistakes) and a noise-free one
#      (beta -> inf, no mistakes) on both campaigns; training uses the noisy labels only;
#   3. `trafficrlhf rm train` on the noisy train labels (400 contexts train, 69 early-stopping, split by context):
#      an ensemble of 3 members that differ only in their seed, weights stored in float16, evaluated on the
#      noise-free test labels and saved with its model card.
# The database stays out of git (out/ is ignored). Data: nuScenes (CC BY-NC-SA 4.0).
# Environment: DB (default out/reward/ctg_no_collision.db), OUT (default reference_models/reward/ctg_no_collision).
set -euo pipefail
cd "$(dirname "$0")/.."
DB=${DB:-out/reward/ctg_no_collision.db}
OUT=${OUT:-reference_models/reward/ctg_no_collision}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
T=.venv/bin/trafficrlhf
mkdir -p "$(dirname "$DB")"

campaign() {  # name split scenes: create the campaign, or extend it to the same scenes if it exists
  if $T feedback status --db "$DB" --campaign "$1" >/dev/null 2>&1; then
    $T feedback create --db "$DB" --name "$1" --scenes "$3" --extend | tail -1
  else
    $T feedback create --db "$DB" --name "$1" --model ctg --guidance no_collision --split "$2" --scenes "$3" \
      --candidates 5 --seconds 5 --seed 0 | tail -1
  fi
}
SECONDS=0
campaign ctg-nc-train train 500   # every long-enough train scene: 469
campaign ctg-nc-val val 100
echo "candidates generated in ${SECONDS} s"

$T feedback label --synthetic --db "$DB" --campaign ctg-nc-train --annotator synth-noisy --beta 20 --epsilon 0.1 --seed 0
$T feedback label --synthetic --db "$DB" --campaign ctg-nc-val --annotator synth-noisy --beta 20 --epsilon 0.1 --seed 0
$T feedback label --synthetic --db "$DB" --campaign ctg-nc-val --annotator oracle --beta 0 --epsilon 0 --seed 0
# noise-free labels of the training campaign too: for diagnostics only (rm train below uses synth-noisy alone)
$T feedback label --synthetic --db "$DB" --campaign ctg-nc-train --annotator oracle --beta 0 --epsilon 0 --seed 0

$T rm train --db "$DB" --campaign ctg-nc-train --annotator synth-noisy --val-fraction 0.1472 --seed 0 \
  --ensemble 3 --no-bootstrap --half \
  --test-campaign ctg-nc-val --test-annotator oracle --out "$OUT" --quiet \
  --title "TrafficRLHF reward model: CTG + no-collision candidates on nuScenes" \
  --note "Rebuilt from scratch, data included, by \`bash scripts/train_reward_model.sh\` (campaigns, synthetic labels, training, evaluation; about 20 min on 2 CPU cores). Accuracy against training-set size (the paper's Figure 3) and how the test accuracy is defined: docs/explanation/reward-model.md."
$T rm eval --model "$OUT" --db "$DB" --campaign ctg-nc-val --annotator oracle
