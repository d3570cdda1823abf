#!/usr/bin/env bash
# The pixel reference's normalised residual RMS (`persist diagnose`, line "pixel
# reference"; persist::diag::base::predict_scaled) on laboratory sequences with nothing
# hidden: the simulator (`persist simulate lab --spots paper`, every pixel lit, or with
# `--dark-pixels`) and the second truth generator (`persist simulate family`), single
# illuminations and campaigns, seeds 1-3 (and the family's held-aside seed 101), 64 x 64,
# default `fit` and `diagnose`.
# Prints a markdown table on stdout (scripts/validation.sh reference writes it to
# docs/validation/reference_rms.md).
#
#   PERSIST_BIN=target/release/persist WORK=/tmp/ref scripts/reference_table.sh
set -euo pipefail
persist=${PERSIST_BIN:-target/release/persist}
work=${WORK:-$(mktemp -d)}
seeds=${SEEDS:-1 2 3}
# the second generator's seeds from 100 on are held aside from its matrix (persist::trapgen)
held_seeds=${HELD_SEEDS:-101}
mkdir -p "$work"

cat <<'TEXT'
What `persist diagnose` prints as "pixel reference": the flexible base (the model's
prediction plus a free response per fluence knot, saturated pixels with knots of their
own, over a fixed grid of decay rates) times each pixel's own factor, quadratic in the
log of the time since the illumination (its amplitude and decay shape) and in the log of
the illumination's fluence (its response: its own saturation onset), fitted to the
input; the paired statistic of its residuals, each divided by the noise measured from
the data (exposure noise from the background pixels, or from pairs of late darks when
every pixel is lit, plus the shot noise of the predicted current, less the sample's
leverage in its pixel's fit), each part's variance scaled by what the reference's
residuals, centred in their cells, show (the line "noise:" under it; "noise x read /
shot" below, "-" where too few samples measured it). Default commands: `persist fit --input DIR --out M.json`, then `persist diagnose
--input DIR --model M.json`. The description's RMS is the line "residual RMS" of the
same run (the measurements' description `diagnose` tests effects against). Family seeds
from 100 on are held aside from the family's matrix (`persist::trapgen`).

| source | sequence | dark pixels | seed | pixel reference RMS | description RMS | cells | noise x read / shot |
|---|---|---|---|---|---|---|---|
TEXT
for source in lab family; do
    for sequence in single campaign; do
        for dark in no yes; do
            all=$seeds
            if [[ $source == family ]]; then all="$seeds $held_seeds"; fi
            for seed in $all; do
                dir=$work/$source-$sequence-$dark-$seed
                args=(--out "$dir" --size 64 --seed "$seed")
                if [[ $source == lab ]]; then
                    args=(simulate lab "${args[@]}" --spots paper)
                    if [[ $sequence == campaign ]]; then args+=(--campaign); else args+=(--darks 120); fi
                else
                    args=(simulate family "${args[@]}" --sequence "$sequence")
                fi
                if [[ $dark == yes ]]; then args+=(--dark-pixels); fi
                "$persist" --log-level error "${args[@]}" > /dev/null
                "$persist" --log-level error fit --input "$dir" --out "$dir.json" > /dev/null
                out=$("$persist" --log-level error diagnose --input "$dir" --model "$dir.json")
                ref=$(sed -n 's/^pixel reference.*residual RMS \([0-9.]*\) over \([0-9]*\) cells$/\1 \2/p' <<< "$out")
                desc=$(sed -n 's/^persist diagnose:.* residual RMS \([0-9.]*\) (.*/\1/p' <<< "$out")
                noise=$(sed -n 's/^  noise: the read-noise variance x\([0-9.]*\) and the shot-noise variance x\([0-9.]*\),.*/\1 \/ \2/p' <<< "$out")
                read -r rms cells <<< "$ref"
                echo "| $source | $sequence | $dark | $seed | $rms | $desc | $cells | ${noise:--} |"
                rm -rf "$dir"
            done
        done
    done
done
