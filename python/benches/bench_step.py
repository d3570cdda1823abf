"""Benchmark: `persist.Model.step` from Python against the pure Rust step, in one run.

Both step the default model over the same two synthetic 2040 x 2040 frames
(`persist::bench::synthetic_frame`, alternating) on a warm state, with the same rayon
pool: the Rust side is `persist bench`'s step case run inside this process
(`persist._bench_rust_step`: buffers reused, each step timed in Rust); the Python side
times each `model.step(...)` call whole (argument conversion, the copy of the flag
plane the step writes into, output allocation, the summary as a dict). Rounds
interleave the two so that a change in the machine's load hits both.

    python python/benches/bench_step.py [--size 2040] [--reps 5] [--rounds 3] [--json FILE]
        [--doc docs/python.md]

Prints the medians and their ratio (the criterion: Python within 1.2 x of Rust); exits
1 when the ratio is above 1.2. `--doc FILE` also writes the printed table, the command
and the machine's load into FILE between the `<!-- bench_step:begin -->` and
`<!-- bench_step:end -->` lines (docs/python.md's measured table).
"""

import argparse
import json
import os
import statistics
import sys
import time

import persist

T_EXPOSURE_S = 112.0  # persist::bench: 112 s integrations every 150 s
CADENCE_S = 150.0
T0_UNIX_S = 1_772_323_200.0


def python_samples(size, reps, warm=3):
    model = persist.Model.default()
    state = persist.State(model, (size, size))
    frames = [persist._synthetic_frame(size, k) for k in (0, 1)]
    out = []
    for k in range(warm + reps):
        image, flags = frames[k % 2]
        t = time.perf_counter()
        r = model.step(state, image, flags, T_EXPOSURE_S,
                       t_start_unix_s=T0_UNIX_S + k * CADENCE_S, exposure_index=k)
        dt = time.perf_counter() - t
        del r
        if k >= warm:
            out.append(dt)
    return out


BEGIN, END = "<!-- bench_step:begin -->", "<!-- bench_step:end -->"


def write_doc(path, lines):
    """Replace the lines between BEGIN and END in `path` with `lines`."""
    with open(path) as f:
        text = f.read()
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise SystemExit(f"{path}: needs one {BEGIN} line and one {END} line after it")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    with open(path, "w") as f:
        f.write(head + BEGIN + "\n" + "\n".join(lines) + "\n" + END + tail)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2040)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", help="write the samples and medians here")
    ap.add_argument("--doc", help="write the table between the bench_step markers of this file")
    a = ap.parse_args()
    rust, py = [], []
    for _ in range(a.rounds):
        rust += persist._bench_rust_step(a.size, a.reps)
        py += python_samples(a.size, a.reps)
    mr, mp = statistics.median(rust), statistics.median(py)
    ratio = mp / mr
    verdict = "within" if ratio <= 1.2 else "NOT within"
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    args = " ".join(sys.argv[1:])
    lines = [
        f"`python python/benches/bench_step.py {args}`: step of {a.size} x {a.size}, "
        f"{len(rust)} samples each ({a.rounds} interleaved rounds of {a.reps}), "
        f"{os.cpu_count()} CPUs, load average {load} at the end:",
        "",
        "| side | median (ms) | min (ms) | max (ms) |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, s in (("Rust (persist bench step case)", rust), ("Python (Model.step)", py)):
        lines.append(f"| {name} | {1e3 * statistics.median(s):.1f} | {1e3 * min(s):.1f} | "
                     f"{1e3 * max(s):.1f} |")
    lines += ["", f"Python / Rust = {ratio:.3f} (medians; {verdict} 1.2 x)"]
    print("\n".join(lines))
    if a.doc:
        write_doc(a.doc, lines)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"size": a.size, "rust_s": rust, "python_s": py,
                       "rust_median_s": mr, "python_median_s": mp, "ratio": ratio}, f,
                      indent=1)
    return 0 if ratio <= 1.2 else 1


if __name__ == "__main__":
    raise SystemExit(main())
