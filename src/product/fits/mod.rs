//! FITS in and out, in the layout of SPHEREx's Level-2 spectral images (docs/fits.md).
//!
//! A SPHEREx Level-2 product is one multi-extension FITS file per detector per
//! exposure: `IMAGE` (calibrated surface brightness, float32, with the spatial WCS and
//! the exposure's keywords in its header), `FLAGS` (int32 bit mask whose header names
//! every bit with `MP_<NAME>` keywords), `VARIANCE`, `ZODI`, `PSF` (a cube) and
//! `WCS-WAVE` (the wavelength lookup table). This module maps such a file onto the same
//! [`Exposure`](crate::product::Exposure) the HDF5 reader gives ([`mod@read`]), and writes
//! the stage's result back into a copy of the same file ([`mod@write`]).
//!
//! Invariants:
//! - The model path does not change: FITS -> `Exposure` (image converted to e-/s with a
//!   recorded [`Conversion`]) -> the same step -> FITS.
//! - Writing an output starts from a byte copy of the input file; only `FLAGS` data
//!   (bit 17 added) and, when missing, its `MP_PERSIST` card change (plus `CHECKSUM` /
//!   `DATASUM` of `FLAGS` when the input carried them); `PERSIST_CURRENT` and
//!   `PERSIST_FLAGS` are appended. Every other extension and card is unchanged, byte
//!   for byte.
//! - Writes are atomic as for HDF5 ([`crate::h5io::publish`]): `.NAME.part`, checked,
//!   synced, renamed, directory synced.
//! - Every error names the file and the field (`EXTNAME` or `EXTNAME/KEYWORD`); a file
//!   cfitsio cannot read is an [`ErrorKind::Invalid`] product (quarantined by the stage).
//!
//! All FITS access goes through the `fitsio` crate (cfitsio); nothing here parses FITS.

pub mod read;
pub mod write;

use crate::error::{Error, ErrorKind, Result};
use crate::units::DetectorId;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

pub use read::{index_of_start, read_exposure, read_meta, read_meta_sequence};
pub use write::write_output;

/// cfitsio's status for a keyword that is not in the header.
pub(crate) const KEY_NO_EXIST: i32 = 202;

/// Names of the extensions this stage appends.
pub const EXT_PERSIST_CURRENT: &str = "PERSIST_CURRENT";
pub const EXT_PERSIST_FLAGS: &str = "PERSIST_FLAGS";

/// The `FLAGS` bits SPHEREx names in its headers (`MP_<NAME>` = bit number), from the
/// archive's flag table (SPHEREx Explanatory Supplement, Table 8).
pub const SPHEREX_FLAG_BITS: &[(&str, u32)] = &[
    ("MP_TRANSIENT", 0),
    ("MP_OVERFLOW", 1),
    ("MP_SUR_ERROR", 2),
    ("MP_NONFUNC", 6),
    ("MP_DICHROIC", 7),
    ("MP_MISSING_DATA", 9),
    ("MP_HOT", 10),
    ("MP_COLD", 11),
    ("MP_FULLSAMPLE", 12),
    ("MP_PHANMISS", 14),
    ("MP_NONLINEAR", 15),
    ("MP_PERSIST", 17),
    ("MP_OUTLIER", 19),
    ("MP_SOURCE", 21),
];

/// The header cards of `PERSIST_FLAGS` naming its bits (as `MP_*` does for `FLAGS`).
pub const PERSIST_FLAG_BITS: &[(&str, u32, &str)] = &[
    ("PF_HIGH", 0, "current above the high threshold: PERSIST"),
    ("PF_LOW", 1, "current above the low threshold"),
    (
        "PF_MAXAMP",
        2,
        "previous fluence unknown: maximum amplitude used",
    ),
    ("PF_RELEAS", 3, "released early in this exposure"),
    (
        "PF_HISTIN",
        4,
        "an earlier exposure is missing or was rejected",
    ),
];

