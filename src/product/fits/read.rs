//! FITS (SPHEREx Level-2 layout) -> [`Exposure`], with the image converted to e-/s.
//!
//! Keywords are looked up in the image extension's header first, then in the primary
//! header ([`Keywords`] names them). Order, so that nothing big is read from a file
//! that is not a usable exposure: open, headers (detector, exposure index, start time,
//! exposure time, conversion factor), then the `IMAGE` and `FLAGS` planes, then the same
//! value checks as for HDF5 (`check_exposure_data` in [`crate::product::read`]: no +/-Inf,
//! some finite pixel).
//!
//! Refused, besides what the HDF5 reader refuses: a file that does not end where its last
//! HDU does (truncated), a file that already has `PERSIST_CURRENT` or `PERSIST_FLAGS` (an
//! output of this stage), and a `FLAGS` header naming a bit the model reads or writes
//! (`MP_OVERFLOW`, `MP_PERSIST`, ...) at another bit number than SPHEREx's. Unlike an
//! HDF5 input, `FLAGS` may carry bit 17: archive products hold their pipeline's own
//! persistence flag, which is cleared here (and counted, [`FitsInput`]) so that the
//! output's bit 17 is this stage's.

use super::{
    fits_error, Conversion, FitsConfig, FitsInput, Keywords, Sequence, KEY_NO_EXIST,
    MODEL_FLAG_BITS,
};
use super::{EXT_PERSIST_CURRENT, EXT_PERSIST_FLAGS};
use crate::error::{Error, ErrorKind, Result};
use crate::product::read::check_exposure_data;
use crate::product::schema::combine;
use crate::product::{Exposure, ExposureMeta};
use crate::units::{DetectorId, UtcSeconds};
use fitsio::hdu::{FitsHdu, HduInfo};
use fitsio::images::ImageType;
use fitsio::FitsFile;
use ndarray::Array2;
use std::path::Path;

/// Seconds from the MJD epoch to the Unix epoch: MJD 40587 is 1970-01-01.
const MJD_UNIX_EPOCH: f64 = 40587.0;

/// Units that are e-/s already (conversion factor 1).
const E_PER_S_UNITS: &[&str] = &["e-/s", "e/s", "electron/s", "electrons/s", "e-/sec"];

/// An open FITS exposure and the headers keywords are looked up in.
pub(crate) struct Headers<'a> {
    pub(crate) path: &'a Path,
    pub(crate) file: FitsFile,
    pub(crate) image: FitsHdu,
    primary: FitsHdu,
    pub(crate) keywords: &'a Keywords,
}

impl<'a> Headers<'a> {
    pub(crate) fn open(path: &'a Path, keywords: &'a Keywords) -> Result<Self> {
        let mut file = FitsFile::open(path).map_err(|e| fits_error(path, "file", e))?;
        check_complete(path, &mut file)?;
        for ext in [EXT_PERSIST_CURRENT, EXT_PERSIST_FLAGS] {
            if file.hdu(ext).is_ok() {
                return Err(Error::invalid(
                    ext,
                    "present: this is an output of persist, not an exposure to flag",
                )
                .path(path));
            }
        }
        let primary = file
            .primary_hdu()
            .map_err(|e| fits_error(path, "PRIMARY", e))?;
        let image = file
            .hdu(keywords.image_ext.as_str())
            .map_err(|e| fits_error(path, &keywords.image_ext, e))?;
        Ok(Headers {
            path,
            file,
            image,
            primary,
            keywords,
        })
    }

    fn field(&self, key: &str) -> String {
        format!("{}/{key}", self.keywords.image_ext)
    }

    /// A keyword from the image header, else the primary header; `None` when absent.
    fn key<T: fitsio::headers::ReadsKey>(&mut self, key: &str) -> Result<Option<T>> {
        for hdu in [&self.image, &self.primary] {
            match hdu.read_key::<T>(&mut self.file, key) {
                Ok(v) => return Ok(Some(v)),
                Err(fitsio::errors::Error::Fits(f)) if f.status == KEY_NO_EXIST => continue,
                Err(e) => {
                    return Err(Error::invalid(
                        self.field(key),
                        format!("cannot be read as the type expected: {e}"),
                    )
                    .path(self.path))
                }
            }
        }
        Ok(None)
    }

    fn required<T: fitsio::headers::ReadsKey>(&mut self, key: &str, what: &str) -> Result<T> {
        self.key(key)?.ok_or_else(|| {
            Error::invalid(self.field(key), format!("missing: the {what} is needed"))
                .path(self.path)
        })
    }

