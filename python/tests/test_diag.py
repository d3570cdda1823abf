"""`compare` and `diagnose` from Python on a small laboratory sequence: their JSON as
Python objects, the same as the files they write."""

import json
import math

import persist


def test_diagnose(lab, tmp_path):
    seq, model = lab
    d = persist.diagnose(seq, model, pixels=256, bootstrap=19, seed=1, statistic="pooled",
                         json=tmp_path / "d.json")
    with open(tmp_path / "d.json") as f:
        assert json.load(f) == d
    assert d["pixels_sampled"] == 256 and d["bootstrap_replicas"] == 19
    assert d["ranking"], d
    for c in d["ranking"]:
        assert math.isfinite(c["score"]) and c["effect"]
    ranks = sorted(c["score_rank"] for c in d["ranking"])
    assert ranks == list(range(1, len(ranks) + 1))
    assert isinstance(d["verdict"], str) and d["verdict"]
    # the same seed gives the same answer
    assert persist.diagnose(seq, model, pixels=256, bootstrap=19, seed=1,
                            statistic="pooled") == d


def test_compare(lab, tmp_path):
    seq, model = lab
    s = persist.compare(seq, [model], tmp_path / "cmp")
    assert (tmp_path / "cmp" / "report.html").exists()
    (m,) = s["models"]
    z2 = [c["z"] ** 2 for c in m["map"]]
    rms = math.sqrt(sum(z2) / len(z2))
    assert abs(m["residual_rms_normalised"] - rms) < 1e-9 * max(rms, 1.0)
    assert s["exposures_compared"] > 0
