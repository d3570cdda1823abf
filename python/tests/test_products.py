"""Products and checkpoints read from Python: attributes and numpy arrays as the stage
wrote them; an L1 product written from Python reads back the same; bad files raise
PersistError naming the file."""

import os

import h5py
import numpy as np
import pytest

import persist
from conftest import products


def test_read_l1_and_output(sky_run):
    sky, out, _, summary = sky_run
    paths = products(sky)
    e = persist.read_product(paths[3])
    assert e["persistence"] is None
    assert e["detector"] == 1 and e["exposure_index"] == 3
    assert e["image"].dtype == np.float32 and e["image"].shape == (64, 64)
    assert e["flags"].dtype == np.uint32
    # the same values h5py reads (no plugin needed)
    with h5py.File(paths[3], "r") as f:
        assert np.array_equal(f["image"][...], e["image"], equal_nan=True)
        assert np.array_equal(f["flags"][...], e["flags"])
        assert f.attrs["t_start_utc"] == e["t_start_utc"]
    o = persist.read_product(out / os.path.basename(paths[3]))
    p = o["persistence"]
    assert p["current_e_per_s"].dtype == np.float32 and p["flags"].dtype == np.uint8
    assert p["previous_exposure_index"] == 2
    assert p["threshold_high_e_per_s"] == persist.Model.default().threshold_high_e_per_s
    with h5py.File(out / os.path.basename(paths[3]), "r") as f:
        assert np.array_equal(f["persistence/current"][...], p["current_e_per_s"])
    # the output's image is the input's
    assert np.array_equal(o["image"], e["image"], equal_nan=True)
    row = [r for r in summary["exposures"] if r["exposure_index"] == 3][0]
    assert row["summary"]["above_high"] == int((p["flags"] & persist.PFLAG_HIGH != 0).sum())


def test_write_product_round_trip(sky_run, tmp_path):
    sky, _, _, _ = sky_run
    e = persist.read_product(products(sky)[5])
    e2 = dict(e, image=e["image"] * np.float32(2.0), exposure_index=99)
    persist.write_product(tmp_path / "x.h5", e2)
    back = persist.read_product(tmp_path / "x.h5")
    assert back["exposure_index"] == 99 and back["t_start_utc"] == e["t_start_utc"]
    assert np.array_equal(back["image"], e2["image"], equal_nan=True)
    assert np.array_equal(back["flags"], e["flags"])
    # no temporary left beside it (atomic publication)
    assert sorted(os.listdir(tmp_path)) == ["x.h5"]


def test_bad_input_is_named(tmp_path):
    with pytest.raises(persist.PersistError, match="missing.h5"):
        persist.read_product(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(persist.PersistError, match="junk.h5"):
        persist.read_product(junk)
    good = {"detector": 1, "exposure_index": 0, "t_start_utc": "2026-01-01T00:00:00Z",
            "t_exposure_s": 112.0, "image": np.zeros((4, 4), np.float32)}
    with pytest.raises(ValueError, match="detector"):
        persist.write_product(tmp_path / "a.h5", dict(good, detector=9))
    with pytest.raises(KeyError, match="t_exposure_s"):
        persist.write_product(tmp_path / "a.h5", {k: v for k, v in good.items()
                                                  if k != "t_exposure_s"})
    with pytest.raises(persist.PersistError, match="t_exposure_s"):
        persist.write_product(tmp_path / "a.h5", dict(good, t_exposure_s=-3.0))
    assert not (tmp_path / "a.h5").exists()
    persist.write_product(tmp_path / "a.h5", good)
    assert persist.read_product(tmp_path / "a.h5")["flags"].sum() == 0


def test_load_checkpoint(sky_run):
    _, _, ckpt, _ = sky_run
    files = sorted(ckpt.rglob("*.h5"))
    assert files
    c = persist.load_checkpoint(files[-1])
    model = persist.Model.default()
    assert c["model_id"] == model.identity and c["detector"] == 1
    assert c["amplitudes_e"].shape == (64, 64, model.n_terms)
    assert c["amplitudes_e"].dtype == np.float64
    assert np.isfinite(c["amplitudes_e"]).all() and (c["amplitudes_e"] >= 0).all()
    assert c["amplitudes_e"].max() > 0
    assert isinstance(c["stage"], dict)
    s = persist.State.from_checkpoint(files[-1])
    assert s.last_index == c["exposure_index"]
    assert np.array_equal(s.amplitudes_e, c["amplitudes_e"])
    with pytest.raises(persist.PersistError, match="checkpoint|product"):
        persist.load_checkpoint(products(sky_run[0])[0])


def test_model_file(tmp_path):
    m = persist.Model.default()
    (tmp_path / "m.json").write_text(m.to_json())
    m2 = persist.Model.from_file(tmp_path / "m.json")
    assert m2.identity == m.identity and len(m.identity) == 64
    (tmp_path / "bad.json").write_text(m.to_json().replace('"terms"', '"termz"', 1))
    with pytest.raises(persist.PersistError, match="bad.json"):
        persist.Model.from_file(tmp_path / "bad.json")
