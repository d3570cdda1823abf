#!/usr/bin/env bash
# Regenerates docs/validation/verify.md: `persist verify` on a simulated two-day sky
# (one detector, SIZE x SIZE, seed SEED) against the simulator's truth, with a model
# fitted on a simulated laboratory sequence of the same detector and four deliberately
# wrong variants of it (knots x2 and x0.5, decay power -0.15 and +0.15).
# SEEDS: one seed or several, comma-separated, each its own detector and section.
# Usage: [PERSIST_BIN=...] scripts/validate_verify.sh [SEEDS] [SIZE]   (defaults 2,3, 128; ~5 min a seed)
set -euo pipefail
cd "$(dirname "$0")/.."
seeds=${1:-2,3}
size=${2:-128}
# PERSIST_BIN: a built binary to use instead of building the release one.
if [[ -n "${PERSIST_BIN:-}" ]]; then
  P=$(realpath "$PERSIST_BIN")
else
  cargo build --release --quiet
  P=$PWD/target/release/persist
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
out=docs/validation/verify.md
mkdir -p docs/validation
section() { # seed, into "$work/$seed"
seed=$1
w=$work/$seed
mkdir -p "$w"
(
  cd "$w"
  "$P" simulate sky --out sky --size "$size" --detectors 1 --exposures 1143 --seed "$seed" >/dev/null
  "$P" simulate lab --out lab --size "$size" --seed "$seed" >/dev/null
  "$P" fit --input lab --out lab.json >/dev/null
  python3 - <<'PY'
import json
m = json.load(open('lab.json'))
def save(name, f):
    v = json.loads(json.dumps(m)); v['name'] = name; f(v)
    json.dump(v, open(name + '.json', 'w'), indent=1)
def knots(k):
    def f(v):
        for x in v['amplitude_knots']: x['amplitude_e'] *= k
    return f
def power(d):
    # C_n proportional to tau_n^-(1+d) turns a sum that follows 1/t into one that
    # follows t^-(1+d); the factor is 1 at tau = 100 s.
    def f(v):
        for t in v['terms']: t['c_per_s'] *= (1.0 / t['rate_per_s'] / 100.0) ** (-d)
    return f
save('knots_x2', knots(2.0)); save('knots_x0.5', knots(0.5))
save('decay_power_plus_0.15', power(0.15)); save('decay_power_minus_0.15', power(-0.15))
PY
  for m in lab knots_x2 knots_x0.5 decay_power_plus_0.15 decay_power_minus_0.15; do
    "$P" run --input sky --output "out_$m" --checkpoints "ck_$m" --model "$m.json" --quiet
    s=$EPOCHREALTIME
    "$P" verify --input sky --output "out_$m" --report "rep_$m" >/dev/null || true
    e=$EPOCHREALTIME
    awk -v m="$m" -v s="$s" -v e="$e" 'BEGIN { printf "%s %.2f\n", m, e - s }' >> times.txt
  done
)
{
  echo "## Seed $seed"
  echo
  echo "Two simulated days (1143 exposures of 112 s) of one ${size} x ${size} detector, seed"
  echo "$seed; the model fitted by \`persist fit\` on a simulated laboratory sequence of the same"
  echo "detector, and four wrong variants of it."
  echo
  python3 - "$w" <<'PY'
import json, sys, os
w = sys.argv[1]
times = dict(l.split() for l in open(os.path.join(w, 'times.txt')))
print('| model | events | samples | slope pred - meas | decay | margin (95 %) | margin check | truth in 95 % interval | verify time, s |')
print('|---|---|---|---|---|---|---|---|---|')
for m in ['lab', 'knots_x2', 'knots_x0.5', 'decay_power_plus_0.15', 'decay_power_minus_0.15']:
    r = json.load(open(os.path.join(w, 'rep_' + m, 'report.json')))
    c = r['checks']
    ins = c['truth_inside']
    print(f"| {m} | {r['events']} | {r['samples']} | {c['slope_difference']['mean']:+.3f} ± {c['slope_difference']['se']:.3f} | "
          f"{'agrees' if c['decay_agrees'] else 'disagrees'} | {c['margin'][0]:.2f} ({c['margin'][1]:.2f}-{c['margin'][2]:.2f}) | "
          f"{c['margin_verdict']} | {ins[0]} of {ins[1]} | {float(times[m]):.1f} |")
r = json.load(open(os.path.join(w, 'rep_lab', 'report.json')))
print()
print('Measured decay slopes per fluence bin (model `lab`), with the truth\'s over the same bins:')
print()
print('| fluence, e- | time bins | time span, s | measured | predicted | truth |')
print('|---|---|---|---|---|---|')
for b in r['checks']['slopes']:
    print(f"| {b['fluence_lo_e']:.0e} - {b['fluence_hi_e']:.0e} | {b['bins']} | {b['time_from_s']:.0f} - {b['time_to_s']:.0f} | "
          f"{b['measured']['mean']:.3f} ± {b['measured']['se']:.3f} | {b['predicted']:.3f} | {b['truth']:.3f} |")
PY
} > "$w/section.md"
rm -rf "$w"/sky "$w"/lab "$w"/out_* "$w"/ck_*
}
IFS=, read -ra list <<< "$seeds"
for s in "${list[@]}"; do section "$s"; done
{
  scripts/validation_header.sh "In-flight verification against the simulator's truth" \
    "scripts/validate_verify.sh $seeds $size"
  echo
  echo "\`verify\` sees only the stage's inputs and outputs; the truth is read only to fill"
  echo "the truth column (the truth's mean inside the measured mean's 95 % interval, bins of"
  echo "the fitted model's run). The decay check compares log-log slopes over the time bins"
  echo "measured at or above the 0.1 e-/s threshold; the margin check the 95th percentile of"
  echo "measured over predicted at the first exposure after an event."
  for s in "${list[@]}"; do echo; cat "$work/$s/section.md"; done
} > "$out"
echo "wrote $out"
