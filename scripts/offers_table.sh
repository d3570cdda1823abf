#!/usr/bin/env bash
# What the addition `persist diagnose` offers does to the pixel reference's RMS, on
# hidden campaigns of one of the two truth generators and the nothing-hidden campaign of
# the same seed (the baseline). SOURCE=family (default): the second truth generator's
# campaigns (`persist simulate family --sequence campaign`), every hidden form the family
# matrix runs (examples/family_matrix: those not held aside); blooming and ipc, which
# couple neighbours, and their baseline with the grid of one-pixel pinholes
# (`--pinholes on`). SOURCE=lab: the simulator's laboratory campaign (`persist simulate
# lab --campaign --effect ROW`), every simulator effect; blooming and ipc, and their
# baseline, with the pinhole grid (`--spots pinholes`), `linefit_bias` with dark
# integrations of two lengths (`--dark-lengths varied`); LAB_ARGS adds options to every
# lab campaign (for example `--durations apart`). Default `fit` and `diagnose`;
# then exactly the `persist fit` command the verdict prints (its first "add it with" /
# "add both with"), `diagnose` again on the model it writes, and `persist compare` of
# the two models' flags on the same data. Prints Markdown on
# stdout (scripts/validation.sh offers writes it to docs/validation/offers.md).
#
#   PERSIST_BIN=target/release/persist WORK=/tmp/offers scripts/offers_table.sh
#   SEEDS="1 2" ROWS="soak:capture" scripts/offers_table.sh     (a subset)
#   SOURCE=lab SEEDS=1 ROWS="soak temperature" SIZE=64 scripts/offers_table.sh
set -euo pipefail
persist=$(realpath "${PERSIST_BIN:-target/release/persist}")
work=${WORK:-$(mktemp -d)}
seeds=${SEEDS:-1 2 3 4 5}
size=${SIZE:-64}
source_kind=${SOURCE:-family}
# shellcheck source=scripts/family_forms.sh
source "$(dirname "$0")/family_forms.sh"
case $source_kind in
    family) default_rows=$FAMILY_FORMS ;;
    lab) default_rows=$LAB_EFFECTS ;;
    *) echo "offers_table.sh: SOURCE must be family or lab, not '$source_kind'" >&2; exit 2 ;;
esac
rows=${ROWS:-$default_rows}
mkdir -p "$work"

# The options that simulate a row ($1; `none` for the baseline) besides its hidden
# effect: the pinhole grid for the effects that couple neighbours, and for the lab
# source the dark lengths `linefit_bias` needs and LAB_ARGS. The baselines are keyed by
# them (one nothing-hidden campaign per set of options).
sim_options() {
    case $source_kind in
        family) pinhole_args "$1" ;;
        lab)
            local o=${LAB_ARGS:-}
            case $1 in
                blooming* | ipc*) o="$o --spots pinholes" ;;
                linefit_bias*) o="$o --dark-lengths varied" ;;
            esac
            echo "$o"
            ;;
    esac
}

# Simulate row $3 (`none`: nothing hidden) with options $4 into $1, seed $2.
simulate() {
    local hidden=()
    case $source_kind in
        family)
            [[ $3 != none ]] && hidden=(--hidden "$3")
            # shellcheck disable=SC2086
            "$persist" --log-level error simulate family --out "$1" --size "$size" --seed "$2" \
                --sequence campaign "${hidden[@]}" $4 > /dev/null
            ;;
        lab)
            [[ $3 != none ]] && hidden=(--effect "$3")
            # shellcheck disable=SC2086
            "$persist" --log-level error simulate lab --out "$1" --size "$size" --seed "$2" \
                --campaign "${hidden[@]}" $4 > /dev/null
            ;;
    esac
}

case $source_kind in
    family) echo "Data: the second truth generator's campaigns (\`persist simulate family --sequence campaign\`, $size x $size), one hidden form each." ;;
    lab) echo "Data: the simulator's laboratory campaign (\`persist simulate lab --campaign${LAB_ARGS:+ $LAB_ARGS}\`, $size x $size), one hidden effect each (\`--effect NAME\` at its defaults; blooming and ipc with \`--spots pinholes\`, linefit_bias with \`--dark-lengths varied\`)." ;;
esac
echo

