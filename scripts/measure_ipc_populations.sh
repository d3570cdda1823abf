#!/usr/bin/env bash
# The measurements of docs/ipc_populations.md: a 128 x 128 laboratory sequence (seed 1)
# with a hidden `ipc` or `populations` (simulator defaults), the paper's calibration
# (m0) and the calibration plus the model effect (m1, `fit --with`), compared with the
# same sequence without the effect as the touched-pixel baseline. Measured with the
# levels cell statistic (passed: $POOLED_LEVELS; on this single illumination pooled and
# per-illumination cells are the same).
# Usage: scripts/measure_ipc_populations.sh [WORKDIR]   (release binary; ~15 min)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
P="$ROOT/target/release/persist"
W="${1:-/tmp/persist-ipc-populations}"
POOLED_LEVELS=(--cells pooled --cell-statistic levels)
rm -rf "$W"; mkdir -p "$W"; cd "$W"
for eff in ipc populations; do
  "$P" simulate lab --size 128 --seed 1 --out "lab-$eff" --effect "$eff" > /dev/null
done
"$P" simulate lab --size 128 --seed 1 --out base > /dev/null
for eff in ipc populations; do
  "$P" fit --input "lab-$eff" --out "m0-$eff.json" "${POOLED_LEVELS[@]}" > /dev/null
  "$P" fit --input "lab-$eff" --out "m1-$eff.json" --with "$eff" "${POOLED_LEVELS[@]}" > /dev/null
  python3 -c "import json,sys; f=json.load(open(sys.argv[1]))['effects']; print(sys.argv[2], 'fit:', [(p['name'], round(p['value'],4), round(p['sigma'],4)) for p in f['params']], 'evaluations', f['evaluations'])" "m1-$eff.fit.json" "$eff"
  "$P" compare --input "lab-$eff" --model "m0-$eff.json" --model "m1-$eff.json" --touched-baseline base --report "cmp-$eff" "${POOLED_LEVELS[@]}"
done
