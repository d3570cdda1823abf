//! HDF5 -> [`Exposure`], after checking the layout against the schema.
//!
//! Order, so that nothing big is read from a file that is not a product of the ICD:
//! 1. open (a file still open for writing elsewhere gives [`crate::ErrorKind::NotReady`]);
//! 2. build the manifest (attributes and dataset headers only) and validate it against
//!    the schema, plus the checks the schema cannot express (dimensions 1..=8192 per
//!    axis, shapes agree, times parse, `t_illuminated_s <= t_exposure_s`);
//! 3. only then read the datasets (one allocation each, no copies), and check values:
//!    no +/-Inf in `/image`, at least one finite pixel, no `PERSIST` bit in an input's
//!    `/flags`, `ramp_times_s` finite and strictly increasing; for outputs, the
//!    predicted current finite and >= 0, no undefined `/persistence/flags` bits, and
//!    `PERSIST` set exactly where `/persistence/flags` has `HIGH`.
//!
//! Every error names the file and the field; reading never panics, whatever the bytes.

use super::exposure::{
    bits, pbits, Exposure, ExposureMeta, FlagStats, PersistenceAttrs, PersistencePlanes,
};
use super::schema::{self, Schema, View};
use crate::error::{Error, Result};
use crate::h5io;
use crate::units::{DetectorId, UtcSeconds};
use ndarray::{Array, Array1, Array2, Dimension, Ix1, Ix3};
use serde_json::Value;
use std::path::Path;

/// Read and validate a Level-1 input product. Several problems are combined into one
/// error naming each field.
pub fn read_exposure(path: &Path) -> Result<Exposure> {
    let file = h5io::open(path)?;
    read_l1(&file, path).map_err(schema::combine)
}

/// Read and validate only the root attributes of a Level-1 input product (the schema
/// check covers the whole layout; no dataset is read). For queueing many files cheaply.
pub fn read_meta(path: &Path) -> Result<ExposureMeta> {
    let file = h5io::open(path)?;
    let m = schema::manifest(&file).map_err(|e| e.path(path))?;
    check_manifest(Schema::L1Exposure, &m, path).map_err(schema::combine)?;
    meta_of(View(&m), path).map_err(schema::combine)
}

/// Read and validate an output product: the exposure (with `PERSIST` set in its
/// flags), the persistence planes and the attributes of `/persistence`.
pub fn read_output(path: &Path) -> Result<(Exposure, PersistencePlanes, PersistenceAttrs)> {
    let file = h5io::open(path)?;
    read_l2(&file, path).map_err(schema::combine)
}

type Checked<T> = std::result::Result<T, Vec<Error>>;

/// Schema and manifest checks; every error found.
fn check_manifest(which: Schema, m: &Value, name: &Path) -> Checked<()> {
    let mut errors = schema::validate(which, m, name);
    let known: Vec<Option<String>> = errors.iter().map(|e| e.context.field.clone()).collect();
    for e in schema::check_exposure_manifest(View(m), which == Schema::L2Persistence) {
        if !known.contains(&e.context.field) {
            errors.push(e.path(name));
        }
    }
    if errors.is_empty() {
        Ok(())
    } else {
        Err(errors)
    }
}

pub(crate) fn read_l1(file: &hdf5::File, name: &Path) -> Checked<Exposure> {
    let m = schema::manifest(file).map_err(|e| vec![e.path(name)])?;
    check_manifest(Schema::L1Exposure, &m, name)?;
    read_exposure_part(file, View(&m), name, false)
}

