#!/usr/bin/env bash
# Install what a fresh Debian 12 machine lacks to build persist: HDF5 headers and
# pkg-config. Does nothing when pkg-config already finds HDF5.
set -euo pipefail
if pkg-config --exists hdf5 2>/dev/null; then
  exit 0
fi
echo "bootstrap: HDF5 not found by pkg-config; installing libhdf5-dev pkg-config" >&2
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq libhdf5-dev pkg-config >/dev/null
pkg-config --modversion hdf5 >&2
