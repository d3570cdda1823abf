#!/usr/bin/env bash
# Regenerates the validation pages under docs/validation/: current results, each page
# produced by the commands it names, with a generated header (date, machine, commit,
# command; scripts/validation_header.sh).
#
#   scripts/validation.sh [PAGE...]        (make validation [PAGES="floor bench"])
#
# Pages:
#   floor   docs/validation/floor_scan.md       `persist demo` over sky and model settings
#                                               (about 13 runs; minutes)
#   bench   docs/validation/bench.md (+ .json)  `persist bench $BENCH_ARGS` (default: the
#                                               full benchmark, tens of minutes; BENCH_ARGS=--quick
#                                               runs in about a minute)
#   matrix  docs/validation/diagnose_matrix.md  examples/diagnose_matrix $MATRIX_ARGS
#                                               (default --size 128: hours)
#   verify  docs/validation/verify.md           scripts/validate_verify.sh (minutes)
#   flag_quality  docs/validation/flag_quality.md  examples/flag_quality on the demo's
#                                               detector (seed 1) and seed 2, not used for
#                                               tuning (about two minutes; not in the default set)
#   verify_bench  docs/validation/verify_bench.md (+ .json)  `persist bench --verify-only
#                                               $VERIFY_BENCH_ARGS`: `persist verify` on full
#                                               frames and one detector-day (about 8 minutes)
#   family  docs/validation/diagnostics_family.md  examples/family_matrix $FAMILY_ARGS
#                                               (default --size 64 --seeds 5: about 5 h
#                                               alone, --resume FILE runs it in parts; not
#                                               in the default set)
#   family128  docs/validation/diagnostics_family_128.md  the same at 128 x 128, single
#                                               illuminations with nothing hidden
#                                               ($FAMILY128_ARGS; minutes; not in the default set)
#   family_heldout  docs/validation/diagnostics_family_heldout.md  the forms and seeds held
#                                               aside while the diagnostics were developed,
#                                               with the nothing-hidden rows
#                                               ($FAMILY_HELDOUT_ARGS; under an hour; not in
#                                               the default set)
#   reference  docs/validation/reference_rms.md  scripts/reference_table.sh: the pixel
#                                               reference's residual RMS on every
#                                               nothing-hidden sequence (two generators x
#                                               single/campaign x dark pixels x seeds 1-3;
#                                               about 15 minutes; not in the default set)
#   offers docs/validation/offers.md            scripts/offers_table.sh: what the addition
#                                               `diagnose` offers, run as printed, does to
#                                               the pixel reference's RMS on the second
#                                               generator's hidden campaigns (every form
#                                               not held aside that does not couple
#                                               neighbours), against the nothing-hidden
#                                               baseline, seeds 1-2 ($OFFERS_SEEDS; a subset
#                                               of forms: $OFFERS_ROWS; about 40 minutes a
#                                               seed; not in the default set)
#   offers_neighbours docs/validation/offers_neighbours.md  the same on the forms that
#                                               couple neighbours (blooming, ipc, with the
#                                               pinhole grid), seeds 1-2 (about 40 minutes;
#                                               not in the default set)
#   offers_sim docs/validation/offers_sim.md  the same on the simulator's laboratory
#                                               campaign (`persist simulate lab --campaign`),
#                                               every simulator effect, seeds 1-2 (about
#                                               90 minutes; not in the default set)
#   kinds  docs/validation/kinds.md             scripts/kinds_table.sh: the kind `diagnose`
#                                               names on the second generator's campaigns,
#                                               nothing hidden and every hidden form not
#                                               held aside, seeds 1-5 (about 40 minutes;
#                                               not in the default set)
#   long_tests  docs/validation/long_tests.md  the tests too long for `make test`
#                                               (`#[ignore = "long: ..."]`): `cargo test
#                                               --release -- --ignored`, each test's result
#                                               and each binary's time (about an hour; not
#                                               in the default set)
# Without arguments every page is regenerated. Release builds (PERSIST_BIN=path skips the
# build of the binary); run it on a quiet machine
# (the header records the load average at the start).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
out_dir=docs/validation
mkdir -p "$out_dir"