    /// The root attributes of the exposure (as the HDF5 reader gives them), and where its
    /// exposure index came from.
    pub(crate) fn meta(&mut self) -> Result<(ExposureMeta, Sequence)> {
        let k = self.keywords;
        let d: i64 = self.required(&k.detector, "detector number (1..=6)")?;
        let detector = DetectorId::new(d).ok_or_else(|| {
            Error::invalid(
                self.field(&k.detector),
                format!("{d} is not a detector 1..=6"),
            )
            .path(self.path)
        })?;
        let (t_start, time_key) = self.start_time()?;
        // The sequence number when the header has one (another mission's, or added by
        // hand); otherwise the start time itself orders the exposures (SPHEREx).
        let from_keyword: Option<i64> = if k.exposure_index.is_empty() {
            None
        } else {
            self.key(&k.exposure_index)?
        };
        let (exposure_index, sequence) = match from_keyword {
            Some(index) => (
                u64::try_from(index).map_err(|_| {
                    Error::invalid(
                        self.field(&k.exposure_index),
                        format!("{index} is negative"),
                    )
                    .path(self.path)
                })?,
                Sequence::Keyword(k.exposure_index.clone()),
            ),
            None => (
                index_of_start(t_start).ok_or_else(|| {
                    Error::invalid(
                        self.field(&time_key),
                        format!(
                            "start {} is before 1970-01-01: no exposure index can be derived",
                            t_start.to_iso()
                        ),
                    )
                    .path(self.path)
                })?,
                Sequence::StartTime(time_key),
            ),
        };
        let t_exposure_s: f64 = self.required(&k.exposure_time, "exposure time (s)")?;
        if !(t_exposure_s.is_finite() && t_exposure_s > 0.0) {
            return Err(Error::invalid(
                self.field(&k.exposure_time),
                format!("must be finite and > 0 s, got {t_exposure_s}"),
            )
            .path(self.path));
        }
        let t_illuminated_s: Option<f64> = self.key(&k.illuminated_time)?;
        if let Some(t) = t_illuminated_s {
            if !(t.is_finite() && t > 0.0 && t <= t_exposure_s) {
                return Err(Error::invalid(
                    self.field(&k.illuminated_time),
                    format!("must be in (0, {t_exposure_s}] s, got {t}"),
                )
                .path(self.path));
            }
        }
        let focal_plane_temp_k: Option<f64> = self.key(&k.focal_plane_temp)?;
        if let Some(t) = focal_plane_temp_k.filter(|t| !(t.is_finite() && *t > 0.0)) {
            return Err(Error::invalid(
                self.field(&k.focal_plane_temp),
                format!("must be finite and > 0 K, got {t}"),
            )
            .path(self.path));
        }
        let meta = ExposureMeta {
            detector,
            exposure_index,
            t_start_utc: t_start.to_iso(),
            t_start,
            t_exposure_s,
            focal_plane_temp_k,
            t_illuminated_s,
        };
        Ok((meta, sequence))
    }

    /// The start of the exposure in UTC, and the keyword it was read from: `DATE-OBS`,
    /// else `MJD-OBS`, in the time scale `TIMESYS` names ([`utc_offset_s`]).
    fn start_time(&mut self) -> Result<(UtcSeconds, String)> {
        let k = self.keywords;
        let (t, key) = match self.key::<String>(&k.date_obs)? {
            Some(s) => (
                parse_date_obs(&s)
                    .map_err(|m| Error::invalid(self.field(&k.date_obs), m).path(self.path))?,
                k.date_obs.clone(),
            ),
            None => {
                let what = format!("start time (or {})", k.date_obs);
                let mjd: f64 = self.required(&k.mjd_obs, &what)?;
                if !mjd.is_finite() {
                    return Err(
                        Error::invalid(self.field(&k.mjd_obs), "not finite").path(self.path)
                    );
                }
                (
                    UtcSeconds((mjd - MJD_UNIX_EPOCH) * 86_400.0),
                    k.mjd_obs.clone(),
                )
            }
        };
        let scale = self
            .key::<String>(&k.time_system)?
            .map(|s| s.trim().to_ascii_uppercase())
            .unwrap_or_default();
        let offset = utc_offset_s(&scale, t)
            .map_err(|m| Error::invalid(self.field(&k.time_system), m).path(self.path))?;
        Ok((UtcSeconds(t.0 - offset), key))
    }

