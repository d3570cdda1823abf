//! The stage's result written back into a copy of the input FITS file.
//!
//! The temporary `.NAME.part` starts as a byte copy of the input; then, through cfitsio,
//! the `FLAGS` data are rewritten with bit 17 (`PERSIST`) set where the high threshold is
//! crossed, `MP_PERSIST = 17` is added to the `FLAGS` header when missing (and its
//! `CHECKSUM`/`DATASUM` updated when the input had them), and the extensions
//! `PERSIST_CURRENT` (float32, e-/s) and `PERSIST_FLAGS` (BITPIX 8, unsigned bytes, the
//! bits of `/persistence/flags`) are appended, each with the `/persistence` attributes as
//! header cards. Nothing else in the file changes. The file is flushed, re-opened and its
//! new extensions checked, then published like an HDF5 product (sync, rename, sync).

use super::{
    fits_error, Conversion, FitsInput, Keywords, EXT_PERSIST_CURRENT, EXT_PERSIST_FLAGS,
    KEY_NO_EXIST,
};
use super::{PERSIST_FLAG_BITS, SPHEREX_FLAG_BITS};
use crate::error::{Error, Result};
use crate::product::read::check_persistence_data;
use crate::product::schema::combine;
use crate::product::{Exposure, PersistenceAttrs, PersistencePlanes};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use std::path::Path;

/// Write the output of one FITS exposure: `input` copied to `path` with the stage's
/// flags and planes (module docs). `e.flags` must carry the `PERSIST` bits already.
pub fn write_output(
    input: &Path,
    path: &Path,
    e: &Exposure,
    planes: &PersistencePlanes,
    attrs: &PersistenceAttrs,
    read: &FitsInput,
    keywords: &Keywords,
) -> Result<()> {
    let dim = e.image.dim();
    for (field, d) in [
        (EXT_PERSIST_CURRENT, planes.current_e_per_s.dim()),
        (EXT_PERSIST_FLAGS, planes.flags.dim()),
        (keywords.flags_ext.as_str(), e.flags.dim()),
    ] {
        if d != dim {
            return Err(
                Error::invalid(field, format!("shape {d:?} differs from {dim:?}")).path(path),
            );
        }
    }
    let errors: Vec<Error> =
        check_persistence_data(&e.flags, &planes.current_e_per_s, &planes.flags)
            .into_iter()
            .map(|err| err.path(path))
            .collect();
    if !errors.is_empty() {
        return Err(combine(errors));
    }
    crate::h5io::publish(
        path,
        |tmp| {
            std::fs::copy(input, tmp).map_err(|err| Error::io(input, err))?;
            let mut f = FitsFile::edit(tmp).map_err(|err| fits_error(path, "file", err))?;
            let ext = keywords.flags_ext.as_str();
            let fe = |err| fits_error(path, ext, err);
            let hdu = f.hdu(ext).map_err(fe)?;
            let had_checksum = match hdu.read_key::<String>(&mut f, "CHECKSUM") {
                Ok(_) => true,
                Err(fitsio::errors::Error::Fits(s)) if s.status == KEY_NO_EXIST => false,
                Err(err) => return Err(fe(err)),
            };
            let bits: Vec<i32> = e.flags.iter().map(|&b| b as i32).collect();
            hdu.write_image(&mut f, &bits).map_err(fe)?;
            match hdu.read_key::<i64>(&mut f, "MP_PERSIST") {
                Ok(_) => {}
                Err(fitsio::errors::Error::Fits(s)) if s.status == KEY_NO_EXIST => {
                    hdu.write_key(
                        &mut f,
                        "MP_PERSIST",
                        (17i64, "persistence flagged by persist"),
                    )
                    .map_err(fe)?;
                }
                Err(err) => return Err(fe(err)),
            }
            if had_checksum {
                hdu.read_key::<String>(&mut f, "CHECKSUM").map_err(fe)?; // current HDU
                let mut status = 0;
                // SAFETY: the pointer is the open file's, used only for this call.
                unsafe { fitsio::sys::ffpcks(f.as_raw(), &mut status) };
                if status != 0 {
                    return Err(Error::invalid(
                        ext,
                        format!("cfitsio error {status} updating CHECKSUM"),
                    )
                    .path(path));
                }
            }
            append_persistence(
                &mut f,
                path,
                planes,
                attrs,
                &read.conversion,
                (e.meta.exposure_index, &read.sequence.describe()),
                Some(read.input_persist_px),
            )?;
            flush(&mut f, path)
        },
        |tmp| check_written(tmp, path, dim, &keywords.flags_ext),
    )
}

/// Flush cfitsio's buffers (closing alone would lose the error).
pub(crate) fn flush(f: &mut FitsFile, path: &Path) -> Result<()> {
    let mut status = 0;
    // SAFETY: the pointer is the open file's, used only for this call.
    unsafe { fitsio::sys::ffflus(f.as_raw(), &mut status) };
    if status == 0 {
        Ok(())
    } else {
        Err(Error::invalid("file", format!("cfitsio error {status} flushing")).path(path))
    }
}

/// Re-open a written file and check its persistence extensions (and the flags plane).
pub(crate) fn check_written(
    tmp: &Path,
    path: &Path,
    dim: (usize, usize),
    flags_ext: &str,
) -> Result<()> {
    let mut f = FitsFile::open(tmp).map_err(|e| fits_error(path, "file", e))?;
    for ext in [flags_ext, EXT_PERSIST_CURRENT, EXT_PERSIST_FLAGS] {
        let hdu = f.hdu(ext).map_err(|e| fits_error(path, ext, e))?;
        let d = super::read::plane_shape(path, ext, &hdu)?;
        if d != dim {
            return Err(
                Error::invalid(ext, format!("written with shape {d:?}, expected {dim:?}"))
                    .path(path),
            );
        }
    }
    Ok(())
}

