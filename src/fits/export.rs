//! HDF5 products -> FITS files in the SPHEREx Level-2 layout (`persist export --fits`).
//!
//! A Level-1 input product becomes a FITS exposure the stage can read (`PRIMARY`,
//! `IMAGE`, `FLAGS`, and with `placeholders` also `VARIANCE`, `ZODI`, `PSF` and
//! `WCS-WAVE` of SPHEREx's shapes); an output product gets `PERSIST_CURRENT` and
//! `PERSIST_FLAGS` as well, with the cards the stage writes. The image is written in
//! e-/s, or divided by a conversion factor (e-/s per unit, then `BUNIT = 'MJy/sr'` and
//! the factor in `ESCONV`), so that reading it back with the same factor gives the
//! HDF5 image. The placeholders are synthetic (a variance from the image, a flat zodi,
//! a Gaussian PSF cube, a linear wavelength table from the band edges): they give
//! round-trip tests SPHEREx's file structure, not science.

use crate::error::{Error, ErrorKind, Result};
use crate::product::fits::write::{append_persistence, check_written, flag_cards, flush};
use crate::product::fits::{fits_error, Conversion, Keywords};
use crate::product::{self, Exposure, PersistenceAttrs, PersistencePlanes};
use crate::validate::{validate_path, ProductKind};
use fitsio::images::{ImageDescription, ImageType};
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// SPHEREx PSF extension: 121 PSFs (an 11 x 11 grid of zones), 101 x 101 each.
pub const PSF_SHAPE: [usize; 3] = [121, 101, 101];

/// Band edges (um) and resolving power per detector (SPHEREx archive documentation).
const BANDS: [(f64, f64, f64); 6] = [
    (0.75, 1.09, 39.0),
    (1.10, 1.62, 41.0),
    (1.63, 2.41, 41.0),
    (2.42, 3.82, 35.0),
    (3.83, 4.41, 112.0),
    (4.42, 5.00, 128.0),
];

/// How to export.
#[derive(Debug, Clone, Default)]
pub struct ExportOptions {
    /// e-/s per written image unit, per detector; absent: the image is written in e-/s.
    pub gains: BTreeMap<u8, f64>,
    /// Add `VARIANCE`, `ZODI`, `PSF`, `WCS-WAVE` placeholders and a spatial WCS.
    pub placeholders: bool,
}

/// Export one HDF5 product (input or output) to `out_dir/NAME.fits`; returns the path.
pub fn export_file(h5: &Path, out_dir: &Path, opts: &ExportOptions) -> Result<PathBuf> {
    let kind = validate_path(h5).map_err(product::schema::combine)?;
    let stem = h5.file_stem().unwrap_or_default().to_string_lossy();
    let path = out_dir.join(format!("{stem}.fits"));
    match kind {
        ProductKind::L1Exposure => {
            let e = product::read_exposure(h5)?;
            write_exposure(&path, &e, None, opts)?;
        }
        ProductKind::L2Persistence => {
            let (e, planes, attrs) = product::read_output(h5)?;
            write_exposure(&path, &e, Some((&planes, &attrs)), opts)?;
        }
        other => {
            return Err(Error::new(
                ErrorKind::Usage,
                format!("is a {other}, not an exposure or output product"),
            )
            .path(h5))
        }
    }
    Ok(path)
}