/// The header keywords read from a FITS exposure, and its extension names. The defaults
/// are SPHEREx's; a JSON file (`persist run --fits-keywords FILE`) replaces any of them
/// for another mission's products.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Keywords {
    /// The image extension (surface brightness, or e-/s).
    pub image_ext: String,
    /// The int32 bit-mask extension.
    pub flags_ext: String,
    /// Detector number 1..=6 (integer).
    pub detector: String,
    /// Optional: exposure sequence number per detector (non-negative integer), the
    /// order the stage processes a detector's exposures in. Absent (SPHEREx's files
    /// carry none), or named `""` here: the start time orders them ([`Sequence`]).
    pub exposure_index: String,
    /// Start of the exposure, ISO 8601 (`YYYY-MM-DDThh:mm:ss[.s]`), in `time_system`.
    pub date_obs: String,
    /// Start of the exposure, MJD, in `time_system`; used when `date_obs` is absent.
    pub mjd_obs: String,
    /// Optional: the time scale of `date_obs` / `mjd_obs` (FITS `TIMESYS`: UTC when
    /// absent; TAI, TT, TDB and GPS are converted to UTC).
    pub time_system: String,
    /// Exposure time, seconds.
    pub exposure_time: String,
    /// Optional: seconds of the exposure that were illuminated.
    pub illuminated_time: String,
    /// Optional: focal plane temperature, K.
    pub focal_plane_temp: String,
    /// The unit of the image extension.
    pub image_unit: String,
    /// Optional: e-/s per image unit (the conversion factor), when no `--fits-gain`
    /// is given for the detector.
    pub conversion: String,
}

impl Default for Keywords {
    fn default() -> Self {
        Keywords {
            image_ext: "IMAGE".into(),
            flags_ext: "FLAGS".into(),
            detector: "DETECTOR".into(),
            exposure_index: "EXPINDEX".into(),
            date_obs: "DATE-OBS".into(),
            mjd_obs: "MJD-OBS".into(),
            time_system: "TIMESYS".into(),
            exposure_time: "EXPTIME".into(),
            illuminated_time: "EXPILLUM".into(),
            focal_plane_temp: "FPATEMP".into(),
            image_unit: "BUNIT".into(),
            conversion: "ESCONV".into(),
        }
    }
}

impl Keywords {
    /// Read a keyword mapping file (JSON; keys absent keep their default).
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        serde_json::from_str(&text).map_err(|e| {
            Error::new(ErrorKind::Usage, format!("not a FITS keyword mapping: {e}")).path(path)
        })
    }
}

/// How FITS inputs are read: keyword names and conversion factors.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FitsConfig {
    pub keywords: Keywords,
    /// e-/s per image unit, per detector (`--fits-gain D:FACTOR`); wins over the header.
    pub gains: BTreeMap<u8, f64>,
}

/// The conversion of a FITS image to e-/s that was used (recorded in the output).
#[derive(Debug, Clone, PartialEq)]
pub struct Conversion {
    /// e-/s per unit of the input image: `image_e_per_s = image * factor`.
    pub factor: f64,
    /// The input image's unit, as its header says (empty when absent).
    pub image_unit: String,
    /// Where the factor came from: `argument`, `header KEYWORD`, or `unit`.
    pub source: String,
}

/// What reading a FITS exposure found that its output records.
#[derive(Debug, Clone, PartialEq)]
pub struct FitsInput {
    /// The image's conversion to e-/s.
    pub conversion: Conversion,
    /// Pixels whose input `FLAGS` had bit 17 (`PERSIST`) set: an archive pipeline's own
    /// persistence flag (SPHEREx's Level-2 files carry one). It is cleared before the
    /// step and replaced by this stage's; the count is recorded as `PERSIN`.
    pub input_persist_px: u64,
    /// Where the exposure index came from (recorded as `IDXSRC`).
    pub sequence: Sequence,
}

/// Where a FITS exposure's index (its place in its detector's history) comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Sequence {
    /// A sequence-number keyword (the mapping's `exposure_index`, named here).
    Keyword(String),
    /// The start time, read from the keyword named here: the index is milliseconds
    /// since 1970-01-01T00:00:00 UTC ([`index_of_start`]), so that a detector's
    /// exposures are processed in start-time order. Consecutive exposures then have
    /// non-consecutive indices: the stage cannot tell a missing exposure from a gap in
    /// time, so it processes each one when it comes ([`mod@crate::stage::run`] docs).
    StartTime(String),
}

