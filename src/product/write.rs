//! [`Exposure`] (+ persistence planes) -> temporary file -> validate -> sync -> rename.
//!
//! Both writers check the data in memory exactly as a reader would check them after
//! reading ([`super::read`]'s data checks), then publish atomically
//! ([`crate::h5io::publish`]; [`stage_output`] is its first half, for a caller that
//! publishes on another thread): the file is written as `.NAME.part` in the destination
//! directory, closed, re-opened and its layout validated as a reader would (schema,
//! manifest checks, root attributes; the datasets are not read back, which would move
//! every byte twice), synced, renamed into place, and the directory synced. On any
//! failure the temporary file is removed and nothing appears under the final name.
//!
//! Layout choices (DEPENDENCIES.md): `/image`, `/ramp`, `/ramp_times_s` and
//! `/persistence/current` contiguous and uncompressed; the flag planes (`/flags` u32 and
//! `/persistence/flags` u8) chunked by rows, shuffled, then deflated. Object times are
//! off, so the same content gives byte-identical files.
//!
//! Attribute types written: strings as variable-length UTF-8, integers as int64,
//! floats as float64, all scalar.

use super::exposure::{Exposure, PersistenceAttrs, PersistencePlanes, PRODUCT_L1, SCHEMA_VERSION};
use super::read::{
    check_exposure_data, check_l1_layout, check_l2_layout, check_persistence_data, check_stats,
};
use super::schema::combine;
use crate::error::{Error, Result};
use crate::h5io::{self, attr_f64, attr_i64, attr_str};
use std::path::Path;

/// Write a Level-1 input product (used by the simulator and the fixtures).
pub fn write_exposure(path: &Path, e: &Exposure) -> Result<()> {
    precheck(e).map_err(|err| err.path(path))?;
    data_errors(
        path,
        check_exposure_data(&e.image, &e.flags, e.ramp_times_s.as_ref(), false),
    )?;
    h5io::publish(
        path,
        |tmp| {
            let file = h5io::create(tmp)?;
            write_input_part(&file, e)?;
            file.close()?;
            Ok(())
        },
        |tmp| {
            let file = h5io::open_as(tmp, path)?;
            check_l1_layout(&file, path).map(|_| ()).map_err(combine)
        },
    )
}

/// Write an output product: everything of the input (`e.flags` must already carry the
/// `PERSIST` bits) plus `/persistence` with its planes and attributes.
pub fn write_output(
    path: &Path,
    e: &Exposure,
    planes: &PersistencePlanes,
    attrs: &PersistenceAttrs,
) -> Result<()> {
    stage_output(path, e, planes, attrs)?.commit()
}

