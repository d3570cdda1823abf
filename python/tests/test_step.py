"""`Model.step` from Python runs the stage's own step: on the same products it gives
exactly the stage's /persistence planes, flags and checkpoint state."""

import json
import os

import numpy as np
import pytest

import persist
from conftest import products


def step_over(model, paths, report):
    """Step `model` over the L1 products `paths` as the stage does; returns the
    per-exposure results and the final state."""
    first = persist.read_product(paths[0])
    state = persist.State(model, first["image"].shape)
    incomplete = {r["exposure_index"]: r["history_incomplete"] for r in report}
    results = []
    for p in paths:
        e = persist.read_product(p)
        r = model.step(
            state,
            e["image"],
            e["flags"],
            e["t_exposure_s"],
            t_start_unix_s=e["t_start_unix_s"],
            t_illuminated_s=e["t_illuminated_s"],
            exposure_index=e["exposure_index"],
            history_incomplete=incomplete[e["exposure_index"]],
            focal_plane_temp_k=e["focal_plane_temp_k"],
        )
        results.append((e, r))
    return results, state


def test_python_step_equals_stage_outputs(sky_run):
    sky, out, ckpt, summary = sky_run
    model = persist.Model.default()
    results, state = step_over(model, products(sky), summary["exposures"])
    assert len(results) == 12
    flagged = 0
    for e, r in results:
        o = persist.read_product(out / os.path.basename(str(e["path"])))
        p = o["persistence"]
        assert p["model_id"] == model.identity
        assert r.current_e_per_s.dtype == np.float32
        assert r.persistence_flags.dtype == np.uint8
        # identical values, bit for bit (not merely close)
        assert np.array_equal(r.current_e_per_s.view(np.uint32),
                              p["current_e_per_s"].view(np.uint32))
        assert np.array_equal(r.persistence_flags, p["flags"])
        assert np.array_equal(r.flags, o["flags"])
        if r.t_meas_s is None:
            assert np.isnan(p["t_meas_s"])
        else:
            assert r.t_meas_s == p["t_meas_s"]
        flagged += int((r.persistence_flags & persist.PFLAG_HIGH).sum())
        # PERSIST set exactly where HIGH
        assert np.array_equal((r.flags & persist.FLAG_PERSIST) != 0,
                              (r.persistence_flags & persist.PFLAG_HIGH) != 0)
    # the sequence does flag something: the equality above is not about empty planes
    assert flagged > 0
    # the state the stage checkpointed last is the one Python ends with
    ck = persist.load_checkpoint(sorted((ckpt).rglob("*.h5"))[-1])
    assert ck["exposure_index"] == state.last_index == 11
    assert np.array_equal(ck["amplitudes_e"], state.amplitudes_e)
    assert np.array_equal(ck["release_count"], state.release_count)
    assert np.array_equal(ck["pending"], state.pending)
    assert ck["t_reset_unix_s"] == state.t_reset_unix_s


def test_slew_times_give_the_same_prediction(sky_run):
    """With t_slew_s (relative times) instead of absolute starts: the same currents to
    float rounding of the times."""
    sky, out, _, _ = sky_run
    model = persist.Model.default()
    paths = products(sky)
    state = persist.State(model, (64, 64))
    t_reset = None
    for p in paths:
        e = persist.read_product(p)
        slew = 0.0 if t_reset is None else e["t_start_unix_s"] - t_reset
        r = model.step(state, e["image"], e["flags"], e["t_exposure_s"], slew,
                       t_illuminated_s=e["t_illuminated_s"])
        t_reset = e["t_start_unix_s"] + e["t_exposure_s"]
        o = persist.read_product(out / os.path.basename(p))["persistence"]
        np.testing.assert_allclose(r.current_e_per_s, o["current_e_per_s"],
                                   rtol=1e-5, atol=1e-7)
    assert state.last_index == len(paths) - 1


def test_step_inputs_are_checked():
    model = persist.Model.default()
    state = persist.State(model, (8, 8))
    img = np.ones((8, 8), np.float32)
    with pytest.raises(TypeError, match="image: must be a 2-D numpy array of float32"):
        model.step(state, img.astype(np.float64), None, 100.0, 0.0)
    with pytest.raises(TypeError, match="flags: .*uint32"):
        model.step(state, img, np.zeros((8, 8), np.int32), 100.0, 0.0)
    with pytest.raises(persist.PersistError, match="image"):
        model.step(state, np.ones((4, 8), np.float32), None, 100.0, 0.0)
    with pytest.raises(persist.PersistError, match="t_exposure_s"):
        model.step(state, img, None, -1.0, 0.0)
    with pytest.raises(ValueError, match="not both"):
        model.step(state, img, None, 100.0, 0.0, t_start_unix_s=5.0)
    # nothing changed by the refused steps
    assert state.last_index is None and state.t_reset_unix_s is None
    r = model.step(state, img, None, 100.0, 0.0)
    assert r.t_meas_s is None and state.last_index == 0
    with pytest.raises(persist.PersistError, match="exposure_index"):
        model.step(state, img, None, 100.0, 10.0, exposure_index=0)