impl Sequence {
    /// Whether the index is a start time (not a sequence number).
    pub fn is_start_time(&self) -> bool {
        matches!(self, Sequence::StartTime(_))
    }

    /// How the index was found, for the `IDXSRC` card.
    pub fn describe(&self) -> String {
        match self {
            Sequence::Keyword(k) => format!("header {k}"),
            Sequence::StartTime(k) => format!("{k}: ms since 1970 UTC"),
        }
    }
}

/// The `MP_<NAME>` cards of `FLAGS` for the bits the stage reads or writes, with the bit
/// it gives each ([`crate::flags::bits`]). A header naming one of them at another bit
/// is refused: its flags do not mean what the model assumes.
pub const MODEL_FLAG_BITS: &[(&str, u32)] = &[
    (
        "MP_TRANSIENT",
        crate::flags::bits::TRANSIENT.trailing_zeros(),
    ),
    ("MP_OVERFLOW", crate::flags::bits::OVERFLOW.trailing_zeros()),
    (
        "MP_SUR_ERROR",
        crate::flags::bits::SUR_ERROR.trailing_zeros(),
    ),
    ("MP_NONFUNC", crate::flags::bits::NONFUNC.trailing_zeros()),
    ("MP_PERSIST", crate::flags::bits::PERSIST.trailing_zeros()),
];

/// Whether a path names a FITS file (`.fits`, `.fit`, `.fts`, any case).
pub fn is_fits(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
        ["fits", "fit", "fts"]
            .iter()
            .any(|x| e.eq_ignore_ascii_case(x))
    })
}

/// Parse `D:FACTOR` (a `--fits-gain` argument).
pub fn parse_gain(s: &str) -> std::result::Result<(u8, f64), String> {
    let (d, f) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected DETECTOR:FACTOR, e.g. 1:0.25"))?;
    let det = d
        .parse::<i64>()
        .ok()
        .and_then(DetectorId::new)
        .ok_or_else(|| format!("`{d}`: not a detector number 1..=6"))?;
    let factor: f64 = f
        .parse()
        .map_err(|_| format!("`{f}`: not a number (e-/s per image unit)"))?;
    if !(factor.is_finite() && factor > 0.0) {
        return Err(format!("`{f}`: the factor must be finite and > 0"));
    }
    Ok((det.0, factor))
}

/// A cfitsio error as one of ours: the file cannot be read as a product (`Invalid`),
/// unless it is gone (`Io`). `field` names the extension or `EXTNAME/KEYWORD`.
pub(crate) fn fits_error(path: &Path, field: &str, e: fitsio::errors::Error) -> Error {
    let kind = if path.exists() {
        ErrorKind::Invalid
    } else {
        ErrorKind::Io
    };
    let message = match e {
        fitsio::errors::Error::Fits(f) => format!("cfitsio error {}: {}", f.status, f.message),
        other => other.to_string(),
    };
    Error::new(kind, message).field(field).path(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gain_arguments_parse_and_refuse() {
        assert_eq!(parse_gain("3:0.5"), Ok((3, 0.5)));
        assert!(parse_gain("7:0.5").is_err());
        assert!(parse_gain("1:-2").is_err());
        assert!(parse_gain("1").is_err());
    }

    #[test]
    fn a_mapping_file_overrides_only_what_it_names() {
        let k: Keywords = serde_json::from_str(r#"{"exposure_time": "XPOSURE"}"#).unwrap();
        assert_eq!(k.exposure_time, "XPOSURE");
        assert_eq!(k.detector, "DETECTOR");
        assert!(serde_json::from_str::<Keywords>(r#"{"exptime": "X"}"#).is_err());
    }

    #[test]
    fn the_model_bits_are_spherex_bits() {
        for (name, bit) in MODEL_FLAG_BITS {
            assert!(SPHEREX_FLAG_BITS.contains(&(name, *bit)), "{name} = {bit}");
        }
    }

    #[test]
    fn fits_names() {
        assert!(is_fits(Path::new("a/b.fits")));
        assert!(is_fits(Path::new("a/b.FITS")));
        assert!(!is_fits(Path::new("a/b.h5")));
    }
}