pub(crate) fn read_l2(
    file: &hdf5::File,
    name: &Path,
) -> Checked<(Exposure, PersistencePlanes, PersistenceAttrs)> {
    let m = schema::manifest(file).map_err(|e| vec![e.path(name)])?;
    check_manifest(Schema::L2Persistence, &m, name)?;
    let view = View(&m);
    let e = read_exposure_part(file, view, name, true)?;
    let current_e_per_s: ndarray::Array2<f32> =
        dataset(file, "/persistence/current", name).map_err(|e| vec![e])?;
    let flags: ndarray::Array2<u8> =
        dataset(file, "/persistence/flags", name).map_err(|e| vec![e])?;
    let errors = check_persistence_data(&e.flags, &current_e_per_s, &flags);
    let g = |attr: &str| view.group_attr("/persistence", attr);
    let text = |attr: &str| {
        g(attr)
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_owned()
    };
    let number = |attr: &str| g(attr).and_then(Value::as_f64).unwrap_or(f64::NAN);
    let attrs = PersistenceAttrs {
        model_id: text("model_id"),
        model_name: text("model_name"),
        threshold_high_e_per_s: number("threshold_high_e_per_s"),
        threshold_low_e_per_s: number("threshold_low_e_per_s"),
        t_meas_s: number("t_meas_s"),
        previous_exposure_index: g("previous_exposure_index")
            .and_then(Value::as_i64)
            .unwrap_or(-1),
        software_version: text("software_version"),
        processed_utc: text("processed_utc"),
        stats: match (
            g("fraction_above_high").and_then(Value::as_f64),
            g("fraction_above_low").and_then(Value::as_f64),
            g("n_flagged").and_then(Value::as_u64),
        ) {
            (Some(h), Some(l), Some(n)) => Some(FlagStats {
                fraction_above_high: h,
                fraction_above_low: l,
                n_flagged: n,
            }),
            _ => None,
        },
        warmup: match (number("warmup_s"), number("carry_in_bound_e_per_s")) {
            (w, b) if w.is_finite() && b.is_finite() => Some(crate::product::WarmupAttrs {
                warmup_s: w,
                carry_in_bound_e_per_s: b,
            }),
            _ => None,
        },
    };
    let mut errors = errors;
    errors.extend(check_stats(attrs.stats.as_ref(), &flags));
    if errors.is_empty() {
        Ok((
            e,
            PersistencePlanes {
                current_e_per_s,
                flags,
            },
            attrs,
        ))
    } else {
        Err(errors.into_iter().map(|e| e.path(name)).collect())
    }
}

/// Read one dataset with explicit types (the schema has checked dtype and rank).
fn dataset<T: hdf5::H5Type, D: Dimension>(
    file: &hdf5::File,
    path: &str,
    name: &Path,
) -> Result<Array<T, D>> {
    file.dataset(path)
        .and_then(|ds| ds.read::<T, D>())
        .map_err(|e| Error::from(e).field(path).path(name))
}

/// The root attributes of a validated manifest.
fn meta_of(m: View<'_>, name: &Path) -> Checked<ExposureMeta> {
    let missing = |field: &str| vec![Error::invalid(field, "missing or malformed").path(name)];
    let detector = m
        .attr_i64("detector")
        .and_then(DetectorId::new)
        .ok_or_else(|| missing("detector"))?;
    let exposure_index = m
        .attr("exposure_index")
        .and_then(Value::as_u64)
        .ok_or_else(|| missing("exposure_index"))?;
    let t_start_utc = m
        .attr_str("t_start_utc")
        .ok_or_else(|| missing("t_start_utc"))?
        .to_owned();
    let t_start = UtcSeconds::parse(&t_start_utc)
        .map_err(|e| vec![Error::invalid("t_start_utc", e).path(name)])?;
    let t_exposure_s = m
        .attr_f64("t_exposure_s")
        .ok_or_else(|| missing("t_exposure_s"))?;
    let meta = ExposureMeta {
        detector,
        exposure_index,
        t_start_utc,
        t_start,
        t_exposure_s,
        focal_plane_temp_k: m.attr_f64("focal_plane_temp_k"),
        t_illuminated_s: m.attr_f64("t_illuminated_s"),
    };
    Ok(meta)
}