pages=("$@")
if [[ ${#pages[@]} -eq 0 ]]; then
    pages=(floor bench matrix verify verify_bench)
fi
for p in "${pages[@]}"; do
    case $p in
        floor|bench|matrix|verify|verify_bench|family|family128|family_heldout|reference|kinds|offers|offers_neighbours|offers_sim|flag_quality|long_tests) ;;
        *) echo "validation.sh: unknown page '$p' (floor, bench, matrix, verify, verify_bench, family, family128, family_heldout, reference, kinds, offers, offers_neighbours, offers_sim, flag_quality, long_tests)" >&2; exit 2 ;;
    esac
done

# PERSIST_BIN: use this binary instead of building one (it must be built from the
# commit the header names).
if [[ -n "${PERSIST_BIN:-}" ]]; then
    persist=$(realpath "$PERSIST_BIN")
else
    cargo build --release --quiet
    persist=$root/target/release/persist
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# ---------------------------------------------------------------------------------
# floor: the demo's flagged fractions, predicted and true, over a few sky settings.
page_floor() {
    local page=$out_dir/floor_scan.md
    # The default model without early release.
    "$persist" model default | sed 's/"enabled": true/"enabled": false/' > "$tmp/no-early-release.json"
    "$persist" model id "$tmp/no-early-release.json" > /dev/null
    grep -q '"enabled": false' "$tmp/no-early-release.json"

    local rows=(
        ""
        "--n12 55"
        "--size 64"
        "--size 64 --n12 55"
        "--size 64 --n12 150"
        "--size 64 --n12 430"
        "--size 64 --n12 1660"
        "--size 64 --cosmic-rate 1"
        "--size 64 --cosmic-rate 10"
        "--size 64 --n12 0 --cosmic-rate 0"
        "--size 64 --model no-early-release.json"
        "--size 64 --cosmic-rate 0 --model no-early-release.json"
        "--size 64 --n12 1660 --model no-early-release.json"
    )
    local table=$tmp/floor_rows.md
    : > "$table"
    local args
    for args in "${rows[@]}"; do
        echo "floor: persist demo $args" >&2
        # shellcheck disable=SC2086
        (cd "$tmp" && "$persist" --log-level warn demo --out demo $args) > "$tmp/demo.txt"
        awk -v cmd="persist demo${args:+ $args}" '
            /^after the first 6 h/ { split($0, a, ": "); split(a[2], b, "% of pixels above 0.1 e-\\/s, "); p1 = b[1]; sub(/% above 0.01 e-\/s/, "", b[2]); p01 = b[2] }
            /^true persistence after the first 6 h/ { split($0, a, ": "); split(a[2], b, "% above 0.1 e-\\/s, "); t1 = b[1]; sub(/% above 0.01 e-\/s/, "", b[2]); t01 = b[2] }
            /^median pixel after the first 6 h/ { for (i = 1; i <= NF; i++) { if ($i == "true") mt = $(i + 1); if ($i == "predicted") mp = $(i + 1) } }
            /^per exposure \(mean\)/ { for (i = 1; i <= NF; i++) { if ($i == "pixels" && $(i + 1) == "saturated,") sat = $(i - 2); if ($i == "hit") cr = $(i - 1) } }
            END {
                if (p1 == "" || t1 == "" || mp == "" || sat == "") { print "floor: could not read the demo output of " cmd > "/dev/stderr"; exit 1 }
                printf "| `%s` | %s%% | %s%% | %s%% | %s%% | %s | %s | %s | %s |\n", cmd, p1, p01, t1, t01, mp, mt, sat, cr
            }' "$tmp/demo.txt" >> "$table"
    done

    {
        scripts/validation_header.sh "Validation: the persistence floor of the two-day sky demo" \
            "make validation PAGES=floor (scripts/validation.sh floor)"
        cat <<'TEXT'
Each row is one `persist demo` run (one detector, 1143 exposures of 112 s: the paper's two
days of survey, seed 1; 128 x 128 pixels unless `--size 64`) and the numbers are what it
printed: the median over the exposures after the first 6 h of the fraction of pixels
whose **predicted** current (the stage's `/persistence/current`) or **true** current (the
simulator's `truth/*.truth.hdf5`) is above 0.1 and 0.01 e-/s; the median pixel's current,
predicted and true; the mean fraction of pixels saturated (`OVERFLOW`) and hit by a
cosmic ray (`TRANSIENT`) per exposure.

Settings (`persist demo --help`): `--n12` is the number of stars per 2040 x 2040 array that
saturate a pixel in one integration (default 30); `--cosmic-rate` in hits /cm^2/s (default
5); `no-early-release.json` is `persist model default` with `early_release.enabled` set to
`false`. What the rows mean for the paper's "floor" is discussed in
[the model page](../model.md#the-sky-demo-and-the-papers-floor).

| command | predicted > 0.1 | predicted > 0.01 | true > 0.1 | true > 0.01 | median pixel predicted (e-/s) | median pixel true (e-/s) | saturated / exposure | cosmic ray / exposure |
|---|---|---|---|---|---|---|---|---|
TEXT
        cat "$table"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

# ---------------------------------------------------------------------------------
# bench: `persist bench` (docs/performance.md explains the cases).
page_bench() {
    local page=$out_dir/bench.md
    local bench_args=${BENCH_ARGS:-}
    echo "bench: persist bench $bench_args" >&2
    # shellcheck disable=SC2086
    "$persist" --log-level warn bench $bench_args --json "$tmp/bench.json" > "$tmp/bench.txt"
    local kind="the full benchmark"
    if [[ " $bench_args " == *" --quick "* ]]; then
        kind="the quick benchmark (--quick: small sizes, few repetitions; rerun without it on a quiet machine for the sizes of docs/performance.md)"
    elif [[ -n "$bench_args" ]]; then
        kind="a part of the full benchmark (the sizes, thread counts and repetitions in the command); rerun with no BENCH_ARGS on a quiet machine for all of them"
    fi
    {
        scripts/validation_header.sh "Validation: performance of the model step and the stage" \
            "make validation PAGES=bench BENCH_ARGS='$bench_args' (persist bench $bench_args)" \
            "$kind"
        cat <<'TEXT'
What each column measures, and the bounds they are compared with, is in
[docs/performance.md](../performance.md). Rates are exposures per second (medians of the
pooled samples); "peak" is the stage's peak resident memory for one detector's stream and
"bound" 1.5 x (state + three float32 images). The raw samples are in
[bench.json](bench.json).

TEXT
        cat "$tmp/bench.txt"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    cp "$tmp/bench.json" "$out_dir/bench.json"
    echo "wrote $page" >&2
}

# ---------------------------------------------------------------------------------
# verify_bench: `persist bench --verify-only` (docs/performance.md explains the case).
page_verify_bench() {
    local page=$out_dir/verify_bench.md
    local args=${VERIFY_BENCH_ARGS:-}
    echo "verify_bench: persist bench --verify-only $args" >&2
    # shellcheck disable=SC2086
    "$persist" --log-level warn bench --verify-only $args --json "$tmp/verify_bench.json" > "$tmp/verify_bench.txt"
    {
        scripts/validation_header.sh "Validation: how long persist verify takes on a detector-day" \
            "make validation PAGES=verify_bench VERIFY_BENCH_ARGS='$args' (persist bench --verify-only $args)"
        cat <<'TEXT'
The case (f) of `persist bench` ([docs/performance.md](../performance.md#persist-verify-on-a-full-frame)):
`persist verify` (tracking, stacking and its report) over the stage's outputs of the
simulator's default sky survey (seed 1, one detector, the default model, the truth
removed as in flight), timed whole in a child process. The full frame is run for a few
exposures; one detector-day (571 exposures of 112 s) is run at a smaller frame with the
same density of stars per pixel, and so are its first exposures, which give the measured
ratio of the two sizes. "track samples" are the pixel-exposures followed after an
event; "peak" the child's peak resident memory. The raw numbers are in
[verify_bench.json](verify_bench.json).

TEXT
        cat "$tmp/verify_bench.txt"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    cp "$tmp/verify_bench.json" "$out_dir/verify_bench.json"
    echo "wrote $page" >&2
}

# ---------------------------------------------------------------------------------
# matrix: hidden effects in simulated laboratory campaigns, diagnosed and refitted.
page_matrix() {
    local page=$out_dir/diagnose_matrix.md
    local matrix_args=${MATRIX_ARGS:---size 128}
    echo "matrix: cargo run --release --example diagnose_matrix -- $matrix_args" >&2
    # shellcheck disable=SC2086
    cargo run --release --quiet --example diagnose_matrix -- $matrix_args --out "$tmp/matrix.md" >&2
    {
        scripts/validation_header.sh "Validation: what persist diagnose finds" \
            "make validation PAGES=matrix MATRIX_ARGS='$matrix_args' (cargo run --release --example diagnose_matrix -- $matrix_args)"
        cat <<'TEXT'
Hidden effects in simulated laboratory campaigns (`persist simulate lab --campaign
--effect NAME`), each diagnosed against a reference model, refitted with `fit --with` and
compared, as the command line does it (`examples/diagnose_matrix.rs` makes the same
library calls). How to read `diagnose` is in [docs/diagnostics.md](../diagnostics.md).

TEXT
        cat "$tmp/matrix.md"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    if [[ -f "$tmp/matrix.jsonl" ]]; then
        cp "$tmp/matrix.jsonl" "$out_dir/diagnose_matrix.jsonl"
    fi
    echo "wrote $page" >&2
}

# One page of examples/family_matrix: family_page NAME TITLE MAKE_VAR ARGS.
family_page() {
    local name=$1 title=$2 var=$3 args=$4
    local page=$out_dir/$name.md key=${var%_ARGS}
    key=${key,,}
    echo "$name: cargo run --release --example family_matrix -- $args" >&2
    # shellcheck disable=SC2086
    cargo run --release --quiet --example family_matrix -- $args \
        --persist "$persist" --work "$tmp/$name" --out "$tmp/$name.md" >&2
    {
        scripts/validation_header.sh "$title" \
            "make validation PAGES=$key $var='$args' (cargo run --release --example family_matrix -- $args)"
        # the example's own title and date line are replaced by the header above
        sed -n '/^Data: /,$p' "$tmp/$name.md" |
            sed "s|$tmp/$name.jsonl|$out_dir/$name.jsonl|"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    cp "$tmp/$name.jsonl" "$out_dir/$name.jsonl"
    echo "wrote $page" >&2
}

# family: the diagnostics on the second truth generator, default commands only.
page_family() {
    family_page diagnostics_family "Diagnostics on the family of the second truth generator" \
        FAMILY_ARGS "${FAMILY_ARGS:---size 64 --seeds 5}"
}

# family128: single illuminations of 128 x 128 with nothing hidden: what diagnose's
# defaults declare there, and how long it takes.
page_family128() {
    family_page diagnostics_family_128 \
        "Diagnostics on 128 x 128 single illuminations of the second truth generator" \
        FAMILY128_ARGS "${FAMILY128_ARGS:---size 128 --seeds 5 --rows none@single,none@single+dark}"
}

# family_heldout: the forms (trapgen::hidden::HELD_ASIDE) and seeds (from
# HELD_ASIDE_FIRST_SEED on) nobody looked at while developing the diagnostics, beside the
# nothing-hidden rows at the same seeds.
page_family_heldout() {
    family_page diagnostics_family_heldout \
        "Diagnostics on the held-aside forms and seeds of the second truth generator" \
        FAMILY_HELDOUT_ARGS "${FAMILY_HELDOUT_ARGS:---held-out --size 64 --seeds 5 --first-seed 100 --rows none@single,none@single+dark,none@campaign,none@campaign+dark,temperature:weight,populations:patches,shape:fast_ceiling}"
}

# flag_quality: the flags against the simulator's truth, the demo's detector and a
# second seed not used for tuning.
page_flag_quality() {
    local page=$out_dir/flag_quality.md
    cargo build --release --quiet --example flag_quality
    local bin=$root/target/release/examples/flag_quality
    {
        scripts/validation_header.sh "Validation: flag quality against the simulator's truth" \
            "make validation PAGES=flag_quality"
        cat <<'TEXT'
What the flags cost and miss, counted the way a user evaluating the stage would: every
pixel-exposure from exposure 200 on, non-functional pixels left out, against the
simulator's true persistence current (`persist::flag_quality`, the same counts
`persist demo` prints). The models, each fitted on the same detector's laboratory
sequence: `persist fit`'s default (the paper's calibration with `refill`, the overlap of
an illumination's filling with the charge its traps still hold, measured on the
sequence; the flags calibrated to 95 % coverage, `persist::calib::coverage`: the margin
the laboratory data ask for at 0.1 and 0.01 e-/s in every time bin and band of measured
current; early release keeping the threshold, `early_release.keep: threshold`,
docs/model.md "Early release"); its parts apart: without `refill` (the paper's sum of
fillings) and released pixels reset to zero (the paper's), with either alone; without
`refill` at the paper's 95th percentile x 1.2 (`--no-coverage`), each of those two with
and without the per-pixel map (`persist::pixmap`, margin 1), and with the decay
reshaped in time; and the paper's default model. Rows "+ transient rule measured in
flight" give a model the transient rule the way operations would: `persist verify` on
the stage's outputs of the same sky run's exposures 0-199 (before the counted ones,
flagged with that model), then `persist fit --from-verify` on its report; the rule
reads what the exposures after each `TRANSIENT` measure, not the simulator's
cosmic-ray charges. The baselines: time-window flaggers (a pixel saturated in the last
W seconds flagged at both thresholds, as jwst's persistence step and snowblind do), for
several W; and HST WFC3's persistence model in closed form (kslong/Persistence
`subtract_persist.py`, `calc_persist` and `do_dataset`; Long, Baggett & MacKenty, WFC3
ISR 2015-15; `persist::flag_quality::Wfc3Flagger`): per pixel the largest, over the
exposures that ended in the last 16 h, of 0.3 e-/s (x / 83,400 e-)^0.159 / (exp((83,400
e- - x) / 18,500 e-) + 1) (dt / 1000 s)^-1.022, x that exposure's extrapolated fluence
and dt the time from its end to the middle of the exposure flagged. Its constants are
WFC3's published ones in electrons as they are, not rescaled to this detector's full
well (200,000 e-). The laboratory sequence keeps a corner of size/8 x size/8 pixels dark (the
measured currents' dark level and noise come from it). Below each table, where the
errors are (`persist::flag_causes`; the truth only counts) for the model without
`refill` and for `fit`'s default with the measured transient rule: by the kind of the
pixel's last event, the time since it, whether early release acted since, and
predicted / true. Without `refill`, most over-flagging at 0.01 e-/s follows unsaturated
sources (the paper's sum adds every exposure's filling to the charge still trapped, and
predicts 2-10 times the truth hours later) and over 90 % of the misses at both
thresholds are pixels early release acted on since their last event (amplitudes reset
to zero). Either alone does not help: `refill` alone misses as many, the threshold kept
without `refill` doubles the over-flagging at 0.01 e-/s; together they take most of
the misses at 0.01 e-/s away and flag less at both thresholds, on both seeds: hence
`fit`'s default. Without a rule measured in flight, most of the over-flagging at 0.1
e-/s is the first 1000 s after a `TRANSIENT`. With it, little of the over-flagging
follows hits: the simulator's hits leave no persistence of their own, and the rule
(the 95th percentile of what the first exposure after each hit measures, sources
screened by their extent and the measurement noise taken out in quadrature,
`persist::verify::transient`) comes out near zero; the exposure after a hit then follows
the prediction. What over-flagging remains at 0.1 e-/s follows bright sources within
1000 s, predicted 1-2 times the truth (the margin); at 0.01 e-/s, mostly 2-10 times the
truth hours after unsaturated sources (the decay's late tail). The misses at 0.1 e-/s
are pixels early release acted on, predicted 0.5-1 times the truth; at 4 noise sigmas
of evidence (the default) none of them has a true current above 0.2 e-/s (the counts
in brackets). With the per-pixel map at margin 1 a few pixel-exposures above 0.2 e-/s
are missed without any release: on seed 1, three, where the map predicts a quarter of
the truth.

## The demo's detector (seed 1)

TEXT
        "$bin" --seed 1
        echo
        echo "## A second detector (seed 2, not used for tuning)"
        echo
        "$bin" --seed 2
        echo
        cat <<'TEXT'
## Early release: evidence against the count of three (seed 1)

The models above release a flagged pixel when its measurements, less the background,
add up to 4 noise sigmas of evidence that its persistence is below both the threshold
and its prediction (`early_release.rule: evidence`, docs/model.md "Early release").
Here every model releases by the paper-style count instead: after 3 exposures in a
row measured below the threshold (`rule: consecutive`). On the sky's noise (about
0.12 e-/s per pixel) a pixel whose true current sits just above 0.1 e-/s is measured
below it about half the time, three times in a row within a few exposures: released,
its amplitudes are zero and it stays unflagged whatever the margin.

TEXT
        "$bin" --seed 1 --release-rule consecutive --no-causes
        echo
        cat <<'TEXT'
## The paper's 14 h of laboratory darks (seed 1)

The paper's laboratory took darks "every three minutes over the following fourteen
hours" (section 2.1); the demo's sequence has 1.5 h. With 280 darks after the first
illumination the coverage's time bins reach 56,000 s. There a single dark's noise
(about 0.02 e-/s) is twice the low threshold and nearly every pixel is truly below
it: the coverage counts a pixel's mean over a time bin's darks, not single darks
(`persist::calib::coverage`, "Rule"), whose noise excursions would otherwise ask for
15 times the knots at 0.01 e-/s (`examples/coverage_bins.rs`).

TEXT
        "$bin" --seed 1 --lab-darks 280 --no-causes
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

# verify: persist verify against the simulator's truth (its own script).
page_reference() {
    local page=$out_dir/reference_rms.md
    echo "reference: scripts/reference_table.sh" >&2
    {
        scripts/validation_header.sh "The pixel reference on data with nothing hidden" \
            "make validation PAGES=reference (scripts/reference_table.sh)"
        PERSIST_BIN=$persist WORK=$tmp/reference scripts/reference_table.sh
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

# kinds: the kind diagnose names, from its first step alone (its own script).
page_kinds() {
    local page=$out_dir/kinds.md
    cargo build --release --quiet --example dependence_scan
    echo "kinds: scripts/kinds_table.sh" >&2
    {
        scripts/validation_header.sh "The kind diagnose names, on the second generator's campaigns" \
            "make validation PAGES=kinds (scripts/kinds_table.sh)"
        PERSIST_BIN=$persist SCAN_BIN=$root/target/release/examples/dependence_scan \
            WORK=$tmp/kinds scripts/kinds_table.sh
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

# An offers page ($1, under $out_dir): scripts/offers_table.sh with seeds $4, rows $5
# (empty: every form) and source $6 (default family), titled $2, its command in the
# header $3.
offers_page() {
    local page=$out_dir/$1
    echo "$1: scripts/offers_table.sh" >&2
    {
        scripts/validation_header.sh "$2" "$3"
        PERSIST_BIN=$persist SEEDS="$4" ROWS="$5" SOURCE="${6:-family}" WORK=$tmp/${1%.md} \
            scripts/offers_table.sh
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

# offers: what the offered addition does to the pixel reference.
# Every form but those that couple neighbours (offers_neighbours), seeds 1-2.
page_offers() {
    local seeds="${OFFERS_SEEDS:-1 2}"
    local rows="${OFFERS_ROWS:-soak:capture soak:diffusion capacity:ceiling capacity:langmuir temperature:arrhenius populations:smooth shape:fill_depth}"
    offers_page offers.md "What the offered addition does, on the second generator's campaigns" \
        "make validation PAGES=offers (scripts/offers_table.sh; SEEDS=\"$seeds\"; ROWS=\"$rows\")" \
        "$seeds" "$rows"
}

# offers_neighbours: the same on the forms that couple neighbours.
page_offers_neighbours() {
    local seeds="${OFFERS_SEEDS:-1 2}" rows="blooming:spill blooming:field ipc:cross4 ipc:aniso8"
    offers_page offers_neighbours.md \
        "What the offered addition does next to far brighter pixels, on the second generator's campaigns" \
        "make validation PAGES=offers_neighbours (scripts/offers_table.sh; SEEDS=\"$seeds\"; ROWS=\"$rows\")" \
        "$seeds" "$rows"
}

# offers_sim: the same on the simulator's laboratory campaign, every simulator effect.
page_offers_sim() {
    local seeds="${OFFERS_SEEDS:-1 2}"
    # shellcheck source=scripts/family_forms.sh
    source scripts/family_forms.sh
    local rows="${OFFERS_ROWS:-$LAB_EFFECTS}"
    offers_page offers_sim.md "What the offered addition does, on the simulator's campaigns" \
        "make validation PAGES=offers_sim (scripts/offers_table.sh; SOURCE=lab; SEEDS=\"$seeds\"; ROWS=\"$rows\")" \
        "$seeds" "$rows" lab
}

# long_tests: the ignored tests, in release, each test's result and each binary's time.
page_long_tests() {
    local page=$out_dir/long_tests.md
    local log=$tmp/long_tests.log
    echo "long_tests: cargo test --release --no-fail-fast -- --ignored" >&2
    local status=0
    cargo test --release --no-fail-fast -- --ignored > "$log" 2>&1 || status=$?
    {
        scripts/validation_header.sh "The tests too long for make test" \
            "make validation PAGES=long_tests (cargo test --release --no-fail-fast -- --ignored)"
        echo "The tests marked \`#[ignore]\` run here, in a release build; \`make test\` (the"
        echo "README's test command, run by CI) skips them. Each one's documentation says what it"
        echo "checks. \`cargo test\` exit status: $status."
        echo
        echo "| test binary | test | result |"
        echo "|---|---|---|"
        awk '/^ *Running /{bin=($2 == "unittests") ? $3 : $2} /^test .* \.\.\. (ok|FAILED)$/{print "| " bin " | `" $2 "` | " $NF " |"}' "$log"
        echo
        echo "| test binary | tests | seconds |"
        echo "|---|---|---|"
        awk '/^ *Running /{bin=($2 == "unittests") ? $3 : $2} /^test result:/{n=$4+$6; if (n > 0) {t=$NF; sub(/s$/, "", t); print "| " bin " | " n " | " t " |"}}' "$log"
    } > "$page.tmp"
    mv "$page.tmp" "$page"
    echo "wrote $page" >&2
}

page_verify() {
    PERSIST_BIN=$persist scripts/validate_verify.sh
}

for p in "${pages[@]}"; do
    "page_$p"
done