/// Append `PERSIST_CURRENT` and `PERSIST_FLAGS` with their header cards; `index` is
/// the exposure index used and where it came from (`EXPINDEX`, `IDXSRC`).
pub(crate) fn append_persistence(
    f: &mut FitsFile,
    path: &Path,
    planes: &PersistencePlanes,
    attrs: &PersistenceAttrs,
    conv: &Conversion,
    index: (u64, &str),
    input_persist_px: Option<u64>,
) -> Result<()> {
    let index_card = i64::try_from(index.0)
        .map_err(|_| Error::invalid("EXPINDEX", "does not fit an int64").path(path))?;
    let (ny, nx) = planes.current_e_per_s.dim();
    let ext = EXT_PERSIST_CURRENT;
    let fe = |err| fits_error(path, ext, err);
    let hdu = f
        .create_image(
            ext,
            &ImageDescription {
                data_type: ImageType::Float,
                dimensions: &[ny, nx],
            },
        )
        .map_err(fe)?;
    let current: Vec<f32> = planes.current_e_per_s.iter().copied().collect();
    hdu.write_image(f, &current).map_err(fe)?;
    hdu.write_key(f, "BUNIT", ("e-/s", "predicted persistence current"))
        .map_err(fe)?;
    attr_cards(f, &hdu, attrs).map_err(fe)?;
    index_cards(f, &hdu, index_card, index.1).map_err(fe)?;
    hdu.write_key(f, "ESCONV", (conv.factor, "e-/s per input image unit used"))
        .map_err(fe)?;
    hdu.write_key(
        f,
        "ESCONVSR",
        (conv.source.as_str(), "where ESCONV came from"),
    )
    .map_err(fe)?;
    hdu.write_key(
        f,
        "IMGUNIT",
        (conv.image_unit.as_str(), "unit of the input image"),
    )
    .map_err(fe)?;

    let ext = EXT_PERSIST_FLAGS;
    let fe = |err| fits_error(path, ext, err);
    let hdu = f
        .create_image(
            ext,
            &ImageDescription {
                data_type: ImageType::UnsignedByte,
                dimensions: &[ny, nx],
            },
        )
        .map_err(fe)?;
    let pflags: Vec<u8> = planes.flags.iter().copied().collect();
    hdu.write_image(f, &pflags).map_err(fe)?;
    for (name, bit, what) in PERSIST_FLAG_BITS {
        hdu.write_key(f, name, (i64::from(*bit), *what))
            .map_err(fe)?;
    }
    attr_cards(f, &hdu, attrs).map_err(fe)?;
    index_cards(f, &hdu, index_card, index.1).map_err(fe)?;
    if let Some(n) = input_persist_px {
        let n = i64::try_from(n).unwrap_or(i64::MAX);
        hdu.write_key(
            f,
            "PERSIN",
            (n, "pixels with PERSIST in the input, replaced"),
        )
        .map_err(fe)?;
    }
    Ok(())
}

/// The attributes of `/persistence` as header cards. `T_MEAS` is absent when there is
/// no previous exposure (the HDF5 attribute is NaN then; FITS has no NaN card value).
fn attr_cards(
    f: &mut FitsFile,
    hdu: &fitsio::hdu::FitsHdu,
    a: &PersistenceAttrs,
) -> fitsio::errors::Result<()> {
    hdu.write_key(
        f,
        "MODEL_ID",
        (a.model_id.as_str(), "SHA-256 of the model file"),
    )?;
    hdu.write_key(f, "MODELNAM", (a.model_name.as_str(), "model name"))?;
    hdu.write_key(
        f,
        "THR_HIGH",
        (a.threshold_high_e_per_s, "[e-/s] high threshold (PERSIST)"),
    )?;
    hdu.write_key(
        f,
        "THR_LOW",
        (a.threshold_low_e_per_s, "[e-/s] low threshold"),
    )?;
    if a.t_meas_s.is_finite() {
        hdu.write_key(f, "T_MEAS", (a.t_meas_s, "[s] after the previous reset"))?;
    }
    hdu.write_key(
        f,
        "PREV_EXP",
        (a.previous_exposure_index, "previous exposure used, -1 none"),
    )?;
    hdu.write_key(
        f,
        "SW_VERS",
        (a.software_version.as_str(), "persist version"),
    )?;
    hdu.write_key(
        f,
        "HDF5VERS",
        (
            crate::h5io::library_version().as_str(),
            "HDF5 library version of persist",
        ),
    )?;
    hdu.write_key(
        f,
        "PROCUTC",
        (a.processed_utc.as_str(), "processing time (UTC)"),
    )?;
    Ok(())
}

/// The exposure index the stage used (`PREV_EXP` of the next output) and its source.
fn index_cards(
    f: &mut FitsFile,
    hdu: &fitsio::hdu::FitsHdu,
    index: i64,
    source: &str,
) -> fitsio::errors::Result<()> {
    hdu.write_key(f, "EXPINDEX", (index, "exposure index used (IDXSRC)"))?;
    hdu.write_key(f, "IDXSRC", (source, "where EXPINDEX came from"))
}

/// The `MP_<NAME>` cards of a `FLAGS` header written from scratch.
pub(crate) fn flag_cards(
    f: &mut FitsFile,
    hdu: &fitsio::hdu::FitsHdu,
) -> fitsio::errors::Result<()> {
    for (name, bit) in SPHEREX_FLAG_BITS {
        hdu.write_key(f, name, (i64::from(*bit), "bit number"))?;
    }
    Ok(())
}
