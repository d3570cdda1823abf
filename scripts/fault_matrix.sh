#!/usr/bin/env bash
# The fault-injection matrix of docs/operations.md ("Write faults and cuts"): runs
# tests/ops_write_faults.rs (strace on the real binary) and puts the table it writes
# between the fault-matrix markers of docs/operations.md.
set -euo pipefail
cd "$(dirname "$0")/.."
command -v strace >/dev/null || bash scripts/bootstrap.sh
table="$(mktemp)"
trap 'rm -f "$table"' EXIT
PERSIST_FAULT_TABLE="$table" cargo test --release --test ops_write_faults -- --nocapture
python3 - "$table" docs/operations.md <<'PY'
import sys
table, doc = sys.argv[1], sys.argv[2]
begin, end = "<!-- fault-matrix:begin -->", "<!-- fault-matrix:end -->"
text = open(doc).read()
head, rest = text.split(begin)
_, tail = rest.split(end)
open(doc, "w").write(head + begin + "\n" + open(table).read() + end + tail)
PY
echo "fault_matrix: docs/operations.md updated" >&2
