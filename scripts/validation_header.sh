#!/usr/bin/env bash
# Prints the generated header of a validation page (docs/validation/*.md) on stdout:
# the page's title, then when, where and from what it was produced, so that every
# number below it can be traced to a machine, a commit and a command.
#
#   scripts/validation_header.sh "TITLE" "COMMAND THAT PRODUCED THE PAGE" [NOTE]
#
# The commit is `git describe --always --dirty` of the working tree ("-dirty": the page
# was produced with uncommitted changes). Used by scripts/validation.sh; a page made by
# another script should call it too.
set -euo pipefail
title=$1
command=$2
note=${3:-}
cd "$(dirname "$0")/.."

cpu=$(sed -n 's/^model name[[:space:]]*:[[:space:]]*//p' /proc/cpuinfo 2>/dev/null | head -n 1)
cores=$(nproc 2>/dev/null || echo "?")
mem_kib=$(sed -n 's/^MemTotal:[[:space:]]*\([0-9]*\) kB/\1/p' /proc/meminfo 2>/dev/null)
if [[ -n "$mem_kib" ]]; then
    mem="$(( (mem_kib + 524288) / 1048576 )) GiB"
else
    mem="? GiB"
fi
load=$(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || echo "?")
commit=$(git describe --always --dirty 2>/dev/null || echo "not a git checkout")

echo "# $title"
echo
echo "<!-- generated header: scripts/validation_header.sh; regenerate the page, do not edit it -->"
echo "| | |"
echo "|---|---|"
echo "| generated (UTC) | $(date -u +%Y-%m-%dT%H:%M:%SZ) |"
echo "| machine | ${cpu:-unknown CPU}, $cores cores, $mem, load average $load at the start |"
echo "| commit | \`$commit\` |"
echo "| command | \`$command\` |"
if [[ -n "$note" ]]; then
    echo "| note | $note |"
fi
echo "<!-- end of generated header -->"
echo
