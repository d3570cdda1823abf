#!/usr/bin/env bash
# The measurements of docs/operations.md at mission scale, at 2040 x 2040:
# 1. checkpoints: one detector of 12 simulated sky exposures, the default cadence against
#    `--checkpoint-every 1` and against no checkpoint but the final one, three runs each: wall time, checkpoint files and bytes, bytes
#    per exposure; then `persist status --projection` (the two-year footprint);
# 2. detectors side by side: 2 detectors x 8 exposures, one `persist run` (a worker
#    process per detector), `--one-process`, and two `persist run` processes on one
#    detector each started together, three runs each (interleaved).
# The stage against a plain copy of its bytes: `persist bench --sizes 2040`.
# Usage: scripts/measure_scale.sh [WORKDIR]   (release binary; about 5 min, 3 GB of disk)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
P="$ROOT/target/release/persist"
W="${1:-/tmp/persist-scale}"
rm -rf "$W"; mkdir -p "$W"; cd "$W"
ts() { date +%s.%N; }
# Every timed run starts after `sync`: the write-back of the files just deleted and
# written would otherwise land on whichever run comes next.
since() { echo "$(ts) - $1" | bc; }
q=(--quiet --log-level warn)

"$P" simulate sky --out sky1 --size 2040 --detectors 1 --exposures 12 --seed 1 > /dev/null
for mode in default every1 tail-only; do
  extra=()
  [ "$mode" = every1 ] && extra=(--checkpoint-every 1)
  # No grid checkpoint, only the tail at the end: what the rest of the stage costs.
  [ "$mode" = tail-only ] && extra=(--checkpoint-every 1000000)
  for rep in 1 2 3; do
    rm -rf out ck; sync
    t0=$(ts)
    "$P" run --input sky1 --output out --checkpoints ck "${q[@]}" "${extra[@]}"
    t=$(since "$t0")
    bytes=$(du -sb ck | cut -f1)
    echo "checkpoints $mode run $rep: $t s, $(ls ck/det1 | wc -l) files, $bytes bytes, $((bytes / 12)) bytes per exposure"
  done
done
mkdir -p empty
"$P" status --output empty --checkpoints ck --projection | tail -n 1
rm -rf sky1 out ck empty

"$P" simulate sky --out sky2 --size 2040 --detectors 2 --exposures 8 --seed 1 > /dev/null
mkdir -p d1 d2; ln sky2/d1_*.h5 d1/; ln sky2/d2_*.h5 d2/
for rep in 1 2 3; do
  rm -rf r; sync; t0=$(ts)
  "$P" run --input sky2 --output r/out --checkpoints r/ck "${q[@]}"
  echo "detectors: one run (workers) run $rep: $(since "$t0") s"
  rm -rf r; sync; t0=$(ts)
  "$P" run --input sky2 --output r/out --checkpoints r/ck "${q[@]}" --one-process
  echo "detectors: --one-process run $rep: $(since "$t0") s"
  rm -rf r; sync; t0=$(ts)
  "$P" run --input d1 --output r/o1 --checkpoints r/c1 "${q[@]}" & a=$!
  "$P" run --input d2 --output r/o2 --checkpoints r/c2 "${q[@]}" & b=$!
  wait "$a"; wait "$b"
  echo "detectors: two processes run $rep: $(since "$t0") s"
done
rm -rf "$W"