/// Write an exposure (and its persistence planes, for an output) as a new FITS file.
pub fn write_exposure(
    path: &Path,
    e: &Exposure,
    persistence: Option<(&PersistencePlanes, &PersistenceAttrs)>,
    opts: &ExportOptions,
) -> Result<()> {
    let k = Keywords::default();
    let dim = e.image.dim();
    let det = e.meta.detector;
    let factor = opts.gains.get(&det.0).copied();
    let unit = if factor.is_some() { "MJy/sr" } else { "e-/s" };
    crate::h5io::publish(
        path,
        |tmp| {
            let mut f = FitsFile::create(tmp)
                .open()
                .map_err(|err| fits_error(path, "file", err))?;
            let ext = k.image_ext.as_str();
            let fe = |err| fits_error(path, ext, err);
            let hdu = f
                .create_image(ext, &image(ImageType::Float, &[dim.0, dim.1]))
                .map_err(fe)?;
            let pixels: Vec<f32> = e
                .image
                .iter()
                .map(|&v| match factor {
                    Some(g) => (f64::from(v) / g) as f32,
                    None => v,
                })
                .collect();
            hdu.write_image(&mut f, &pixels).map_err(fe)?;
            let m = &e.meta;
            hdu.write_key(&mut f, &k.image_unit, (unit, "image unit"))
                .map_err(fe)?;
            if let Some(g) = factor {
                hdu.write_key(&mut f, &k.conversion, (g, "e-/s per MJy/sr"))
                    .map_err(fe)?;
            }
            hdu.write_key(&mut f, &k.detector, (i64::from(det.0), "detector number"))
                .map_err(fe)?;
            hdu.write_key(&mut f, "TIMESYS", ("UTC", "time scale"))
                .map_err(fe)?;
            hdu.write_key(
                &mut f,
                &k.date_obs,
                (date_obs(m.t_start.0).as_str(), "start of exposure"),
            )
            .map_err(fe)?;
            let mjd = m.t_start.0 / 86_400.0 + 40587.0;
            hdu.write_key(&mut f, &k.mjd_obs, (mjd, "[d] start of exposure (MJD)"))
                .map_err(fe)?;
            hdu.write_key(
                &mut f,
                &k.exposure_time,
                (m.t_exposure_s, "[s] exposure time"),
            )
            .map_err(fe)?;
            if let Some(t) = m.t_illuminated_s {
                hdu.write_key(&mut f, &k.illuminated_time, (t, "[s] illuminated time"))
                    .map_err(fe)?;
            }
            if let Some(t) = m.focal_plane_temp_k {
                hdu.write_key(
                    &mut f,
                    &k.focal_plane_temp,
                    (t, "[K] focal plane temperature"),
                )
                .map_err(fe)?;
            }
            if opts.placeholders {
                spatial_wcs(&mut f, &hdu, dim).map_err(fe)?;
            }

            let ext = k.flags_ext.as_str();
            let fe = |err| fits_error(path, ext, err);
            let hdu = f
                .create_image(ext, &image(ImageType::Long, &[dim.0, dim.1]))
                .map_err(fe)?;
            let bits: Vec<i32> = e.flags.iter().map(|&b| b as i32).collect();
            hdu.write_image(&mut f, &bits).map_err(fe)?;
            flag_cards(&mut f, &hdu).map_err(fe)?;

            if opts.placeholders {
                placeholders(&mut f, path, e, factor.unwrap_or(1.0))?;
            }
            if let Some((planes, attrs)) = persistence {
                let conv = Conversion {
                    factor: factor.unwrap_or(1.0),
                    image_unit: unit.into(),
                    source: match factor {
                        Some(_) => "argument --fits-gain (export)".into(),
                        None => "unit BUNIT (export)".into(),
                    },
                };
                let index = (e.meta.exposure_index, "HDF5 exposure_index");
                append_persistence(&mut f, path, planes, attrs, &conv, index, None)?;
            }
            flush(&mut f, path)
        },
        |tmp| {
            let mut f = FitsFile::open(tmp).map_err(|err| fits_error(path, "file", err))?;
            for ext in [k.image_ext.as_str(), k.flags_ext.as_str()] {
                let hdu = f.hdu(ext).map_err(|err| fits_error(path, ext, err))?;
                crate::product::fits::read::plane_shape(path, ext, &hdu)?;
            }
            if persistence.is_some() {
                check_written(tmp, path, dim, &k.flags_ext)?;
            }
            Ok(())
        },
    )
}

fn image<'a>(data_type: ImageType, dimensions: &'a [usize]) -> ImageDescription<'a> {
    ImageDescription {
        data_type,
        dimensions,
    }
}

/// FITS `DATE-OBS`: `YYYY-MM-DDThh:mm:ss.ssssss`, UTC, no zone.
fn date_obs(unix_s: f64) -> String {
    let iso = crate::units::UtcSeconds(unix_s).to_iso();
    iso.trim_end_matches('Z').to_owned()
}

/// A tangent-plane WCS of SPHEREx's pixel scale (6.15 arcsec) at (0, 0).
fn spatial_wcs(
    f: &mut FitsFile,
    hdu: &fitsio::hdu::FitsHdu,
    dim: (usize, usize),
) -> fitsio::errors::Result<()> {
    let scale_deg = 6.15 / 3600.0;
    hdu.write_key(f, "WCSAXES", (2i64, "placeholder WCS"))?;
    hdu.write_key(f, "CTYPE1", ("RA---TAN", ""))?;
    hdu.write_key(f, "CTYPE2", ("DEC--TAN", ""))?;
    hdu.write_key(f, "CRPIX1", ((dim.1 as f64 + 1.0) / 2.0, ""))?;
    hdu.write_key(f, "CRPIX2", ((dim.0 as f64 + 1.0) / 2.0, ""))?;
    hdu.write_key(f, "CRVAL1", (0.0f64, "[deg]"))?;
    hdu.write_key(f, "CRVAL2", (0.0f64, "[deg]"))?;
    hdu.write_key(f, "CDELT1", (-scale_deg, "[deg/pixel]"))?;
    hdu.write_key(f, "CDELT2", (scale_deg, "[deg/pixel]"))?;
    hdu.write_key(f, "CUNIT1", ("deg", ""))?;
    hdu.write_key(f, "CUNIT2", ("deg", ""))?;
    Ok(())
}