/// The first half of [`write_output`]: every check, and the write and validation under
/// the temporary name. [`h5io::Staged::commit`] publishes it (fsync, rename, directory
/// fsync) and needs no HDF5 call and none of the data, so it can run on another thread.
pub fn stage_output(
    path: &Path,
    e: &Exposure,
    planes: &PersistencePlanes,
    attrs: &PersistenceAttrs,
) -> Result<h5io::Staged> {
    precheck(e).map_err(|err| err.path(path))?;
    let dim = e.image.dim();
    for (field, d) in [
        ("/persistence/current", planes.current_e_per_s.dim()),
        ("/persistence/flags", planes.flags.dim()),
    ] {
        if d != dim {
            return Err(
                Error::invalid(field, format!("shape {d:?} differs from /image {dim:?}"))
                    .path(path),
            );
        }
    }
    let mut errors = check_exposure_data(&e.image, &e.flags, e.ramp_times_s.as_ref(), true);
    errors.extend(check_persistence_data(
        &e.flags,
        &planes.current_e_per_s,
        &planes.flags,
    ));
    errors.extend(check_stats(attrs.stats.as_ref(), &planes.flags));
    data_errors(path, errors)?;
    h5io::write_temp(
        path,
        |tmp| {
            let file = h5io::create(tmp)?;
            write_input_part(&file, e)?;
            let g = h5io::create_group(&file, "persistence")?;
            h5io::write_plain(&g, "current", planes.current_e_per_s.view())?;
            h5io::write_flags(&g, "flags", planes.flags.view())?;
            attr_str(&g, "model_id", &attrs.model_id)?;
            attr_str(&g, "model_name", &attrs.model_name)?;
            attr_f64(&g, "threshold_high_e_per_s", attrs.threshold_high_e_per_s)?;
            attr_f64(&g, "threshold_low_e_per_s", attrs.threshold_low_e_per_s)?;
            attr_f64(&g, "t_meas_s", attrs.t_meas_s)?;
            attr_i64(&g, "previous_exposure_index", attrs.previous_exposure_index)?;
            attr_str(&g, "software_version", &attrs.software_version)?;
            attr_str(&g, "hdf5_version", &h5io::library_version())?;
            attr_str(&g, "processed_utc", &attrs.processed_utc)?;
            if let Some(st) = &attrs.stats {
                attr_f64(&g, "fraction_above_high", st.fraction_above_high)?;
                attr_f64(&g, "fraction_above_low", st.fraction_above_low)?;
                let n = i64::try_from(st.n_flagged)
                    .map_err(|_| Error::invalid("n_flagged", "does not fit an int64"))?;
                attr_i64(&g, "n_flagged", n)?;
            }
            if let Some(w) = &attrs.warmup {
                attr_f64(&g, "warmup_s", w.warmup_s)?;
                attr_f64(&g, "carry_in_bound_e_per_s", w.carry_in_bound_e_per_s)?;
            }
            drop(g);
            file.close()?;
            Ok(())
        },
        |tmp| {
            let file = h5io::open_as(tmp, path)?;
            check_l2_layout(&file, path).map(|_| ()).map_err(combine)
        },
    )
}

/// The value checks a reader makes, done on the data in memory before they are written.
fn data_errors(path: &Path, errors: Vec<Error>) -> Result<()> {
    if errors.is_empty() {
        Ok(())
    } else {
        Err(combine(errors.into_iter().map(|e| e.path(path)).collect()))
    }
}

/// Shapes that would make HDF5 fail obscurely (validation checks the rest).
fn precheck(e: &Exposure) -> Result<()> {
    let dim = e.image.dim();
    h5io::check_plane("/image", dim)?;
    if e.flags.dim() != dim {
        return Err(Error::invalid(
            "/flags",
            format!("shape {:?} differs from /image {dim:?}", e.flags.dim()),
        ));
    }
    if let Some(r) = &e.ramp {
        h5io::check_axes("/ramp", r.shape())?;
    }
    if e.ramp.is_some() != e.ramp_times_s.is_some() {
        return Err(Error::invalid(
            "/ramp_times_s",
            "/ramp and /ramp_times_s go together",
        ));
    }
    Ok(())
}

fn write_input_part(file: &hdf5::File, e: &Exposure) -> Result<()> {
    let m = &e.meta;
    attr_str(file, "product", PRODUCT_L1)?;
    attr_str(file, "schema_version", SCHEMA_VERSION)?;
    attr_i64(file, "detector", i64::from(m.detector.0))?;
    let index = i64::try_from(m.exposure_index)
        .map_err(|_| Error::invalid("exposure_index", "does not fit an int64"))?;
    attr_i64(file, "exposure_index", index)?;
    attr_str(file, "t_start_utc", &m.t_start_utc)?;
    attr_f64(file, "t_exposure_s", m.t_exposure_s)?;
    if let Some(t) = m.focal_plane_temp_k {
        attr_f64(file, "focal_plane_temp_k", t)?;
    }
    if let Some(t) = m.t_illuminated_s {
        attr_f64(file, "t_illuminated_s", t)?;
    }
    let field = |f: &'static str| move |err: hdf5::Error| Error::from(err).field(f);
    h5io::write_plain(file, "image", e.image.view()).map_err(field("/image"))?;
    h5io::write_flags(file, "flags", e.flags.view()).map_err(field("/flags"))?;
    if let Some(r) = &e.ramp {
        h5io::write_plain(file, "ramp", r.view()).map_err(field("/ramp"))?;
    }
    if let Some(t) = &e.ramp_times_s {
        h5io::write_plain(file, "ramp_times_s", t.view()).map_err(field("/ramp_times_s"))?;
    }
    Ok(())
}
