#!/usr/bin/env bash
# Regenerates docs/validation/pixel_map.md: the per-pixel response map against the
# global 95th-percentile model on the simulator's truth (examples/pixel_map_validation),
# with the simulator's cosmic rays and without them, and the map learned in flight after
# FLIGHT_DAYS days of sky. About six minutes in release.
#
#   scripts/validate_pixel_map.sh [SIZE] [EXPOSURES] [FLIGHT_DAYS]
set -euo pipefail
cd "$(dirname "$0")/.."
size=${1:-128}
exposures=${2:-1143}
flight_days=${3:-1,2,4,8}
margins=0.7,0.8,0.9,1,1.2
cargo build --release --example pixel_map_validation >&2
bin=target/release/examples/pixel_map_validation
page=docs/validation/pixel_map.md
tmp=$(mktemp)
{
    scripts/validation_header.sh "Validation: per-pixel response maps against the global model" \
        "scripts/validate_pixel_map.sh $size $exposures $flight_days"
    echo
    echo "What is compared and why: [docs/pixel_map.md](../pixel_map.md). The same simulated"
    echo "detector (seed 1) is measured in the laboratory sequence of"
    echo "\`persist::pixmap::eval::lab_campaign\`, which gives the global model (\`persist fit\`'s"
    echo "calibration, the paper's 95th percentile x 1.2) and the map; then its sky run is flagged"
    echo "by the global model and by the model with the map at several margins."
    echo
    echo "## Sky with the simulator's cosmic rays (5 per cm^2 per s)"
    echo
    "$bin" --size "$size" --exposures "$exposures" --skip-h 6 --margins "$margins"
    echo
    echo "## Sky without cosmic rays"
    echo
    echo "A transient gets the maximum amplitude and the next exposure is flagged whatever the"
    echo "prediction, until early release has seen three measurements below 0.1 e-/s: at least"
    echo "three flagged exposures per hit, whatever the pixel's response. Without cosmic rays"
    echo "what remains is what the persistence model decides."
    echo
    "$bin" --size "$size" --exposures "$exposures" --skip-h 6 --margins "$margins" --cosmic-rate 0
    echo
    echo "## Learned in flight"
    echo
    echo "The same detector's sky, flagged by the global model and followed by \`verify\`'s"
    echo "tracks; a flight map (\`persist::pixmap::flight\`) is built from the first N days,"
    echo "alone and starting from the laboratory map; then each model flags the next day of"
    echo "sky, which no map learned from. Margin 0.8 for every map (the laboratory map's"
    echo "over-flagging falls with its margin, section above; at 1 it hardly changes)."
    echo
    "$bin" --size "$size" --flight-days "$flight_days" --eval-days 1 --skip-h 6 --margin 0.8
} > "$tmp"
mv "$tmp" "$page"
echo "wrote $page" >&2
