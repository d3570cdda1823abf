"""Read back the FITS round trip with astropy and h5py (run by tests/fits_roundtrip.rs).

Usage: check_roundtrip.py FITS_IN FITS_OUT H5_OUT EXPORTED H5_DIR...

Checks, per exposure, between the FITS input, the stage's FITS output and the HDF5 run's
output on the same data:
- bit 17 of FLAGS equals the high-threshold plane (bit 0 of /persistence/flags), and
  every other FLAGS bit is the input's;
- PERSIST_CURRENT equals /persistence/current to float32 precision;
- the conversion (ESCONV, ESCONVSR, IMGUNIT) and the exposure index (EXPINDEX, IDXSRC:
  the start time, as SPHEREx's files carry no sequence number) are recorded;
- every extension other than FLAGS is byte-identical (header and data bytes) to the
  input's, and the FLAGS header keeps every input card (MP_PERSIST added if missing;
  CHECKSUM and DATASUM, when the input had them, updated and verified);
- astropy opens every FITS file (inputs, outputs, exports) with warnings as errors and
  verify('exception') (and writes it back to memory with output_verify='exception');
  h5py opens every HDF5 file under H5_DIR... and reads every dataset, with
  HDF5_PLUGIN_PATH an empty directory and only HDF5's built-in filters.
Prints one JSON line of counts; exits non-zero on the first failure.
"""
import glob
import io
import json
import os
import sys
import tempfile
import warnings

# No HDF5 filter plugin can be found: every file must open with HDF5's own filters.
os.environ["HDF5_PLUGIN_PATH"] = tempfile.mkdtemp()
import h5py  # noqa: E402
import numpy as np  # noqa: E402
from astropy.io import fits  # noqa: E402

warnings.simplefilter("error")
fits_in, fits_out, h5_out, exported = sys.argv[1:5]
h5_dirs = sys.argv[5:]
NEW = {"PERSIST_CURRENT", "PERSIST_FLAGS"}


def strict_open(path):
    hdul = fits.open(path, mode="readonly", memmap=False, checksum=True)
    hdul.verify("exception")
    for hdu in hdul:
        _ = hdu.data  # decode every extension (a bad one raises here)
    hdul.writeto(io.BytesIO(), output_verify="exception")  # as astropy would write it
    return hdul


def raw_parts(path, hdul):
    """(header bytes, data bytes) of every HDU, straight from the file."""
    with open(path, "rb") as f:
        blob = f.read()
    parts = []
    for i in range(len(hdul)):
        info = hdul.fileinfo(i)
        h0, d0, span = info["hdrLoc"], info["datLoc"], info["datSpan"]
        parts.append((blob[h0:d0], blob[d0:d0 + span]))
    return parts


