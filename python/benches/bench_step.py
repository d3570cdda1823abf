"""Benchmark: `persist.Model.step` from Python against the pure Rust step, in one run.

Both step the default model over the same two synthetic 2040 x 2040 frames
(`persist::bench::synthetic_frame`, alternating) on a warm state, with the same rayon
pool: the Rust side is `persist bench`'s step case run inside this process
(`persist._bench_rust_step`: buffers reused, each step timed in Rust); the Python side
times each `model.step(...)` call whole (argument conversion, the copy of the flag
plane the step writes into, output allocation, the summary as a dict). Rounds
interleave the two so that a change in the machine's load hits both.

    python python/benches/bench_step.py [--size 2040] [--reps 5] [--rounds 3] [--json FILE]

Prints the medians and their ratio (the criterion: Python within 1.2 x of Rust).
"""

import argparse
import json
import platform
import statistics
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2040)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", help="write the samples and medians here")
    a = ap.parse_args()
    rust, py = [], []
    for _ in range(a.rounds):
        rust += persist._bench_rust_step(a.size, a.reps)
        py += python_samples(a.size, a.reps)
    mr, mp = statistics.median(rust), statistics.median(py)
    ratio = mp / mr
    print(f"step of {a.size} x {a.size}, {len(rust)} samples each "
          f"({a.rounds} interleaved rounds of {a.reps}), {platform.node()}")
    print("| side | median (ms) | min (ms) | max (ms) |")
    print("| --- | ---: | ---: | ---: |")
    for name, s in (("Rust (persist bench step case)", rust), ("Python (Model.step)", py)):
        print(f"| {name} | {1e3 * statistics.median(s):.1f} | {1e3 * min(s):.1f} | "
              f"{1e3 * max(s):.1f} |")
    verdict = "within" if ratio <= 1.2 else "NOT within"
    print(f"Python / Rust = {ratio:.3f} ({verdict} 1.2 x)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"size": a.size, "rust_s": rust, "python_s": py,
                       "rust_median_s": mr, "python_median_s": mp, "ratio": ratio}, f,
                      indent=1)
    return 0 if ratio <= 1.2 else 1


if __name__ == "__main__":
    raise SystemExit(main())
