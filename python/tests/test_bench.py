"""python/benches/bench_step.py: prints the medians and their ratio and writes them into
a document between its markers (docs/python.md's benchmark table)."""

import json
import os
import re
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.join(HERE, "..", "benches", "bench_step.py")


def test_bench_writes_the_ratio_of_the_medians_into_the_doc(tmp_path):
    doc = tmp_path / "page.md"
    doc.write_text("before\n<!-- bench_step:begin -->\nold\n<!-- bench_step:end -->\nafter\n")
    samples = tmp_path / "samples.json"
    r = subprocess.run([sys.executable, BENCH, "--size", "64", "--reps", "3", "--rounds", "2",
                        "--json", str(samples), "--doc", str(doc)],
                       capture_output=True, text=True, timeout=300)
    # Exit status 1 means "not within 1.2 x" (likely at 64 x 64, where the call's
    # overhead is most of the step); anything else is a failure.
    assert r.returncode in (0, 1), r.stderr
    s = json.loads(samples.read_text())
    assert len(s["rust_s"]) == len(s["python_s"]) == 6
    ratio = s["python_median_s"] / s["rust_median_s"]
    assert abs(s["ratio"] - ratio) < 1e-12
    assert (r.returncode == 0) == (ratio <= 1.2)
    text = doc.read_text()
    assert text.startswith("before\n<!-- bench_step:begin -->\n")
    assert text.endswith("<!-- bench_step:end -->\nafter\n")
    assert "old" not in text
    m = re.search(r"Python / Rust = ([0-9.]+)", text)
    assert m and abs(float(m.group(1)) - ratio) < 5e-4, text
    assert "bench_step.py --size 64 --reps 3 --rounds 2" in text
    assert r.stdout.strip() in text
