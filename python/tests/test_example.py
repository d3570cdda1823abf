"""docs/python_example.py runs and writes its plot."""

import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
EXAMPLE = os.path.join(HERE, "..", "..", "docs", "python_example.py")


def test_example_runs_and_plots(tmp_path):
    r = subprocess.run([sys.executable, EXAMPLE, str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    png = tmp_path / "pixel_persistence.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 10_000
    assert "30 products simulated" in r.stdout
