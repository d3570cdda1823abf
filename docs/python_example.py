"""A notebook-style tour of the `persist` Python package (docs/python.md).

Simulates a short SPHEREx-like sequence, steps the persistence model over it in Python
(the stage's own step, on numpy arrays), and plots one pixel's predicted persistence
current with matplotlib. Run:

    python docs/python_example.py [OUT_DIR]

It writes OUT_DIR/pixel_persistence.png (default OUT_DIR: python_example_out). The
pytest suite (python/tests/test_example.py) runs it in CI.
"""

# %% Setup
import glob
import os
import sys

import matplotlib

matplotlib.use("Agg")  # no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import persist  # noqa: E402

out = sys.argv[1] if len(sys.argv) > 1 else "python_example_out"
os.makedirs(out, exist_ok=True)

# %% Simulate 30 exposures of one 128 x 128 detector (as `persist simulate sky`)
sky = os.path.join(out, "sky")
n = persist.simulate_sky(sky, size=128, detectors=1, exposures=30, seed=7)
paths = sorted(p for p in glob.glob(os.path.join(sky, "**", "*.h5"), recursive=True)
               if os.sep + "truth" + os.sep not in p)
exposures = sorted((persist.read_product(p) for p in paths),
                   key=lambda e: e["exposure_index"])
print(f"{n} products simulated in {sky}")

# %% Step the default model (the paper's constants) over the sequence
model = persist.Model.default()
state = persist.State(model, exposures[0]["image"].shape)
times, currents, flagged = [], [], []
for e in exposures:
    r = model.step(state, e["image"], e["flags"], e["t_exposure_s"],
                   t_start_unix_s=e["t_start_unix_s"],
                   t_illuminated_s=e["t_illuminated_s"],
                   focal_plane_temp_k=e["focal_plane_temp_k"])
    times.append(e["t_start_unix_s"] + 0.5 * e["t_exposure_s"])
    currents.append(r.current_e_per_s)
    flagged.append(r.persistence_flags & persist.PFLAG_HIGH != 0)
currents = np.stack(currents)
flagged = np.stack(flagged)

# %% The pixel with the largest predicted persistence anywhere in the sequence
k, y, x = np.unravel_index(np.argmax(currents), currents.shape)
t_h = (np.array(times) - times[0]) / 3600.0
print(f"pixel ({y}, {x}): up to {currents[k, y, x]:.3g} e-/s at exposure {k}, "
      f"flagged in {int(flagged[:, y, x].sum())} of {len(exposures)} exposures")

fig, ax = plt.subplots(figsize=(7, 4))
ax.semilogy(t_h, np.maximum(currents[:, y, x], 1e-4), "o-", label="predicted persistence")
ax.axhline(model.threshold_high_e_per_s, color="C3", ls="--",
           label=f"high threshold {model.threshold_high_e_per_s} e-/s")
ax.axhline(model.threshold_low_e_per_s, color="C2", ls=":",
           label=f"low threshold {model.threshold_low_e_per_s} e-/s")
ax.set_xlabel("time since the first exposure (h)")
ax.set_ylabel("current at t_meas (e-/s)")
ax.set_title(f"persist: pixel ({y}, {x}) of a simulated sky sequence")
ax.legend(fontsize=8)
fig.tight_layout()
png = os.path.join(out, "pixel_persistence.png")
fig.savefig(png, dpi=100)
print(f"wrote {png}")