def model_without_release(tmp_path):
    """The default model with early release off: on these uniform, noiseless images the
    evidence rule (released once the measured deficit reaches 3 sigma of the quiet
    pixels' spread, here zero) would release every pixel, and these tests are about
    the state and its planes."""
    m = json.loads(persist.Model.default().to_json())
    m["early_release"]["enabled"] = False
    (tmp_path / "no_release.json").write_text(json.dumps(m))
    return persist.Model.from_file(tmp_path / "no_release.json")


def test_nan_never_enters_the_state(tmp_path):
    """A NaN pixel adds the maximum amplitude (unknown fluence) and is flagged next
    time; the state stays finite (the crate's invariant, seen from Python)."""
    model = model_without_release(tmp_path)
    state = persist.State(model, (4, 4))
    img = np.full((4, 4), 1.0, np.float32)
    img[1, 2] = np.nan
    model.step(state, img, None, 112.0, 0.0)
    assert np.isfinite(state.amplitudes_e).all()
    r = model.step(state, np.ones((4, 4), np.float32), None, 112.0, 10.0)
    assert r.persistence_flags[1, 2] & persist.PFLAG_MAX_AMPLITUDE
    assert r.persistence_flags[1, 2] & persist.PFLAG_HIGH
    assert r.summary["max_amplitude"] == 1


def test_image_is_read_in_place_from_any_layout():
    """A non-contiguous (transposed) image gives the same result as its contiguous copy."""
    model = persist.Model.default()
    rng = np.random.default_rng(1)
    img = (rng.random((16, 16)) * 3e4).astype(np.float32)
    a, b = persist.State(model, (16, 16)), persist.State(model, (16, 16))
    ra = model.step(a, img.T, None, 112.0, 0.0)
    rb = model.step(b, np.ascontiguousarray(img.T), None, 112.0, 0.0)
    assert np.array_equal(a.amplitudes_e, b.amplitudes_e)
    ra = model.step(a, img, None, 112.0, 20.0)
    rb = model.step(b, img, None, 112.0, 20.0)
    assert np.array_equal(ra.current_e_per_s, rb.current_e_per_s)
    assert (ra.current_e_per_s > 0).any()


def test_results_stay_valid_and_planes_are_reused(tmp_path):
    """A result's arrays are views of planes the state keeps: they never change while
    the caller holds them, and once dropped the planes serve a later step (no
    allocation in a stepping loop)."""
    model = model_without_release(tmp_path)
    state = persist.State(model, (32, 32))
    img = np.full((32, 32), 5e4, np.float32)
    r1 = model.step(state, img, None, 112.0, 0.0)
    r2 = model.step(state, img, None, 112.0, 30.0)
    kept = r2.current_e_per_s.copy(), r2.persistence_flags.copy(), r2.flags.copy()
    assert (kept[0] > 0).all() and r2.current_e_per_s.base is not None
    address = r1.current_e_per_s.__array_interface__["data"][0]
    del r1
    r3 = model.step(state, np.zeros((32, 32), np.float32), None, 112.0, 30.0)
    # r2 unchanged by the step after it
    assert np.array_equal(r2.current_e_per_s, kept[0])
    assert np.array_equal(r2.persistence_flags, kept[1])
    assert np.array_equal(r2.flags, kept[2])
    assert not np.array_equal(r3.current_e_per_s, kept[0])
    # r1's planes, free again, were written by the third step
    assert r3.current_e_per_s.__array_interface__["data"][0] == address
    # an array kept on its own keeps its planes too
    c3 = r3.current_e_per_s
    saved = c3.copy()
    del r3
    r4 = model.step(state, img, None, 112.0, 30.0)
    assert np.array_equal(c3, saved)
    assert r4.current_e_per_s.__array_interface__["data"][0] != c3.__array_interface__["data"][0]
    with pytest.raises(ValueError, match="flags: shape"):
        model.step(state, img, np.zeros((4, 4), np.uint32), 112.0, 30.0)
