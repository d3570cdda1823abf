"""One exposure path: the Python `persist.run`, the command line's `persist run` and
`persist slurm`'s tile jobs give the same output and checkpoint bytes on the committed
fixtures and on a 2-detector simulated sky (tests/one_path.rs compares the last two
alone). Needs the `persist` executable of this checkout (`cargo build`, or `cargo test`,
which `make test` runs first), or its path in PERSIST_BIN."""

import os
import pathlib
import shutil
import subprocess

import pytest

import persist

ROOT = pathlib.Path(__file__).resolve().parents[2]
EPOCH = "1767225600"


def executable():
    """PERSIST_BIN, or the newer of this checkout's release and debug builds."""
    if "PERSIST_BIN" in os.environ:
        exe = pathlib.Path(os.environ["PERSIST_BIN"])
    else:
        built = [ROOT / "target" / p / "persist" for p in ("release", "debug")]
        found = [b for b in built if b.is_file()]
        exe = max(found, key=lambda b: b.stat().st_mtime) if found else built[0]
    assert exe.is_file(), f"{exe}: build it with `cargo build` or set PERSIST_BIN"
    return exe


def cli(*args):
    env = dict(os.environ, SOURCE_DATE_EPOCH=EPOCH)
    r = subprocess.run([str(executable()), *map(str, args)], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return r


def tree(directory):
    """Every file under a directory but the lock: relative path -> bytes."""
    d = pathlib.Path(directory)
    return {
        p.relative_to(d): p.read_bytes()
        for p in sorted(d.rglob("*"))
        if p.is_file() and p.name != ".persist.lock"
    }


def newest_checkpoints(ckpt):
    """The newest checkpoint of each detector: name -> bytes."""
    by_det = {}
    for p in sorted(pathlib.Path(ckpt).rglob("*.h5")):
        by_det.setdefault(p.parent.name, []).append(p)
    return {d: max(ps).read_bytes() for d, ps in by_det.items()}


def three_paths(input_dir, root, model=None):
    """(python, stage, tiles) directories of the three runs of `input_dir`."""
    py, stage, tiles = root / "python", root / "stage", root / "tiles"
    os.environ["SOURCE_DATE_EPOCH"] = EPOCH
    try:
        summary = persist.run(input_dir, py / "out", py / "ckpt", model)
    finally:
        del os.environ["SOURCE_DATE_EPOCH"]
    assert summary["errors"] == [], summary["errors"]
    m = ["--model", model] if model else []
    cli("run", "--input", input_dir, "--output", stage / "out", "--checkpoints", stage / "ckpt",
        "--quiet", *m)
    cli("slurm", "--input", input_dir, "--output", tiles / "out", "--checkpoints",
        tiles / "ckpt", "--work", tiles / "work", "--tiles", "2x2", *m)
    env = dict(os.environ, SOURCE_DATE_EPOCH=EPOCH)
    r = subprocess.run(["bash", str(tiles / "work" / "run_local.sh")], env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return py, stage, tiles


def assert_same(dirs, n_outputs):
    outs = [tree(d / "out") for d in dirs]
    assert len(outs[0]) == n_outputs
    ckpts = [newest_checkpoints(d / "ckpt") for d in dirs]
    assert len(ckpts[0]) == 2
    for o, c in zip(outs[1:], ckpts[1:]):
        assert o == outs[0]
        assert c == ckpts[0]


def test_fixtures_give_the_same_bytes_by_all_three_paths(tmp_path):
    inp = tmp_path / "in"
    inp.mkdir()
    for p in (ROOT / "fixtures").glob("*.h5"):
        shutil.copy(p, inp / p.name)
    assert_same(three_paths(inp, tmp_path), 24)


def test_a_two_detector_sky_gives_the_same_bytes_by_all_three_paths(tmp_path):
    sky = tmp_path / "sky"
    assert persist.simulate_sky(sky, size=64, detectors=2, exposures=6, seed=5) == 12
    assert_same(three_paths(sky, tmp_path), 12)
