"""Shared data of the Python suite: a small simulated sky sequence run through the
stage (the command line's own code, through `persist.run`), and a small laboratory
sequence. Each is made once per test module that asks for it."""

import glob
import os

import pytest

import persist


def products(directory):
    """The `*.h5` products of a directory, in (detector, exposure index) order."""
    paths = glob.glob(os.path.join(directory, "**", "*.h5"), recursive=True)
    paths = [p for p in paths if os.sep + "truth" + os.sep not in p]
    def key(p):
        e = persist.read_product(p)
        return e["detector"], e["exposure_index"]

    return sorted(paths, key=key)


@pytest.fixture(scope="module")
def sky_run(tmp_path_factory):
    """64 x 64, one detector, 12 exposures of the sky simulator, run through the
    stage with the default model: (input dir, output dir, checkpoint dir, run summary)."""
    root = tmp_path_factory.mktemp("sky")
    sky, out, ckpt = root / "sky", root / "out", root / "ckpt"
    n = persist.simulate_sky(sky, size=64, detectors=1, exposures=12, seed=3)
    assert n == 12
    summary = persist.run(sky, out, ckpt, quarantine=root / "quarantine")
    assert summary["errors"] == [], summary["errors"]
    assert summary["processed"] == 12
    return sky, out, ckpt, summary


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The paper's laboratory test at 64 x 64 with 60 darks, and the default model
    written as a model file: (lab dir, model path)."""
    root = tmp_path_factory.mktemp("lab")
    persist.simulate_lab(root / "lab", size=64, darks=60, seed=2)
    model = root / "paper.json"
    model.write_text(persist.Model.default().to_json())
    return root / "lab", model