    /// The factor that turns the image into e-/s, and where it came from.
    pub(crate) fn conversion(&mut self, det: DetectorId, cfg: &FitsConfig) -> Result<Conversion> {
        let k = self.keywords;
        let image_unit = self
            .key::<String>(&k.image_unit)?
            .unwrap_or_default()
            .trim()
            .to_owned();
        if let Some(&factor) = cfg.gains.get(&det.0) {
            return Ok(Conversion {
                factor,
                image_unit,
                source: "argument --fits-gain".into(),
            });
        }
        if let Some(factor) = self.key::<f64>(&k.conversion)? {
            if !(factor.is_finite() && factor > 0.0) {
                return Err(Error::invalid(
                    self.field(&k.conversion),
                    format!("conversion factor must be finite and > 0, got {factor}"),
                )
                .path(self.path));
            }
            return Ok(Conversion {
                factor,
                image_unit,
                source: format!("header {}", k.conversion),
            });
        }
        if E_PER_S_UNITS
            .iter()
            .any(|u| u.eq_ignore_ascii_case(&image_unit))
        {
            return Ok(Conversion {
                factor: 1.0,
                image_unit,
                source: format!("unit {}", k.image_unit),
            });
        }
        Err(Error::invalid(
            self.field(&k.image_unit),
            format!(
                "image unit `{image_unit}` is not e-/s and no conversion factor is known for \
                 detector {det}: pass --fits-gain {det}:FACTOR (e-/s per image unit) or set \
                 the {} keyword",
                k.conversion
            ),
        )
        .path(self.path))
    }
}

/// Refuse a file that does not end where its last HDU does: truncated (the last data
/// unit, or a header after it, cut short), or followed by bytes that are no HDU. cfitsio
/// reads what it is asked for and would otherwise fail only when an extension past the
/// cut is touched, which for an output starting from a copy of the input is after the
/// step.
fn check_complete(path: &Path, file: &mut FitsFile) -> Result<()> {
    let n = file.num_hdus().map_err(|e| fits_error(path, "file", e))?;
    let last = n
        .checked_sub(1)
        .ok_or_else(|| Error::invalid("file", "has no header data unit").path(path))?;
    file.hdu(last)
        .map_err(|e| fits_error(path, &format!("HDU {n}"), e))?;
    let (mut header_start, mut data_start, mut data_end) = (0i64, 0i64, 0i64);
    let mut status = 0;
    // SAFETY: the pointer is the open file's, used only for this call; the outputs are
    // plain integers.
    unsafe {
        fitsio::sys::ffghadll(
            file.as_raw(),
            &mut header_start,
            &mut data_start,
            &mut data_end,
            &mut status,
        )
    };
    if status != 0 {
        return Err(Error::invalid(
            format!("HDU {n}"),
            format!("cfitsio error {status} locating the data unit"),
        )
        .path(path));
    }
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    let end = u64::try_from(data_end).unwrap_or(0);
    if end > len {
        return Err(Error::invalid(
            format!("HDU {n}"),
            format!("truncated: its data end at byte {end}, the file has {len} bytes"),
        )
        .path(path));
    }
    if end < len {
        return Err(Error::invalid(
            "file",
            format!(
                "{} bytes after the last complete HDU ({n}, ending at byte {end}) are not a \
                 FITS extension (truncated?)",
                len - end
            ),
        )
        .path(path));
    }
    Ok(())
}

/// `DATE-OBS` as FITS writes it (`YYYY-MM-DDThh:mm:ss[.s...]`, UTC, no zone), or with
/// an explicit zone.
pub(crate) fn parse_date_obs(s: &str) -> std::result::Result<UtcSeconds, String> {
    let s = s.trim();
    UtcSeconds::parse(s)
        .or_else(|_| UtcSeconds::parse(&format!("{s}Z")))
        .map_err(|_| format!("`{s}` is not an ISO 8601 UTC time (YYYY-MM-DDThh:mm:ss[.s])"))
}

/// The 2-D shape `[ny, nx]` of an image extension, checked.
pub(crate) fn plane_shape(path: &Path, ext: &str, hdu: &FitsHdu) -> Result<(usize, usize)> {
    match &hdu.info {
        HduInfo::ImageInfo { shape, .. } if shape.len() == 2 => {
            crate::h5io::check_axes(ext, shape).map_err(|e| e.path(path))?;
            Ok((shape[0], shape[1]))
        }
        HduInfo::ImageInfo { shape, .. } => {
            Err(Error::invalid(ext, format!("must be a 2-D image, has shape {shape:?}")).path(path))
        }
        _ => Err(Error::invalid(ext, "must be an image extension, is a table").path(path)),
    }
}

