#!/usr/bin/env bash
# What the addition `persist diagnose` offers does to the pixel reference's RMS, on the
# second truth generator's campaigns (`persist simulate family --sequence campaign`,
# 64 x 64, seeds 1-5): each event-level hidden form of scripts/kinds_table.sh and the
# nothing-hidden campaign of the same seed (the baseline). Default `fit` and `diagnose`;
# then exactly the `persist fit` command the verdict prints (its first "add it with" /
# "add both with"), and `diagnose` again on the model it writes. Prints Markdown on
# stdout (scripts/validation.sh offers writes it to docs/validation/offers.md).
#
#   PERSIST_BIN=target/release/persist WORK=/tmp/offers scripts/offers_table.sh
#   SEEDS="1 2" ROWS="soak:capture" scripts/offers_table.sh     (a subset)
set -euo pipefail
persist=$(realpath "${PERSIST_BIN:-target/release/persist}")
work=${WORK:-$(mktemp -d)}
seeds=${SEEDS:-1 2 3 4 5}
rows=${ROWS:-soak:capture soak:diffusion capacity:ceiling capacity:langmuir temperature:arrhenius}
mkdir -p "$work"

cat <<'TEXT'
The addition `persist diagnose` offers, run as printed, against the pixel reference
(the line "pixel reference" of `diagnose`: the flexible base times each pixel's own
amplitude and decay shape; [reference_rms.md](reference_rms.md)). Per run: the default
`persist fit --input D --out M.json` and `persist diagnose --input D --model M.json`;
the `persist fit` command its verdict prints, run as printed; `diagnose` again on the
model that command writes. Before / after: the pixel reference's normalised residual
RMS of the two diagnoses; baseline: the same on the nothing-hidden campaign of the
same seed (default `fit` and `diagnose`). Excess = RMS - baseline; halved: the excess
after at most half the excess before (an excess before of at most 0 counts as halved
when the excess after is at most 0 too).

| run | named | offered | before | after | baseline | excess before -> after | halved |
|---|---|---|---|---|---|---|---|
TEXT

# The pixel reference's RMS in diagnose's output ($1).
pixel_rms() {
    sed -n 's/^pixel reference.*residual RMS \([0-9.]*\) over [0-9]* cells$/\1/p' <<< "$1"
}

# The kind the verdict names ($1: diagnose's output): the missing effect's covariate,
# or the covariate the residual depends on; "nothing" otherwise.
named() {
    perl -ne '
        if (/^missing effect: \S+ \(the evidence is in the residual against (\w+)/) { print "$1\n"; exit }
        if (/(\w+) or (\w+): confounded in these data\./) { print "$1 / $2\n"; exit }
        if (/^no library effect is significant alone, but (\S+) and (\S+) are together/) { print "$1 + $2\n"; exit }
        if (/^the residual of .* depends on (\w+) /) { print "$1\n"; exit }
        if (/^no library effect is significant; /) { print "nothing\n"; exit }' <<< "$1"
}

# The first `persist fit` command the verdict offers ($1), empty when none.
offered_command() {
    perl -ne 'if (/add (?:it|both) with: (persist fit .*?)(?= \(|\. |; |$)/) { print "$1\n"; exit }' <<< "$1"
}

diagnose_rms() {
    "$persist" --log-level error diagnose --input "$1" --model "$2"
}

for seed in $seeds; do
    base_dir=$work/none-$seed
    "$persist" --log-level error simulate family --out "$base_dir" --size 64 --seed "$seed" \
        --sequence campaign > /dev/null
    "$persist" --log-level error fit --input "$base_dir" --out "$base_dir.json" > /dev/null
    baseline=$(pixel_rms "$(diagnose_rms "$base_dir" "$base_dir.json")")
    rm -rf "$base_dir" "$base_dir".json "$base_dir".fit.json
    for row in $rows; do
        dir=$work/${row//[:+]/_}-$seed
        "$persist" --log-level error simulate family --out "$dir" --size 64 --seed "$seed" \
            --sequence campaign --hidden "$row" > /dev/null
        "$persist" --log-level error fit --input "$dir" --out "$dir.json" > /dev/null
        out=$(diagnose_rms "$dir" "$dir.json")
        before=$(pixel_rms "$out")
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
            after=$(pixel_rms "$(diagnose_rms "$dir" "$model")")
        fi
        awk -v run="$row, seed $seed" -v kind="${kind:-?}" -v off="$offered" -v b="$before" \
            -v a="$after" -v z="$baseline" 'BEGIN {
                eb = b - z
                if (a == "-") {
                    printf "| %s | %s | %s | %.2f | - | %.2f | %+.2f -> - | no |\n", run, kind, off, b, z, eb
                    exit
                }
                ea = a - z
                halved = (ea <= 0.5 * eb || (eb <= 0 && ea <= 0)) ? "yes" : "no"
                printf "| %s | %s | %s | %.2f | %.2f | %.2f | %+.2f -> %+.2f | %s |\n", run, kind, off, b, a, z, eb, ea, halved
            }'
        rm -rf "$dir" "$dir".json "$dir".fit.json "$dir"+*.json
    done
done | tee "$work/rows.md"
awk -F' [|] ' '
    /^[|] [a-z]+:/ { h++; if ($3 != "nothing") o++; if ($8 ~ /^yes/) y++ }
    END {
        printf "\nHidden: an addition offered in %d of %d runs; the excess over the nothing-hidden baseline halved in %d of %d.\n", o, h, y, h
    }' "$work/rows.md"