/// `VARIANCE`, `ZODI`, `PSF` and `WCS-WAVE` of SPHEREx's shapes (module docs).
fn placeholders(f: &mut FitsFile, path: &Path, e: &Exposure, factor: f64) -> Result<()> {
    let (ny, nx) = e.image.dim();
    let t = e.meta.t_exposure_s;
    let unit2 = if factor == 1.0 {
        "(e-/s)^2"
    } else {
        "(MJy/sr)^2"
    };
    let unit = if factor == 1.0 { "e-/s" } else { "MJy/sr" };
    // Shot noise plus a 20 e- read noise, in image units squared.
    let variance: Vec<f32> = e
        .image
        .iter()
        .map(|&v| {
            let electrons = f64::from(v).max(0.0) * t;
            let var_e_per_s = (electrons + 400.0) / (t * t);
            (var_e_per_s / (factor * factor)) as f32
        })
        .collect();
    let mut finite: Vec<f32> = e.image.iter().copied().filter(|v| v.is_finite()).collect();
    finite.sort_by(f32::total_cmp);
    let zodi_level = finite.get(finite.len() / 2).copied().unwrap_or(0.0) / factor as f32;
    let zodi = vec![zodi_level; ny * nx];
    for (ext, data, u) in [("VARIANCE", &variance, unit2), ("ZODI", &zodi, unit)] {
        let fe = |err| fits_error(path, ext, err);
        let hdu = f
            .create_image(ext, &image(ImageType::Float, &[ny, nx]))
            .map_err(fe)?;
        hdu.write_image(f, data).map_err(fe)?;
        hdu.write_key(f, "BUNIT", (u, "")).map_err(fe)?;
    }
    let ext = "PSF";
    let fe = |err| fits_error(path, ext, err);
    let hdu = f
        .create_image(ext, &image(ImageType::Float, &PSF_SHAPE))
        .map_err(fe)?;
    let [nz, py, px] = PSF_SHAPE;
    let sigma = 10.0f64; // oversampled pixels (10 per image pixel)
    let (cy, cx) = ((py as f64 - 1.0) / 2.0, (px as f64 - 1.0) / 2.0);
    let one: Vec<f64> = (0..py * px)
        .map(|i| {
            let (y, x) = ((i / px) as f64 - cy, (i % px) as f64 - cx);
            (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let sum: f64 = one.iter().sum();
    let layer: Vec<f32> = one.iter().map(|v| (v / sum) as f32).collect();
    let cube: Vec<f32> = (0..nz).flat_map(|_| layer.iter().copied()).collect();
    hdu.write_image(f, &cube).map_err(fe)?;
    hdu.write_key(f, "OVERSAMP", (10i64, "PSF pixels per image pixel"))
        .map_err(fe)?;

    let ext = "WCS-WAVE";
    let fe = |err| fits_error(path, ext, err);
    let (lo, hi, r) = BANDS[usize::from(e.meta.detector.0 - 1)];
    let grid =
        |n: usize| -> Vec<f64> { (0..7).map(|i| i as f64 * (n as f64 - 1.0) / 6.0).collect() };
    let (xs, ys) = (grid(nx), grid(ny));
    let mut values = Vec::with_capacity(98);
    for yi in 0..7 {
        for _xi in 0..7 {
            let lambda = hi - (hi - lo) * yi as f64 / 6.0;
            values.push(lambda);
            values.push(lambda / r);
        }
    }
    let cols = [
        ColumnDescription::new("X")
            .with_type(ColumnDataType::Double)
            .that_repeats(7)
            .create()
            .map_err(fe)?,
        ColumnDescription::new("Y")
            .with_type(ColumnDataType::Double)
            .that_repeats(7)
            .create()
            .map_err(fe)?,
        ColumnDescription::new("VALUES")
            .with_type(ColumnDataType::Double)
            .that_repeats(98)
            .create()
            .map_err(fe)?,
    ];
    let hdu = f.create_table(ext, &cols).map_err(fe)?;
    hdu.write_col(f, "X", &xs).map_err(fe)?;
    hdu.write_col(f, "Y", &ys).map_err(fe)?;
    hdu.write_col(f, "VALUES", &values).map_err(fe)?;
    hdu.write_key(f, "TDIM3", ("(2,7,7)", "wavelength, bandwidth per point"))
        .map_err(fe)?;
    hdu.write_key(f, "TUNIT3", ("um", "")).map_err(fe)?;
    Ok(())
}

/// Replace every HDF5 input product directly in `dir` (not in subfolders) by its FITS
/// export (`NAME.fits`, placeholders as `opts` says); returns how many. The simulator's
/// `--format fits`.
pub fn convert_dir(dir: &Path, opts: &ExportOptions) -> Result<usize> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .filter_map(|d| d.ok().map(|d| d.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or_default();
            p.is_file() && name.ends_with(".h5") && !name.starts_with('.')
        })
        .collect();
    files.sort();
    for h5 in &files {
        export_file(h5, dir, opts)?;
        std::fs::remove_file(h5).map_err(|e| Error::io(h5, e))?;
    }
    Ok(files.len())
}
