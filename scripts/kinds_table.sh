#!/usr/bin/env bash
# The kind `persist diagnose` names, measured on the second truth generator's
# campaigns (`persist simulate family --sequence campaign`, 64 x 64, seeds 1-5): nothing
# hidden (with and without dark pixels) and every hidden form whose class a library
# effect stands for on an event-level covariate. Default `fit`, then the first step of
# `diagnose` with its defaults (examples/dependence_scan: the dependences, the separation
# of the two leading kinds, the kind named). Prints Markdown on stdout
# (scripts/validation.sh kinds writes it to docs/validation/kinds.md).
#
#   PERSIST_BIN=target/release/persist SCAN_BIN=target/release/examples/dependence_scan \
#       WORK=/tmp/kinds scripts/kinds_table.sh
set -euo pipefail
persist=${PERSIST_BIN:-target/release/persist}
scan=${SCAN_BIN:-target/release/examples/dependence_scan}
work=${WORK:-$(mktemp -d)}
seeds=${SEEDS:-1 2 3 4 5}
rows=${ROWS:-none none+dark soak:capture soak:diffusion capacity:ceiling capacity:langmuir temperature:arrhenius}
mkdir -p "$work"

cat <<'TEXT'
What the residual depends on, and the kind `persist diagnose` names from it (module
docs of `persist::diag::contrast` and `persist::diag::separate`): event-level classes
against the pixel reference, the two leading ones tested each given the other. "Depends":
above all 99 permutations and explaining at least `MIN_R2_EVENT` of the residual's sum
of squares beyond their mean. Right kind: the hidden class's contrast class (soak:
illumination_time; capacity: earlier_illuminations; temperature: temperature), or
nothing where nothing is hidden. "With one other": named together with one other kind
(confounded, or each depending beyond the other), with the measurement that separates
them. Largest below: the largest share explained by a class that does not depend.

| run | depends | largest below | separation | named | right kind |
|---|---|---|---|---|---|
TEXT
for seed in $seeds; do
    for row in $rows; do
        dir=$work/${row//[:+]/_}-$seed
        args=(--out "$dir" --size 64 --seed "$seed" --sequence campaign)
        expect=none
        case $row in
            none+dark) args+=(--dark-pixels) ;;
            none) ;;
            *) args+=(--hidden "$row") ;;
        esac
        case $row in
            soak:*) expect=illumination_time ;;
            capacity:*) expect=earlier_illuminations ;;
            temperature:*) expect=temperature ;;
        esac
        "$persist" --log-level error simulate family "${args[@]}" > /dev/null
        "$persist" --log-level error fit --input "$dir" --out "$dir.json" > /dev/null
        "$scan" "$dir" "$dir.json" "$row, seed $seed" "$expect"
        rm -rf "$dir" "$dir.json" "$dir.fit.json"
    done
done | tee "$work/rows.md"
awk -F' [|] ' '
    /^[|] none/ { n++; if ($6 ~ /^yes/) q++ }
    /^[|] [a-z]+:/ { h++; if ($6 ~ /^yes/) y++; if ($6 ~ /^with one other/) w++ }
    END {
        printf "\nNothing hidden: nothing named in %d of %d runs. Hidden: the right kind named first in %d of %d runs, named with one other in %d more.\n", q, n, y, h, w
    }' "$work/rows.md"
