#!/usr/bin/env bash
# Times one `persist run` against the split of docs/slurm.md (1x1 and 2x2 tiles, the
# jobs run one after the other on this machine, so each job's time is what one array
# task takes), for the default model and for the default model with blooming and ipc,
# on a simulated sky (default: 2040 x 2040, 1 detector, 4 exposures), and checks that
# the outputs and final checkpoints are byte-identical.
#   scripts/split_measure.sh [PERSIST_BINARY] [SCRATCH] [SIZE] [EXPOSURES]
set -euo pipefail
P=$(realpath "${1:-target/release/persist}")
S=${2:-/tmp/persist-split-measure}
SIZE=${3:-2040}
N=${4:-4}
rm -rf "$S"; mkdir -p "$S"
export SOURCE_DATE_EPOCH=1772409600
/usr/bin/time -f "simulate %e s" "$P" simulate sky --size "$SIZE" --detectors 1 --exposures "$N" --seed 2 --out "$S/sky" >/dev/null
"$P" model default | python3 -c '
import json, sys
m = json.load(sys.stdin)
m["effects"] = m.get("effects", []) + [{"name": "blooming"}, {"name": "ipc"}]
json.dump(m, open(sys.argv[1], "w"))' "$S/fx.json"
for model in default fx; do
  M=()
  if [ "$model" = fx ]; then M=(--model "$S/fx.json"); fi
  /usr/bin/time -f "$model: persist run %e s, max RSS %M KB" "$P" run --input "$S/sky" --output "$S/$model-ref/out" --checkpoints "$S/$model-ref/ckpt" "${M[@]}" --quiet
  for g in 1x1 2x2; do
    W=$S/$model-$g
    "$P" slurm --input "$S/sky" --output "$W/out" --checkpoints "$W/ckpt" --work "$W/work" --tiles "$g" "${M[@]}" >/dev/null
    n=$(( ${g%x*} * ${g#*x} ))
    for t in $(seq 0 $((n - 1))); do
      /usr/bin/time -f "$model $g: tile $t %e s, max RSS %M KB" "$P" tile --plan "$W/work/plan.json" --task "$t" >/dev/null
    done
    /usr/bin/time -f "$model $g: assemble %e s, max RSS %M KB" "$P" assemble --plan "$W/work/plan.json" >/dev/null
    last=$(ls "$S/$model-ref/ckpt/det1/" | tail -1)
    if diff -r -x .persist.lock "$S/$model-ref/out" "$W/out" >/dev/null \
       && cmp -s "$S/$model-ref/ckpt/det1/$last" "$W/ckpt/det1/$last"; then
      echo "$model $g: outputs and final checkpoint byte-identical to persist run"
    else
      echo "$model $g: DIFFERS from persist run"
    fi
  done
done
rm -rf "$S"
