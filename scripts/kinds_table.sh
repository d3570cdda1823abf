#!/usr/bin/env bash
# The kind `persist diagnose` names, measured on the second truth generator's
# campaigns (`persist simulate family --sequence campaign`, 64 x 64, seeds 1-5): nothing
# hidden (with dark pixels, and with the grid of one-pixel pinholes) and every hidden
# form the family matrix runs (examples/family_matrix: those not held aside; blooming
# and ipc, which couple neighbours, with the pinholes). Default `fit`, then the first step of
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
# shellcheck source=scripts/family_forms.sh
source "$(dirname "$0")/family_forms.sh"
rows=${ROWS:-none none+dark none+pinholes $FAMILY_FORMS}
mkdir -p "$work"

cat <<'TEXT'
What the residual depends on, and the kind `persist diagnose` names from it (module
docs of `persist::diag::contrast` and `persist::diag::separate`): event-level classes
against the pixel reference, the two leading ones tested each given the other;
pixel-level classes (neighbours, position) against the flexible base. "Depends": above
all 99 permutations and explaining at least `MIN_R2_EVENT` (event-level) or `MIN_R2`
(pixel-level) of the residual's sum of squares beyond their mean; the neighbours also
when the pixel-events next to far brighter pixels carry a residual beyond their cells'
mean at `|z|` of at least `MIN_SHARP_Z` (shown as "next to far brighter pixels", the
mean in units of the cells' spread). Right kind: the
hidden class's contrast class (soak: illumination_time; capacity:
earlier_illuminations; temperature: temperature; blooming and ipc:
neighbour_excess_fluence; populations: position; shape, a decay shape that depends on
the fluence: fluence_x_time, measured as the rise of the decay's tilt between fluence
bins after the first illumination, `persist::diag::shape`, and named when no contrast
names a kind), or nothing where nothing is hidden. "With one other": named together with one other kind
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
            none | none+pinholes) ;;
            *) args+=(--hidden "$row") ;;
        esac
        read -r -a pin <<< "$(pinhole_args "$row")"
        args+=("${pin[@]}")
        case $row in
            soak:*) expect=illumination_time ;;
            capacity:*) expect=earlier_illuminations ;;
            temperature:*) expect=temperature ;;
            blooming:* | ipc:*) expect=neighbour_excess_fluence ;;
            populations:*) expect=position ;;
            shape:*) expect=fluence_x_time ;;
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