/// The exposure's header values only (cheap: no plane is read), for queueing.
pub fn read_meta(path: &Path, cfg: &FitsConfig) -> Result<ExposureMeta> {
    read_meta_sequence(path, cfg).map(|(meta, _)| meta)
}

/// [`read_meta`], and where the exposure index came from.
pub fn read_meta_sequence(path: &Path, cfg: &FitsConfig) -> Result<(ExposureMeta, Sequence)> {
    let mut h = Headers::open(path, &cfg.keywords)?;
    let (meta, sequence) = h.meta()?;
    h.conversion(meta.detector, cfg)?;
    Ok((meta, sequence))
}

/// The exposure index of a start time: milliseconds since 1970-01-01T00:00:00 UTC
/// (rounded), so that the index order is the start-time order; `None` before 1970.
pub fn index_of_start(t_start: UtcSeconds) -> Option<u64> {
    let ms = (t_start.0 * 1e3).round();
    (ms.is_finite() && ms >= 0.0 && ms < 2f64.powi(63)).then_some(ms as u64)
}

/// TAI - UTC since 2017-01-01T00:00:00 UTC (IERS Bulletin C: no leap second since).
const TAI_MINUS_UTC_S: f64 = 37.0;
/// 2017-01-01T00:00:00 UTC, Unix seconds: the last leap second's end.
const LAST_LEAP_UNIX_S: f64 = 1_483_228_800.0;

/// Seconds to subtract from a time read in the scale `scale` (FITS `TIMESYS`, upper
/// case; empty when absent) to get UTC. UTC and absent: 0. TAI: 37 s, GPS: 19 s less,
/// TT (or TDT): TAI + 32.184 s; TDB is taken as TT (they differ by < 2 ms). The offsets
/// hold from 2017 on (the last leap second); earlier times in those scales, and other
/// scales, are refused rather than converted wrongly.
pub fn utc_offset_s(scale: &str, t: UtcSeconds) -> std::result::Result<f64, String> {
    let offset = match scale {
        "" | "UTC" => return Ok(0.0),
        "TAI" => TAI_MINUS_UTC_S,
        "GPS" => TAI_MINUS_UTC_S - 19.0,
        "TT" | "TDT" | "TDB" => TAI_MINUS_UTC_S + 32.184,
        other => {
            return Err(format!(
                "time scale `{other}` is not supported: UTC, TAI, TT, TDB or GPS"
            ))
        }
    };
    if t.0 - offset < LAST_LEAP_UNIX_S {
        return Err(format!(
            "{scale} before 2017-01-01 is not supported (leap seconds before it are not \
             tabulated): give the start time in UTC"
        ));
    }
    Ok(offset)
}

