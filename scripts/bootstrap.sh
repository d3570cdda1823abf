#!/usr/bin/env bash
# Install what a fresh Debian 12 machine lacks to build persist: HDF5 and cfitsio headers and
# pkg-config, strace and jq. Does nothing when they are already there.
# With --chromium, also Debian's chromium (for tests/report_chromium.rs) when it is not
# on PATH.
set -euo pipefail
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
updated=0
if ! pkg-config --exists hdf5 2>/dev/null; then
  echo "bootstrap: HDF5 not found by pkg-config; installing libhdf5-dev pkg-config" >&2
  $SUDO apt-get update -qq
  updated=1
  $SUDO apt-get install -y -qq libhdf5-dev pkg-config >/dev/null
  pkg-config --modversion hdf5 >&2
fi
if [ "${1:-}" = "--chromium" ] && ! command -v chromium >/dev/null 2>&1; then
  echo "bootstrap: chromium not found; installing Debian's chromium" >&2
  if [ "$updated" -eq 0 ]; then $SUDO apt-get update -qq; fi
  $SUDO apt-get install -y -qq chromium >/dev/null
  chromium --version >&2 || true
fi
# FITS (the fitsio crate links Debian's cfitsio).
if ! pkg-config --exists cfitsio 2>/dev/null; then
  echo "bootstrap: cfitsio not found by pkg-config; installing libcfitsio-dev" >&2
  if [ "$updated" -eq 0 ]; then $SUDO apt-get update -qq; updated=1; fi
  $SUDO apt-get install -y -qq libcfitsio-dev pkg-config >/dev/null
  pkg-config --modversion cfitsio >&2
fi
# strace: the fault-injection matrix (tests/ops_write_faults.rs) runs the stage under it.
if ! command -v strace >/dev/null 2>&1; then
  echo "bootstrap: strace not found; installing Debian's strace" >&2
  if [ "$updated" -eq 0 ]; then $SUDO apt-get update -qq; updated=1; fi
  $SUDO apt-get install -y -qq strace >/dev/null
fi
# jq: the validation pages read the commands' JSON reports (scripts/offers_table.sh).
if ! command -v jq >/dev/null 2>&1; then
  echo "bootstrap: jq not found; installing Debian's jq" >&2
  if [ "$updated" -eq 0 ]; then $SUDO apt-get update -qq; updated=1; fi
  $SUDO apt-get install -y -qq jq >/dev/null
fi
# With --python (anywhere in the arguments), also what the Python package and its tests
# need (scripts/python_test.sh) and the FITS round trip (tests/fits_roundtrip.rs): pip,
# then maturin, numpy, h5py, pytest, matplotlib and astropy from PyPI when they are missing.
for arg in "$@"; do
  if [ "$arg" = "--python" ]; then
    if ! python3 -m pip --version >/dev/null 2>&1; then
      echo "bootstrap: pip not found; installing Debian's python3-pip python3-venv" >&2
      if [ "$updated" -eq 0 ]; then $SUDO apt-get update -qq; updated=1; fi
      $SUDO apt-get install -y -qq python3-pip python3-venv >/dev/null
    fi
    if ! python3 -c "import maturin, numpy, h5py, pytest, matplotlib, astropy" >/dev/null 2>&1; then
      echo "bootstrap: installing maturin numpy h5py pytest matplotlib astropy (pip)" >&2
      # Debian's own python3 refuses pip installs outside a venv (PEP 668) unless told.
      python3 -m pip install --quiet maturin numpy h5py pytest matplotlib astropy 2>/dev/null \
        || python3 -m pip install --quiet --break-system-packages \
          maturin numpy h5py pytest matplotlib astropy
    fi
  fi
done
# With --slurm (anywhere in the arguments), also Debian's slurm-wlm and munge for the
# one-node cluster of tests/slurm_cluster.rs (scripts/slurm_cluster.sh install).
for arg in "$@"; do
  if [ "$arg" = "--slurm" ]; then
    bash "$(dirname "$0")/slurm_cluster.sh" install
  fi
done