outputs = sorted(glob.glob(os.path.join(fits_out, "*.fits")))
assert outputs, f"no FITS output in {fits_out}"
n_high = 0
n_ext_same = 0
n_mp_added = 0
n_checksum = 0
max_rel = 0.0
for out_path in outputs:
    name = os.path.basename(out_path)
    in_path = os.path.join(fits_in, name)
    h5_path = os.path.join(h5_out, name[: -len(".fits")] + ".h5")
    hin, hout = strict_open(in_path), strict_open(out_path)
    names_in = [h.name for h in hin]
    names_out = [h.name for h in hout]
    assert names_out == names_in + ["PERSIST_CURRENT", "PERSIST_FLAGS"], (name, names_out)
    with h5py.File(h5_path, "r") as h5:
        current_h5 = h5["/persistence/current"][...]
        pflags_h5 = h5["/persistence/flags"][...]
    high = (pflags_h5 & 1) != 0
    flags_out = hout["FLAGS"].data.astype(np.int64)
    flags_in = hin["FLAGS"].data.astype(np.int64)
    persist = (flags_out >> 17) & 1
    assert np.array_equal(persist.astype(bool), high), f"{name}: bit 17 != high plane"
    assert np.array_equal(flags_out & ~(1 << 17), flags_in), f"{name}: other FLAGS bits changed"
    assert np.array_equal(hout["PERSIST_FLAGS"].data, pflags_h5), f"{name}: PERSIST_FLAGS"
    cur = hout["PERSIST_CURRENT"].data.astype(np.float64)
    ref = current_h5.astype(np.float64)
    eps = np.finfo(np.float32).eps
    tol = 4 * eps * np.maximum(np.abs(ref), 1e-30)
    bad = np.abs(cur - ref) > tol
    assert not bad.any(), f"{name}: PERSIST_CURRENT differs at {int(bad.sum())} pixels"
    rel = np.abs(cur - ref) / np.maximum(np.abs(ref), 1e-30)
    max_rel = max(max_rel, float(rel.max()))
    n_high += int(high.sum())
    assert hout["PERSIST_CURRENT"].header["BUNIT"] == "e-/s"
    # The conversion used and the exposure order are recorded: the input's ESCONV (no
    # argument in this run), the start time in ms since 1970 UTC as the index.
    hcur = hout["PERSIST_CURRENT"].header
    assert hcur["ESCONV"] == hin["IMAGE"].header["ESCONV"], (name, hcur["ESCONV"])
    assert hcur["ESCONVSR"] == "header ESCONV", (name, hcur["ESCONVSR"])
    assert hcur["IMGUNIT"] == hin["IMAGE"].header["BUNIT"]
    assert "EXPINDEX" not in hin["IMAGE"].header, f"{name}: SPHEREx files have no EXPINDEX"
    assert hcur["IDXSRC"] == "DATE-OBS: ms since 1970 UTC", (name, hcur["IDXSRC"])
    assert hcur["EXPINDEX"] == hout["PERSIST_FLAGS"].header["EXPINDEX"]
    assert hout["FLAGS"].header["MP_PERSIST"] == 17
    n_mp_added += "MP_PERSIST" not in hin["FLAGS"].header
    if "CHECKSUM" in hin["FLAGS"].header:
        assert hout["FLAGS"].verify_checksum() == 1, f"{name}: FLAGS CHECKSUM"
        assert hout["FLAGS"].verify_datasum() == 1, f"{name}: FLAGS DATASUM"
        n_checksum += 1
    raw_in, raw_out = raw_parts(in_path, hin), raw_parts(out_path, hout)
    for i, ext in enumerate(names_in):
        if ext == "FLAGS":
            sums = ("CHECKSUM", "DATASUM")
            cards_in = [c.image for c in hin[i].header.cards if c.keyword not in sums]
            cards_out = [c.image for c in hout[i].header.cards]
            missing = [c for c in cards_in if c not in cards_out]
            assert not missing, f"{name}: FLAGS header lost {missing}"
            continue
        assert raw_in[i][0] == raw_out[i][0], f"{name}: {ext} header bytes differ"
        assert raw_in[i][1] == raw_out[i][1], f"{name}: {ext} data bytes differ"
        n_ext_same += 1
    hin.close()
    hout.close()

n_fits = 0
for d in (fits_in, fits_out, exported):
    for p in sorted(glob.glob(os.path.join(d, "*.fits"))):
        strict_open(p).close()
        n_fits += 1
# HDF5's built-in filters (H5Z): anything else would need a plugin.
BUILTIN_FILTERS = {"gzip", "shuffle", "fletcher32", "scaleoffset", "szip"}


def read_dataset(name, obj):
    if isinstance(obj, h5py.Dataset):
        extra = set(obj._filters) - BUILTIN_FILTERS
        assert not extra, f"{name}: filters {extra} need a plugin"
        obj[...]


n_h5 = 0
for d in h5_dirs:
    for p in sorted(glob.glob(os.path.join(d, "**", "*.h5"), recursive=True)):
        with h5py.File(p, "r") as f:
            f.visititems(read_dataset)
        n_h5 += 1
print(json.dumps({
    "outputs": len(outputs),
    "high_pixels": n_high,
    "untouched_extensions_identical": n_ext_same,
    "max_rel_current_diff": max_rel,
    "mp_persist_added": n_mp_added,
    "flags_checksum_verified": n_checksum,
    "fits_opened_strict": n_fits,
    "h5_opened": n_h5,
}))
