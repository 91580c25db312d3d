#!/usr/bin/env bash
# Set everything up, then run the main job on the bundled nuScenes data (../shared/data by default, or
# TRAFFICRLHF_DATA): inspect the val split, render a scene, and evaluate log replay and constant velocity in
# closed loop on the first 100 long-enough val scenes, then the compact CTG without and with no-collision
# guidance, the aligned CTG, the 4 s CTG with its four aligned versions, TrafficGen with its aligned-and-extrapolated
# version, the 4 s TrafficGen with its aligned version and its pace-keeping composition, and BITS with its
# aligned version; a comparison table closes. Outputs land in out/main/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
OUT=${OUT:-out/main}
mkdir -p "$OUT"
T=.venv/bin/trafficrlhf
$T sources
$T inspect nuscenes_pred --split val
first_scene=$(.venv/bin/python -c "import trafficrlhf_sdk as t; print(t.get_scenario_source('nuscenes_pred').scene_ids('val')[0])")
$T render nuscenes_pred "$first_scene" --split val -o "$OUT/$first_scene.png"
for model in log_replay constant_velocity ctg; do
  $T evaluate --model "$model" --source nuscenes_pred --split val --scenes 100 --out "$OUT/$model"
done
$T evaluate --model ctg --guidance no_collision --source nuscenes_pred --split val --scenes 100 --out "$OUT/ctg_no_collision"
# stage III: the committed aligned CTG (trafficrlhf align, see reference_models/aligned/ctg/README.md)
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/aligned/ctg --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/ctg_aligned_no_collision"
# the same pair for the CTG trained over a 4 s plan (reference_models/aligned/ctg_4s/README.md)
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/ctg/checkpoints/ctg_small_4s \
  --source nuscenes_pred --split val --scenes 100 --out "$OUT/ctg4s_no_collision"
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/aligned/ctg_4s --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/ctg4s_aligned_no_collision"
# ... and the 4 s CTG with a road-reading steering head, the only part trained (reference_models/aligned/ctg_4s_road/README.md)
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/aligned/ctg_4s_road --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/ctg4s_road_no_collision"
# ... and with that head gated by each plan's hazard, so plans on a clear road are left alone
# (reference_models/aligned/ctg_4s_gated/README.md)
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/aligned/ctg_4s_gated --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/ctg4s_gated_no_collision"
# ... and that model with a braking prior behind a closing lead and a third steer stage around it
# (reference_models/aligned/ctg_4s_follow/README.md)
$T evaluate --model ctg --guidance no_collision --checkpoint reference_models/aligned/ctg_4s_follow --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/ctg4s_follow_no_collision"
# TrafficGen and its aligned version extrapolated by 2 (reference_models/aligned/trafficgen_x2/README.md)
$T evaluate --model trafficgen --guidance no_collision --source nuscenes_pred --split val --scenes 100 \
  --out "$OUT/trafficgen_no_collision"
$T evaluate --model trafficgen --guidance no_collision --checkpoint reference_models/aligned/trafficgen_x2 \
  --source nuscenes_pred --split val --scenes 100 --out "$OUT/trafficgen_x2_no_collision"
# the 4 s TrafficGen and its aligned version (reference_models/aligned/trafficgen_4s/README.md)
$T evaluate --model trafficgen --guidance no_collision \
  --checkpoint reference_models/trafficgen/checkpoints/trafficgen_small_4s --source nuscenes_pred --split val \
  --scenes 100 --out "$OUT/trafficgen4s_no_collision"
$T evaluate --model trafficgen --guidance no_collision --checkpoint reference_models/aligned/trafficgen_4s \
  --source nuscenes_pred --split val --scenes 100 --out "$OUT/trafficgen4s_aligned_no_collision"
# ... and that aligned version extrapolated by 2 plus half a pace-keeping stage
# (reference_models/aligned/trafficgen_4s_pace/README.md)
$T evaluate --model trafficgen --guidance no_collision --checkpoint reference_models/aligned/trafficgen_4s_pace \
  --source nuscenes_pred --split val --scenes 100 --out "$OUT/trafficgen4s_pace_no_collision"
# BITS and its aligned version: three training stages, eight stage-3 runs averaged (reference_models/aligned/bits/README.md)
$T evaluate --model bits --guidance no_collision --source nuscenes_pred --split val --scenes 100 \
  --out "$OUT/bits_no_collision"
$T evaluate --model bits --guidance no_collision --checkpoint reference_models/aligned/bits --source nuscenes_pred \
  --split val --scenes 100 --out "$OUT/bits_aligned_no_collision" --worst-scenes 5 --render-worst 3
$T compare "$OUT/log_replay" "$OUT/constant_velocity" "$OUT/ctg" "$OUT/ctg_no_collision" "$OUT/ctg_aligned_no_collision" \
  "$OUT/ctg4s_no_collision" "$OUT/ctg4s_aligned_no_collision" "$OUT/ctg4s_road_no_collision" \
  "$OUT/ctg4s_gated_no_collision" "$OUT/ctg4s_follow_no_collision" "$OUT/trafficgen_no_collision" \
  "$OUT/trafficgen_x2_no_collision" "$OUT/trafficgen4s_no_collision" \
  "$OUT/trafficgen4s_aligned_no_collision" "$OUT/trafficgen4s_pace_no_collision" \
  "$OUT/bits_no_collision" "$OUT/bits_aligned_no_collision" | tee "$OUT/comparison.md"
# where the aligned BITS gains and loses, scene by scene (drawings of its worst scenes: bits_aligned_no_collision/worst_scenes/)
$T compare "$OUT/bits_no_collision" "$OUT/bits_aligned_no_collision" --scene-changes 10 > "$OUT/bits_scene_changes.md"
echo "main job done: results in $OUT/"