/// Read and check one FITS exposure; the image is returned in e-/s.
pub fn read_exposure(path: &Path, cfg: &FitsConfig) -> Result<(Exposure, FitsInput)> {
    let mut h = Headers::open(path, &cfg.keywords)?;
    let (meta, sequence) = h.meta()?;
    let conv = h.conversion(meta.detector, cfg)?;
    let k = &cfg.keywords;
    let dim = plane_shape(path, &k.image_ext, &h.image)?;
    let flags_hdu = h
        .file
        .hdu(k.flags_ext.as_str())
        .map_err(|e| fits_error(path, &k.flags_ext, e))?;
    let fdim = plane_shape(path, &k.flags_ext, &flags_hdu)?;
    // Bit 17 is written back into this plane: it must hold 32 bits or more.
    if let HduInfo::ImageInfo { image_type, .. } = &flags_hdu.info {
        if !matches!(
            image_type,
            ImageType::Long | ImageType::UnsignedLong | ImageType::LongLong
        ) {
            return Err(Error::invalid(
                format!("{}/BITPIX", k.flags_ext),
                format!(
                    "a {image_type:?} plane cannot hold bit 17 (PERSIST): 32-bit integers needed"
                ),
            )
            .path(path));
        }
    }
    for (name, bit) in MODEL_FLAG_BITS {
        let field = || format!("{}/{name}", k.flags_ext);
        match flags_hdu.read_key::<i64>(&mut h.file, name) {
            Ok(b) if b == i64::from(*bit) => {}
            Ok(b) => {
                return Err(Error::invalid(
                    field(),
                    format!("names bit {b}; persist reads and writes it as bit {bit} (SPHEREx's)"),
                )
                .path(path))
            }
            Err(fitsio::errors::Error::Fits(f)) if f.status == KEY_NO_EXIST => {}
            Err(e) => {
                return Err(
                    Error::invalid(field(), format!("not an integer bit number: {e}")).path(path),
                )
            }
        }
    }
    if fdim != dim {
        return Err(Error::invalid(
            k.flags_ext.as_str(),
            format!("shape {fdim:?} differs from {} {dim:?}", k.image_ext),
        )
        .path(path));
    }
    let pixels: Vec<f32> = h
        .image
        .read_image(&mut h.file)
        .map_err(|e| fits_error(path, &k.image_ext, e))?;
    let bits: Vec<i32> = flags_hdu
        .read_image(&mut h.file)
        .map_err(|e| fits_error(path, &k.flags_ext, e))?;
    let plane = |n: usize, ext: &str| -> Result<()> {
        if n == dim.0 * dim.1 {
            Ok(())
        } else {
            Err(Error::new(
                ErrorKind::Invalid,
                format!("read {n} pixels, expected {dim:?}"),
            )
            .field(ext)
            .path(path))
        }
    };
    plane(pixels.len(), &k.image_ext)?;
    plane(bits.len(), &k.flags_ext)?;
    let factor = conv.factor;
    let image = Array2::from_shape_vec(
        dim,
        pixels
            .into_iter()
            .map(|v| {
                if factor == 1.0 {
                    v
                } else {
                    (f64::from(v) * factor) as f32
                }
            })
            .collect(),
    )
    .map_err(|e| Error::invalid(k.image_ext.as_str(), e.to_string()).path(path))?;
    // The bit pattern of the int32 plane, unchanged but for an archive's PERSIST bit.
    let persist = crate::flags::bits::PERSIST;
    let input_persist_px = bits.iter().filter(|&&b| b as u32 & persist != 0).count() as u64;
    let flags =
        Array2::from_shape_vec(dim, bits.into_iter().map(|b| b as u32 & !persist).collect())
            .map_err(|e| Error::invalid(k.flags_ext.as_str(), e.to_string()).path(path))?;
    let errors: Vec<Error> = check_exposure_data(&image, &flags, None, false)
        .into_iter()
        .map(|mut e| {
            e.context.field = e.context.field.map(|f| match f.as_str() {
                "/image" => format!("{} (in e-/s)", k.image_ext),
                "/flags" => k.flags_ext.clone(),
                _ => f,
            });
            e.path(path)
        })
        .collect();
    if !errors.is_empty() {
        return Err(combine(errors));
    }
    Ok((
        Exposure {
            meta,
            image,
            flags,
            ramp: None,
            ramp_times_s: None,
        },
        FitsInput {
            conversion: conv,
            input_persist_px,
            sequence,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn date_obs_without_zone_is_utc() {
        let a = parse_date_obs("2025-05-01T12:00:00.5").unwrap();
        let b = UtcSeconds::parse("2025-05-01T12:00:00.5Z").unwrap();
        assert_eq!(a, b);
        assert!(parse_date_obs("2025-05-01").is_err());
    }

    #[test]
    fn start_time_indices_order_as_the_times_do() {
        let t = UtcSeconds::parse("2025-05-01T12:00:00.0016Z").unwrap();
        // 1,746,100,800 s since 1970 (date -d 2025-05-01T12:00:00Z +%s), in ms, rounded.
        assert_eq!(index_of_start(t), Some(1_746_100_800_002));
        let later = UtcSeconds(t.0 + 0.001);
        assert!(index_of_start(later) > index_of_start(t));
        assert_eq!(index_of_start(UtcSeconds(-1.0)), None);
        assert_eq!(index_of_start(UtcSeconds(f64::NAN)), None);
    }

    #[test]
    fn time_scales_convert_to_utc_or_are_refused() {
        let t = UtcSeconds::parse("2025-05-01T12:00:00Z").unwrap();
        assert_eq!(utc_offset_s("", t), Ok(0.0));
        assert_eq!(utc_offset_s("UTC", t), Ok(0.0));
        // TAI - UTC = 37 s since 2017-01-01 (IERS Bulletin C); TT = TAI + 32.184 s.
        assert_eq!(utc_offset_s("TAI", t), Ok(37.0));
        assert_eq!(utc_offset_s("TT", t), Ok(69.184));
        assert_eq!(utc_offset_s("GPS", t), Ok(18.0));
        assert!(utc_offset_s("TCB", t).unwrap_err().contains("TCB"));
        let old = UtcSeconds::parse("2010-01-01T00:00:00Z").unwrap();
        assert!(utc_offset_s("TAI", old).is_err());
        assert_eq!(utc_offset_s("UTC", old), Ok(0.0));
    }
}