cat <<'TEXT'
The addition `persist diagnose` offers, run as printed, against the pixel reference
(the line "pixel reference" of `diagnose`: the flexible base times each pixel's own
amplitude and decay shape; [reference_rms.md](reference_rms.md)). Per run: the default
`persist fit --input D --out M.json` and `persist diagnose --input D --model M.json`;
the `persist fit` command its verdict prints, run as printed; `diagnose` again on the
model that command writes. Before / after: the pixel reference's normalised residual
RMS of the two diagnoses; baseline: the same on the nothing-hidden campaign of the
same seed (default `fit` and `diagnose`; for blooming and ipc, with the pinhole grid
that both are simulated with). Excess = RMS - baseline; halved: the excess
after at most half the excess before (an excess before of at most 0 counts as halved
when the excess after is at most 0 too). Next to far brighter pixels: where the pinhole
grid gives them, the mean residual of the pixel-events next to far brighter pixels
beyond their cells' mean, in units of the cells' spread, and its z (`diagnose`'s line
"next to far brighter pixels", against the flexible base), before -> after: what the
candidates on the neighbours are judged on (`persist::diag::marked`), since each
pixel's own terms in the pixel reference take in what a bright neighbour, the same in
every illumination, does to it. Field: the share of one illumination's residual that
a map of another's, smoothed over 4 px, predicts (`diagnose`'s line "spatial
coherence", R^2; at most 0.20 counts as no field), before -> after: a field over the
array (a trap density that follows the position) shows there, and candidates on the
position are judged by tile of the array against the flexible base, which each
pixel's own amplitude in the pixel reference takes in too. Decay tilt: the rise of the
decay's log-log slope between the faintest and the brightest pixels after the first
illumination, per decade of time, and its z (`diagnose`'s "the decay's shape depends on
the fluence", JSON `decay_shape`; at least 0.07 depends), before -> after: a decay
shape that depends on the fluence is a function of fluence and time, which the pixel
reference takes in by construction, so its terms are judged there. Flags at 0.1 e-/s:
`persist compare --input D --model M.json --model M+EFFECT.json` on the laboratory
samples, each model at its own margin (`persist fit` re-derives it after the
addition): the share of the samples measured above 0.1 e-/s that are flagged
(coverage), and the share of all samples flagged while measured below it
(over-flagged), before -> after; in brackets the added model's over-flagging with its
knots scaled to the first model's coverage (`compare`'s line "at the first model's
coverage"), and its over-flagged samples minus the first model's +- the standard error
of that difference, paired by pixel (a rise within twice it is within the noise). Flagging model's pixel reference: `compare`'s "pixel reference" of the two
flagging models themselves (the default `fit`'s and the one the printed command
writes), before -> after, where the columns before and after are of the models
`diagnose` tested against (the measurements' descriptions).

| run | named | offered | before | after | baseline | excess before -> after | halved | next to far brighter pixels | field | decay tilt | flags at 0.1 e-/s: coverage; over-flagged | flagging model's pixel reference |
|---|---|---|---|---|---|---|---|---|---|---|---|---|
TEXT

# The pixel reference's RMS in diagnose's output ($1).
pixel_rms() {
    sed -n 's/^pixel reference.*residual RMS \([0-9.]*\) over [0-9]* cells$/\1/p' <<< "$1"
}

# "+0.21 (z 6.9)": the pixels next to far brighter ones in diagnose's output ($1), or "-".
marked() {
    local m
    m=$(sed -n "s/.*next to far brighter pixels: [0-9]* pixel-events, \([-+0-9.]*\) of their cells' spread, z \([-0-9.]*\).*/\1 (z \2)/p" <<< "$1" | head -1)
    echo "${m:--}"
}

# The spatial coherence's R^2 at 4 px in diagnose's output ($1), or "-".
field() {
    local r
    r=$(sed -n 's/^spatial coherence: .* predicts R^2 \([0-9.]*\)\/.*/\1/p' <<< "$1" | head -1)
    echo "${r:--}"
}

# The kind the verdict names ($1: diagnose's output): the missing effect's covariate,
# or the covariate the residual depends on; "nothing" otherwise.
named() {
    perl -ne '
        if (/^missing effect: \S+ \(the evidence is in the residual against (\w+)/) { print "$1\n"; exit }
        if (/(\w+) or (\w+): confounded in these data\./) { print "$1 / $2\n"; exit }
        if (/^no library effect is significant alone, but (\S+) and (\S+) are together/) { print "$1 + $2\n"; exit }
        if (/^the residual of .*? depends on (\w+) /) { print "$1\n"; exit }
        if (/^the decay.s shape depends on the fluence \((\w+)\)/) { print "$1\n"; exit }
        if (/^no library effect is significant; /) { print "nothing\n"; exit }' <<< "$1"
}

# The first `persist fit` command the verdict offers ($1), empty when none.
offered_command() {
    perl -ne 'if (/add (?:it|both) with: (persist fit .*?)(?= \(|\. |; |$)/) { print "$1\n"; exit }' <<< "$1"
}

# "2.26 -> 4.64": the pixel reference's RMS of the first model and the second in
# compare's summary.json ($1).
flagging_rms() {
    jq -r '[.models[] | .pixel_reference.residual_rms_normalised * 100 | round / 100]
        | "\(.[0]) -> \(.[1])"' "$1"
}

# diagnose's output on data $1 with model $2, its JSON written to $3.
diagnose_rms() {
    "$persist" --log-level error diagnose --input "$1" --model "$2" --json "$3"
}

# "0.19 (z 24)": the decay's tilt in diagnose's JSON ($1), or "-".
tilt() {
    jq -r 'if .decay_shape == null then "-" else
        "\(.decay_shape.rise * 100 | round / 100) (z \(.decay_shape.rise_z | round))" end' "$1"
}

# "99.5 -> 99.5 %; 0.42 -> 0.43 % (0.41 %, -12 +- 9.8)": compare's flags at 0.1 e-/s of
# the first model and the second ($1: summary.json), the second's also at the first's
# coverage, with its over-flagged samples minus the first's and the standard error of
# that difference, paired by pixel.
flags() {
    jq -r '[.models[] | .flag_quality["0.1"]] as $q
        | .models[1].flags_at_first_coverage as $f
        | def pc: . * 1000 | round / 10;
          def pc2: . * 10000 | round / 100;
          def paired: .over_flagged_vs_first
            | "\(if .difference > 0 then "+" else "" end)\(.difference) +- \(.standard_error * 10 | round / 10)";
        "\((1 - $q[0].missed_of_measured_above) | pc) -> \((1 - $q[1].missed_of_measured_above) | pc) %; \($q[0].over_flag_fraction | pc2) -> \($q[1].over_flag_fraction | pc2) % (\(if $f == null then "-" else ($f.quality.over_flag_fraction | pc2 | tostring) + " %, " + ($f | paired) end))"' "$1"
}

for seed in $seeds; do
    # the baseline of each set of options the rows use, keyed "opts:OPTIONS"
    declare -A baseline=()
    mapfile -t option_sets < <(for row in $rows; do printf '%s\n' "$(sim_options "$row")"; done | sort -u)
    for opts in "${option_sets[@]}"; do
        base_dir=$work/none-$seed
        simulate "$base_dir" "$seed" none "$opts"
        "$persist" --log-level error fit --input "$base_dir" --out "$base_dir.json" > /dev/null
        baseline["opts:$opts"]=$(pixel_rms "$(diagnose_rms "$base_dir" "$base_dir.json" "$base_dir.diag.json")")
        rm -rf "$base_dir" "$base_dir".json "$base_dir".fit.json "$base_dir".diag.json
    done
    for row in $rows; do
        dir=$work/${row//[:+]/_}-$seed
        opts=$(sim_options "$row")
        simulate "$dir" "$seed" "$row" "$opts"
        "$persist" --log-level error fit --input "$dir" --out "$dir.json" > /dev/null
        out=$(diagnose_rms "$dir" "$dir.json" "$dir.diag.json")
        before=$(pixel_rms "$out")
        # the pixels next to far brighter ones: where the pinhole grid gives them
        marked_before=-
        [[ $opts == *pin* ]] && marked_before=$(marked "$out")
        marked_after=-
        field_before=$(field "$out")
        field_after=-
        tilt_before=$(tilt "$dir.diag.json")
        tilt_after=-
        flags_row=-
        flagging_row=-
        kind=$(named "$out")
        command=$(offered_command "$out")
        after=-
        offered=nothing
        if [[ -n $command ]]; then
            # the model the command writes: its --out
            model=$(perl -ne 'print "$1\n" if /--out (\S+)/' <<< "$command")
            offered=$(perl -ne 'print "$1\n" if /--out \S*?((?:\+[^+\s]+)+)\.json/' <<< "$command")
            offered=${offered#+}
            offered=${offered//+/ + }
            # run as printed (the words of the command; no quoting in it)
            read -r -a words <<< "$command"
            "$persist" --log-level error "${words[@]:1}" > /dev/null
            out_after=$(diagnose_rms "$dir" "$model" "$dir.after.json")
            after=$(pixel_rms "$out_after")
            [[ $opts == *pin* ]] && marked_after=$(marked "$out_after")
            field_after=$(field "$out_after")
            tilt_after=$(tilt "$dir.after.json")
            "$persist" --log-level error compare --input "$dir" --model "$dir.json" \
                --model "$model" --report "$dir.compare" > /dev/null
            flags_row=$(flags "$dir.compare/summary.json")
            flagging_row=$(flagging_rms "$dir.compare/summary.json")
        fi
        awk -v run="$row, seed $seed" -v kind="${kind:-?}" -v off="$offered" -v b="$before" \
            -v a="$after" -v z="${baseline["opts:$opts"]}" \
            -v mk="$marked_before -> $marked_after" -v fd="$field_before -> $field_after" \
            -v tl="$tilt_before -> $tilt_after" -v fl="$flags_row" -v fm="$flagging_row" 'BEGIN {
                eb = b - z
                if (mk == "- -> -") mk = "-"
                if (a == "-") {
                    printf "| %s | %s | %s | %.2f | - | %.2f | %+.2f -> - | no | %s | %s | %s | %s | %s |\n", run, kind, off, b, z, eb, mk, fd, tl, fl, fm
                    exit
                }
                ea = a - z
                halved = (ea <= 0.5 * eb || (eb <= 0 && ea <= 0)) ? "yes" : "no"
                printf "| %s | %s | %s | %.2f | %.2f | %.2f | %+.2f -> %+.2f | %s | %s | %s | %s | %s | %s |\n", run, kind, off, b, a, z, eb, ea, halved, mk, fd, tl, fl, fm
            }'
        rm -rf "$dir" "$dir".json "$dir".fit.json "$dir"+*.json "$dir".diag.json "$dir".after.json \
            "$dir".compare
    done
done | tee "$work/rows.md"
awk -F' [|] ' '
    /^[|] [^|]+, seed [0-9]+ [|]/ {
        h++; if ($3 != "nothing") o++; if ($8 ~ /^yes/) y++
        split($7, e, " "); if (e[1] + 0 <= 0) z++
        # the pixels next to far brighter ones: "+0.29 (z 11.0) -> +0.09 (z 2.4) |"
        split($9, m, " ")
        if (m[1] != "-" && m[1] != "|") {
            n++
            b = m[1] + 0; a = m[5] + 0
            if (m[5] != "-" && (a < 0 ? -a : a) <= 0.5 * (b < 0 ? -b : b)) mh++
        }
        # the field: "0.73 -> 0.25 |"
        split($10, f, " ")
        if (f[1] != "-" && f[1] + 0 > 0.2) {
            nf++
            if (f[3] != "-" && f[3] + 0 <= 0.2) fg++
        }
        # the decay tilt: "0.19 (z 24) -> 0.02 (z 3)"
        split($11, d, " ")
        if (d[1] != "-" && d[1] + 0 >= 0.07) {
            nd++
            k = (d[4] == "->") ? 5 : 3
            if (d[k] != "-" && d[k] + 0 < 0.07) dg++
        }
        # the flags: "99.5 -> 99.5 %; 0.42 -> 0.43 % (0.41 %)"
        split($12, q, " ")
        if (q[1] != "-" && q[1] != "|") {
            nq++
            if (q[3] - q[1] >= -1 && q[3] - q[1] <= 1) qc++
            if (q[7] + 0 <= q[5] + 0) qo++
            if (q[9] != "(-)" && substr(q[9], 2) + 0 <= q[5] + 0) qm++
        }
        # the pixel reference of the flagging models: "2.26 -> 4.64"
        split($13, g, " ")
        if (g[1] != "-" && g[1] != "|") { ng++; if (g[3] + 0 < g[1] + 0) gf++ }
    }
    END {
        printf "\nHidden: an addition offered in %d of %d runs; the excess over the nothing-hidden baseline halved in %d of %d. With no excess before (the pixel reference at or below the baseline): %d of %d.\n", o, h, y, h, z, h
        if (n > 0) printf "Next to far brighter pixels (where the pinhole grid gives them): their excess beyond their cells halved in %d of %d runs.\n", mh, n
        if (nf > 0) printf "A field shared by neighbouring pixels (R^2 above 0.20) before in %d runs; none left after in %d of them.\n", nf, fg + 0
        if (nd > 0) printf "A decay tilt that depends on the fluence (at least 0.07) before in %d runs; below it after in %d of them.\n", nd, dg + 0
        if (nq > 0) printf "Flags at 0.1 e-/s after the addition, in the %d runs with one: coverage within 1 percentage point of before in %d; over-flagging no higher at the model'"'"'s own margin in %d, and at the first model'"'"'s coverage in %d.\n", nq, qc + 0, qo + 0, qm + 0
        if (ng > 0) printf "The flagging model'"'"'s own pixel reference fell after the addition in %d of %d runs.\n", gf + 0, ng
    }' "$work/rows.md"