/// The meta data and datasets of an input (or of the input part of an output).
fn read_exposure_part(
    file: &hdf5::File,
    m: View<'_>,
    name: &Path,
    output: bool,
) -> Checked<Exposure> {
    let meta = meta_of(m, name)?;

    let image: ndarray::Array2<f32> = dataset(file, "/image", name).map_err(|e| vec![e])?;
    let flags: ndarray::Array2<u32> = dataset(file, "/flags", name).map_err(|e| vec![e])?;
    let (ramp, ramp_times_s) = if m.has_dataset("/ramp") {
        let r: ndarray::Array3<f32> =
            dataset::<f32, Ix3>(file, "/ramp", name).map_err(|e| vec![e])?;
        let t: ndarray::Array1<f64> =
            dataset::<f64, Ix1>(file, "/ramp_times_s", name).map_err(|e| vec![e])?;
        (Some(r), Some(t))
    } else {
        (None, None)
    };

    let errors = check_exposure_data(&image, &flags, ramp_times_s.as_ref(), output);
    if !errors.is_empty() {
        return Err(errors.into_iter().map(|e| e.path(name)).collect());
    }
    Ok(Exposure {
        meta,
        image,
        flags,
        ramp,
        ramp_times_s,
    })
}

/// Check the layout of a Level-1 product without reading its datasets: schema,
/// manifest checks and the root attributes. Used after writing, when the data were
/// checked in memory ([`check_exposure_data`]) before they were written.
pub(crate) fn check_l1_layout(file: &hdf5::File, name: &Path) -> Checked<ExposureMeta> {
    let m = schema::manifest(file).map_err(|e| vec![e.path(name)])?;
    check_manifest(Schema::L1Exposure, &m, name)?;
    meta_of(View(&m), name)
}

/// [`check_l1_layout`] for an output product.
pub(crate) fn check_l2_layout(file: &hdf5::File, name: &Path) -> Checked<ExposureMeta> {
    let m = schema::manifest(file).map_err(|e| vec![e.path(name)])?;
    check_manifest(Schema::L2Persistence, &m, name)?;
    meta_of(View(&m), name)
}

/// The contiguous elements of a plane (products are read and built in standard layout;
/// anything else is copied once, for the check only).
fn elements<T: Clone>(a: &Array2<T>) -> std::borrow::Cow<'_, [T]> {
    match a.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().cloned().collect()),
    }
}

/// Elements per block of the parallel value checks.
const PAR_CHUNK: usize = 1 << 16;

/// Two counts over `a`, block by block in parallel (each block branch-free), summed.
fn par_count<T: Sync>(
    a: &[T],
    count: impl Fn(&[T]) -> (usize, usize) + Sync + Send,
) -> (usize, usize) {
    use rayon::prelude::*;
    a.par_chunks(PAR_CHUNK)
        .map(&count)
        .reduce(|| (0, 0), |x, y| (x.0 + y.0, x.1 + y.1))
}

/// The value checks of an input (`output`: of the input part of an output product):
/// no +/-Inf in `/image`, at least one finite pixel, no `PERSIST` in an input's
/// `/flags`, `ramp_times_s` finite and strictly increasing. Errors name the field only.
pub(crate) fn check_exposure_data(
    image: &Array2<f32>,
    flags: &Array2<u32>,
    ramp_times_s: Option<&Array1<f64>>,
    output: bool,
) -> Vec<Error> {
    let mut errors = Vec::new();
    let img = elements(image);
    // One branch-free pass for the common case; details only when something is wrong.
    let (infinite, finite) = par_count(&img, |c| {
        c.iter().fold((0usize, 0usize), |(i, f), v| {
            (i + v.is_infinite() as usize, f + v.is_finite() as usize)
        })
    });
    if infinite > 0 {
        let first = image
            .indexed_iter()
            .find(|(_, v)| v.is_infinite())
            .map(|((y, x), _)| format!(" (first at [{y}, {x}])"))
            .unwrap_or_default();
        errors.push(Error::invalid(
            "/image",
            format!("holds +/-Inf at {infinite} pixels{first}; NaN is the only allowed no-value"),
        ));
    } else if finite == 0 {
        errors.push(Error::invalid(
            "/image",
            "NaN plane: no pixel has a finite value",
        ));
    }
    if !output {
        let persist = par_count(&elements(flags), |c| {
            (
                c.iter()
                    .map(|f| (*f & bits::PERSIST != 0) as usize)
                    .sum::<usize>(),
                0,
            )
        })
        .0;
        if persist > 0 {
            errors.push(Error::invalid(
                "/flags",
                format!(
                    "bit 17 (PERSIST) is set at {persist} pixels; upstream never sets it \
                     (is this an output product?)"
                ),
            ));
        }
    }
    if let Some(t) = ramp_times_s {
        if let Some(i) = (0..t.len()).find(|&i| !t[i].is_finite() || (i > 0 && t[i] <= t[i - 1])) {
            errors.push(Error::invalid(
                "/ramp_times_s",
                format!(
                    "must be finite and strictly increasing; element {i} is {}",
                    t[i]
                ),
            ));
        }
    }
    errors
}

