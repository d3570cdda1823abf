#!/usr/bin/env bash
# Build the Python package (python/: PyO3 + maturin, module `persist`) from this
# checkout, install it into the current Python, check that it imports, and run its
# pytest suite (python/tests; it also runs docs/python_example.py).
# scripts/bootstrap.sh --python installs maturin, numpy, h5py, pytest and matplotlib.
# The build is a release build (a crate of its own, with its own lock) in the main
# crate's target directory, so that the dependencies `cargo test --release` built with
# the same features are reused; the wheel goes to python/target/wheels.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
start=$(date +%s)
# A wheel (what a release would publish), then installed from that file.
rm -f python/target/wheels/persist-*.whl
python3 -m pip wheel --quiet --no-build-isolation --no-deps -w python/target/wheels ./python
wheel=$(ls python/target/wheels/persist-*.whl)
echo "python: built $wheel" >&2
python3 -m pip install --quiet --force-reinstall --no-deps "$wheel"
built=$(date +%s)
echo "python: build+install $((built - start)) s" >&2
python3 -c "import persist; print('python package persist', persist.__version__, 'imported')"
# pytest's summary line stays the last line of `make test`.
python3 -m pytest -q python/tests