/// The value checks of the persistence planes of an output: the predicted current
/// finite and >= 0, no undefined `/persistence/flags` bits, and `PERSIST` in `/flags`
/// exactly where `/persistence/flags` has `HIGH`. Errors name the field only.
/// The per-exposure statistics of `/persistence` are those of its flag plane (exactly:
/// the same counts, the same divisions).
pub(crate) fn check_stats(stats: Option<&FlagStats>, pflags: &Array2<u8>) -> Vec<Error> {
    let Some(st) = stats else {
        return Vec::new();
    };
    let want = FlagStats::of_plane(pflags);
    let mut errors = Vec::new();
    for (field, got, recount) in [
        (
            "fraction_above_high",
            st.fraction_above_high,
            want.fraction_above_high,
        ),
        (
            "fraction_above_low",
            st.fraction_above_low,
            want.fraction_above_low,
        ),
        ("n_flagged", st.n_flagged as f64, want.n_flagged as f64),
    ] {
        if got.to_bits() != recount.to_bits() {
            errors.push(Error::invalid(
                field,
                format!("is {got}, but /persistence/flags gives {recount}"),
            ));
        }
    }
    errors
}

pub(crate) fn check_persistence_data(
    flags: &Array2<u32>,
    current_e_per_s: &Array2<f32>,
    pflags: &Array2<u8>,
) -> Vec<Error> {
    let mut errors = Vec::new();
    let current = elements(current_e_per_s);
    let bad_current = par_count(&current, |c| {
        (
            c.iter()
                .map(|c| !(c.is_finite() && *c >= 0.0) as usize)
                .sum::<usize>(),
            0,
        )
    })
    .0;
    if bad_current > 0 {
        if let Some(bad) = current.iter().find(|c| !(c.is_finite() && **c >= 0.0)) {
            errors.push(Error::invalid(
                "/persistence/current",
                format!("holds {bad}, every predicted current must be finite and >= 0 e-/s"),
            ));
        }
    }
    let defined = pbits::HIGH
        | pbits::LOW
        | pbits::MAX_AMPLITUDE
        | pbits::RELEASED
        | pbits::HISTORY_INCOMPLETE;
    let pf = elements(pflags);
    let undefined = par_count(&pf, |c| {
        (
            (c.iter().fold(0u8, |acc, f| acc | f) & !defined != 0) as usize,
            0,
        )
    })
    .0;
    if undefined > 0 {
        if let Some(bad) = pf.iter().find(|f| **f & !defined != 0) {
            errors.push(Error::invalid(
                "/persistence/flags",
                format!("holds {bad:#04x}: bits 5-7 are not defined by the ICD"),
            ));
        }
    }
    let f = elements(flags);
    let mismatched = if f.len() == pf.len() {
        use rayon::prelude::*;
        f.par_chunks(PAR_CHUNK)
            .zip(pf.par_chunks(PAR_CHUNK))
            .map(|(f, pf)| {
                f.iter()
                    .zip(pf)
                    .map(|(f, p)| ((*f & bits::PERSIST != 0) != (*p & pbits::HIGH != 0)) as usize)
                    .sum::<usize>()
            })
            .sum::<usize>()
    } else {
        f.len().max(pf.len())
    };
    if mismatched > 0 {
        errors.push(Error::invalid(
            "/flags",
            format!(
                "PERSIST (bit 17) differs from bit 0 of /persistence/flags at {mismatched} pixels"
            ),
        ));
    }
    errors
}
