//! HDF5 layout -> JSON manifest -> JSON Schema validation, with errors that name the
//! file, the field and the reason.
//!
//! A JSON Schema cannot look inside an HDF5 file, so every HDF5 file (products and
//! checkpoints) is first described by a JSON **manifest** of its layout, and the
//! schemas in `schemas/` validate that manifest. The manifest of a file is:
//!
//! ```json
//! {
//!   "attributes": {                         // attributes of the root group, by name
//!     "detector":    {"type": "integer", "dtype": "int64",  "shape": [], "value": 3},
//!     "t_start_utc": {"type": "string",  "dtype": "string", "shape": [], "value": "2026-03-01T00:02:31.500000Z"},
//!     "t_meas_s":    {"type": "float",   "dtype": "float64","shape": [], "value": "NaN"}
//!   },
//!   "datasets": {                           // every dataset, by absolute path
//!     "/image": {"dtype": "float32", "shape": [64, 64], "attributes": {}}
//!   },
//!   "groups": {                             // every group but the root, by absolute path
//!     "/persistence": {"attributes": {"model_id": {"type": "string", ...}}}
//!   },
//!   "links": {"/alias": "soft"}             // links not followed: soft, external, datatype
//! }
//! ```
//!
//! - `type` is the HDF5 type class: `integer` (signed or unsigned), `float`, `string`
//!   (fixed or variable length, ASCII or UTF-8), `enum` (booleans too), `compound`,
//!   `array`, `vlen`, `reference`, `other`.
//! - `dtype` is the exact type: `int8`..`int64`, `uint8`..`uint64`, `float32`,
//!   `float64`, `string`, `bool`, or the class name for the others.
//! - `shape` is the dataspace, `[]` for a scalar, slowest axis first.
//! - `value` is given for scalar integer, float and string attributes, else `null`.
//!   Non-finite floats, which JSON cannot hold, are the strings `"NaN"`, `"Infinity"`
//!   and `"-Infinity"` (so a schema asking for a number refuses them).
//! - Keys are sorted (serde_json maps), so the manifest of a file does not depend on
//!   the HDF5 version's iteration order. At most [`MAX_OBJECTS`] objects and
//!   [`MAX_DEPTH`] levels of groups are described: anything larger is not an ICD file.
//!
//! Building the manifest reads attributes and dataset headers only, never dataset data:
//! absurd dimensions are refused from it before any data is read.
//!
//! **Field names in errors**: a root attribute by its name (`t_exposure_s`), a dataset
//! or group by its absolute path (`/image`), an attribute of a group or dataset as
//! `PATH@NAME` (`/persistence@model_id`). For model files (plain JSON), the JSON
//! pointer of the offending value (`/terms/2/rate_per_s`).
//!
//! Each schema is compiled once per process ([`OnceLock`]).

use crate::error::{Error, ErrorKind, Result};
use crate::units::UtcSeconds;
use hdf5::types::{FloatSize, IntSize, TypeDescriptor as TD};
use serde_json::{json, Map, Value};
use std::path::Path;
use std::sync::OnceLock;

/// Most objects (datasets, groups, links) a manifest describes.
pub const MAX_OBJECTS: usize = 1024;
/// Deepest group nesting a manifest follows.
pub const MAX_DEPTH: usize = 8;

/// The schemas of `schemas/`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Schema {
    L1Exposure,
    L2Persistence,
    Checkpoint,
    Model,
    PixelMap,
}

const SCHEMAS: [Schema; 5] = [
    Schema::L1Exposure,
    Schema::L2Persistence,
    Schema::Checkpoint,
    Schema::Model,
    Schema::PixelMap,
];

static COMPILED: [OnceLock<std::result::Result<jsonschema::Validator, String>>; 5] =
    [const { OnceLock::new() }; 5];

impl Schema {
    pub fn all() -> [Schema; 5] {
        SCHEMAS
    }

    /// The schema's text, as committed in `schemas/`.
    pub fn text(self) -> &'static str {
        match self {
            Schema::L1Exposure => include_str!("../../schemas/l1_exposure.schema.json"),
            Schema::L2Persistence => include_str!("../../schemas/l2_persistence.schema.json"),
            Schema::Checkpoint => include_str!("../../schemas/checkpoint.schema.json"),
            Schema::Model => include_str!("../../schemas/model.schema.json"),
            Schema::PixelMap => include_str!("../../schemas/pixel_map.schema.json"),
        }
    }

    pub fn file_name(self) -> &'static str {
        match self {
            Schema::L1Exposure => "l1_exposure.schema.json",
            Schema::L2Persistence => "l2_persistence.schema.json",
            Schema::Checkpoint => "checkpoint.schema.json",
            Schema::Model => "model.schema.json",
            Schema::PixelMap => "pixel_map.schema.json",
        }
    }

    /// What the schema describes, for messages.
    pub fn what(self) -> &'static str {
        match self {
            Schema::L1Exposure => "a Level-1 input product",
            Schema::L2Persistence => "an output product",
            Schema::Checkpoint => "a checkpoint",
            Schema::Model => "a model file",
            Schema::PixelMap => "a per-pixel response map",
        }
    }

    fn index(self) -> usize {
        match self {
            Schema::L1Exposure => 0,
            Schema::L2Persistence => 1,
            Schema::Checkpoint => 2,
            Schema::Model => 3,
            Schema::PixelMap => 4,
        }
    }

    /// The compiled validator (compiled on first use, once per process).
    pub fn validator(self) -> Result<&'static jsonschema::Validator> {
        let compiled = COMPILED[self.index()].get_or_init(|| {
            let schema: Value = serde_json::from_str(self.text()).map_err(|e| e.to_string())?;
            jsonschema::draft202012::options()
                .should_validate_formats(true)
                .build(&schema)
                .map_err(|e| e.to_string())
        });
        compiled.as_ref().map_err(|e| {
            Error::invalid(
                self.file_name(),
                format!("the embedded schema does not compile: {e}"),
            )
        })
    }
}

// ---------------------------------------------------------------------------------------
// Manifest

/// Describe the layout of an HDF5 file as JSON (module docs). Reads no dataset data.
pub fn manifest(file: &hdf5::File) -> Result<Value> {
    let mut out = Out {
        datasets: Map::new(),
        groups: Map::new(),
        links: Map::new(),
        objects: 0,
    };
    let attributes = attributes(file, "")?;
    walk(file, "", 0, &mut out)?;
    Ok(json!({
        "attributes": attributes,
        "datasets": out.datasets,
        "groups": out.groups,
        "links": out.links,
    }))
}

struct Out {
    datasets: Map<String, Value>,
    groups: Map<String, Value>,
    links: Map<String, Value>,
    objects: usize,
}

fn walk(group: &hdf5::Group, path: &str, depth: usize, out: &mut Out) -> Result<()> {
    let here = if path.is_empty() { "/" } else { path };
    let links = group
        .links(hdf5::IndexType::Name, hdf5::IterationOrder::Increasing)
        .map_err(|e| Error::from(e).field(here))?;
    for (name, info) in links {
        let full = format!("{path}/{name}");
        out.objects += 1;
        if out.objects > MAX_OBJECTS {
            return Err(Error::invalid(
                here,
                format!("more than {MAX_OBJECTS} objects: not a product of the ICD"),
            ));
        }
        let h5 = |e: hdf5::Error| Error::from(e).field(full.clone());
        match info.link_type {
            hdf5::LinkType::Hard => {
                match group.loc_type_by_name(&name).map_err(h5)? {
                    hdf5::LocationType::Group => {
                        let g = group.group(&name).map_err(h5)?;
                        let attrs = attributes(&g, &full)?;
                        out.groups
                            .insert(full.clone(), json!({ "attributes": attrs }));
                        if depth + 1 >= MAX_DEPTH {
                            return Err(Error::invalid(
                            full,
                            format!("groups nested deeper than {MAX_DEPTH}: not a product of the ICD"),
                        ));
                        }
                        walk(&g, &full, depth + 1, out)?;
                    }
                    hdf5::LocationType::Dataset => {
                        let ds = group.dataset(&name).map_err(h5)?;
                        let (_, dtype) = type_names(ds.dtype().map_err(h5)?.to_descriptor().ok());
                        let shape = ds.get_shape().map_err(h5)?;
                        let attrs = attributes(&ds, &full)?;
                        out.datasets.insert(
                            full,
                            json!({ "dtype": dtype, "shape": shape, "attributes": attrs }),
                        );
                    }
                    _ => {
                        out.links.insert(full, json!("datatype"));
                    }
                }
            }
            hdf5::LinkType::Soft => {
                out.links.insert(full, json!("soft"));
            }
            hdf5::LinkType::External => {
                out.links.insert(full, json!("external"));
            }
        }
    }
    Ok(())
}

fn attributes(loc: &hdf5::Location, owner: &str) -> Result<Map<String, Value>> {
    let field = |name: &str| {
        if owner.is_empty() {
            name.to_owned()
        } else {
            format!("{owner}@{name}")
        }
    };
    let names = loc
        .attr_names()
        .map_err(|e| Error::from(e).field(if owner.is_empty() { "/" } else { owner }))?;
    let mut map = Map::new();
    for name in names {
        let described = loc.attr(&name).and_then(|a| describe_attr(&a));
        let v = described.map_err(|e| Error::from(e).field(field(&name)))?;
        map.insert(name, v);
    }
    Ok(map)
}

fn describe_attr(a: &hdf5::Attribute) -> hdf5::Result<Value> {
    let td = a.dtype()?.to_descriptor().ok();
    let shape = a.get_shape()?;
    let (class, dtype) = type_names(td.clone());
    let value = match (&td, shape.is_empty()) {
        (Some(td), true) => scalar_value(a, td)?,
        _ => Value::Null,
    };
    Ok(json!({ "type": class, "dtype": dtype, "shape": shape, "value": value }))
}

/// HDF5 type class and exact type name.
fn type_names(td: Option<TD>) -> (&'static str, String) {
    let bits = |n: usize| n * 8;
    match td {
        Some(TD::Integer(s)) => ("integer", format!("int{}", bits(int_bytes(s)))),
        Some(TD::Unsigned(s)) => ("integer", format!("uint{}", bits(int_bytes(s)))),
        Some(TD::Float(s)) => ("float", format!("float{}", bits(float_bytes(s)))),
        Some(TD::Boolean) => ("enum", "bool".into()),
        Some(TD::Enum(_)) => ("enum", "enum".into()),
        Some(TD::Compound(_)) => ("compound", "compound".into()),
        Some(TD::FixedArray(..)) => ("array", "array".into()),
        Some(TD::FixedAscii(_) | TD::FixedUnicode(_) | TD::VarLenAscii | TD::VarLenUnicode) => {
            ("string", "string".into())
        }
        Some(TD::VarLenArray(_)) => ("vlen", "vlen".into()),
        Some(TD::Reference(_)) => ("reference", "reference".into()),
        None => ("other", "other".into()),
    }
}

fn int_bytes(s: IntSize) -> usize {
    match s {
        IntSize::U1 => 1,
        IntSize::U2 => 2,
        IntSize::U4 => 4,
        IntSize::U8 => 8,
    }
}

#[allow(unreachable_patterns)]
fn float_bytes(s: FloatSize) -> usize {
    match s {
        FloatSize::U4 => 4,
        FloatSize::U8 => 8,
        _ => 2,
    }
}

/// Longest fixed-length string attribute whose value is read.
const MAX_FIXED_STRING: usize = 4096;

fn scalar_value(a: &hdf5::Attribute, td: &TD) -> hdf5::Result<Value> {
    use hdf5::types::{FixedAscii, FixedUnicode, VarLenAscii, VarLenUnicode};
    Ok(match td {
        TD::Integer(_) => json!(a.read_scalar::<i64>()?),
        TD::Unsigned(_) => json!(a.read_scalar::<u64>()?),
        TD::Float(_) => float_value(a.read_scalar::<f64>()?),
        TD::VarLenUnicode => json!(a.read_scalar::<VarLenUnicode>()?.as_str()),
        TD::VarLenAscii => json!(a.read_scalar::<VarLenAscii>()?.as_str()),
        TD::FixedAscii(n) if *n <= MAX_FIXED_STRING => {
            json!(a.read_scalar::<FixedAscii<MAX_FIXED_STRING>>()?.as_str())
        }
        TD::FixedUnicode(n) if *n <= MAX_FIXED_STRING => {
            json!(a.read_scalar::<FixedUnicode<MAX_FIXED_STRING>>()?.as_str())
        }
        _ => Value::Null,
    })
}

/// A float as JSON; non-finite values as strings (module docs).
pub fn float_value(x: f64) -> Value {
    if x.is_finite() {
        json!(x)
    } else if x.is_nan() {
        json!("NaN")
    } else if x > 0.0 {
        json!("Infinity")
    } else {
        json!("-Infinity")
    }
}

// ---------------------------------------------------------------------------------------
// Validation

/// Validate `instance` (a manifest, or a model file's JSON) against `schema`. Every
/// schema error becomes one [`Error`] naming `file`, the field and the reason (at most
/// one per field, the most basic first: type before shape before value). Kind
/// [`ErrorKind::Invalid`], or [`ErrorKind::Model`] for model files.
pub fn validate(schema: Schema, instance: &Value, file: &Path) -> Vec<Error> {
    let validator = match schema.validator() {
        Ok(v) => v,
        Err(e) => return vec![e.path(file)],
    };
    let mut found: Vec<(String, u8, String)> = Vec::new();
    for err in validator.iter_errors(instance) {
        let segs: Vec<String> = err.instance_path().iter().map(|s| s.to_string()).collect();
        for (field, rank, message) in describe(schema, &segs, &err, instance) {
            match found.iter_mut().find(|(f, _, _)| *f == field) {
                Some(slot) if rank < slot.1 => *slot = (field, rank, message),
                Some(_) => {}
                None => found.push((field, rank, message)),
            }
        }
    }
    let kind = if schema == Schema::Model {
        ErrorKind::Model
    } else {
        ErrorKind::Invalid
    };
    found
        .into_iter()
        .map(|(field, _, message)| Error::new(kind, message).field(field).path(file))
        .collect()
}

/// (field, rank, message) for one schema error; rank orders errors of one field.
fn describe(
    schema: Schema,
    segs: &[String],
    err: &jsonschema::ValidationError<'_>,
    root: &Value,
) -> Vec<(String, u8, String)> {
    use jsonschema::error::ValidationErrorKind as K;
    let inst = err.instance();
    let what = schema.what();
    // `additionalProperties: false` with no `properties` is reported as a false schema
    // at the object, naming only its first member: name every member instead.
    let parent = root.pointer(err.instance_path().as_str());
    let unexpected: Option<Vec<String>> = match err.kind() {
        K::AdditionalProperties { unexpected } => Some(unexpected.clone()),
        K::FalseSchema => parent
            .and_then(Value::as_object)
            .map(|o| o.keys().cloned().collect()),
        _ => None,
    };
    if schema == Schema::Model {
        let pointer = |extra: Option<&str>| {
            let mut p: String = segs.iter().map(|s| format!("/{s}")).collect();
            if let Some(x) = extra {
                p.push('/');
                p.push_str(x);
            }
            if p.is_empty() {
                p.push('/');
            }
            p
        };
        return match err.kind() {
            K::Required { property } => {
                let name = property.as_str().unwrap_or_default();
                vec![(pointer(Some(name)), 0, "missing required field".into())]
            }
            _ if unexpected.is_some() => unexpected
                .unwrap_or_default()
                .iter()
                .map(|u| (pointer(Some(u)), 0, format!("unknown field in {what}")))
                .collect(),
            _ => vec![(pointer(None), 1, err.to_string())],
        };
    }
    let s: Vec<&str> = segs.iter().map(String::as_str).collect();
    let noun = |section: &str| match section {
        "attributes" => "attribute",
        "datasets" => "dataset",
        "groups" => "group",
        _ => "link",
    };
    match (s.as_slice(), err.kind()) {
        // Missing or unexpected members of a section.
        ([section], K::Required { property }) => {
            let name = property.as_str().unwrap_or_default().to_owned();
            vec![(name, 0, format!("missing required {}", noun(section)))]
        }
        ([section], _) if unexpected.is_some() => unexpected
            .unwrap_or_default()
            .iter()
            .map(|u| {
                let reason = if *section == "links" {
                    let kind = parent
                        .and_then(|p| p.get(u))
                        .and_then(Value::as_str)
                        .unwrap_or("link");
                    format!("{kind} link: not allowed in {what}")
                } else {
                    format!("{} not defined by the ICD for {what}", noun(section))
                };
                (u.clone(), 0, reason)
            })
            .collect(),
        // Attributes of groups and datasets.
        (["groups" | "datasets", owner, "attributes"], K::Required { property }) => {
            let name = property.as_str().unwrap_or_default();
            vec![(
                format!("{owner}@{name}"),
                0,
                "missing required attribute".into(),
            )]
        }
        (["groups" | "datasets", owner, "attributes"], _) if unexpected.is_some() => unexpected
            .unwrap_or_default()
            .iter()
            .map(|u| {
                let r = format!("attribute not defined by the ICD for {what}");
                (format!("{owner}@{u}"), 0, r)
            })
            .collect(),
        (["groups", owner, "attributes", name, rest @ ..], kind) => {
            let (rank, m) = attr_message(rest, kind, inst, err);
            vec![(format!("{owner}@{name}"), rank, m)]
        }
        (["attributes", name, rest @ ..], kind) => {
            let (rank, m) = attr_message(rest, kind, inst, err);
            vec![((*name).to_owned(), rank, m)]
        }
        (["datasets", path, "dtype"], K::Constant { expected_value }) => vec![(
            (*path).to_owned(),
            0,
            format!("dtype is {inst}, the ICD requires {expected_value}"),
        )],
        (["datasets", path, "shape", ..], K::MinItems { limit } | K::MaxItems { limit }) => {
            vec![(
                (*path).to_owned(),
                1,
                format!("has shape {inst}, the ICD requires {limit} axes"),
            )]
        }
        ([section, path, ..], _) if *section == "datasets" || *section == "groups" => {
            vec![((*path).to_owned(), 2, err.to_string())]
        }
        _ => {
            let field = s.last().copied().unwrap_or("/").to_owned();
            vec![(field, 2, err.to_string())]
        }
    }
}

fn attr_message(
    rest: &[&str],
    kind: &jsonschema::error::ValidationErrorKind,
    inst: &Value,
    err: &jsonschema::ValidationError<'_>,
) -> (u8, String) {
    use jsonschema::error::ValidationErrorKind as K;
    match (rest, kind) {
        (["type"], K::Constant { expected_value }) => (
            0,
            format!("has HDF5 type {inst}, the ICD requires {expected_value}"),
        ),
        (["shape", ..], _) => (1, format!("must be a scalar attribute, has shape {inst}")),
        (["value"], K::Constant { expected_value }) => {
            (2, format!("is {inst}, must be {expected_value}"))
        }
        (["value"], K::Format { format }) => (2, format!("{inst} is not a valid {format}")),
        (["value"], K::Type { .. }) if inst.is_string() => {
            (2, format!("is {inst}, must be a finite number"))
        }
        (["value"], _) => (2, format!("value {inst}: {err}")),
        _ => (2, err.to_string()),
    }
}

// ---------------------------------------------------------------------------------------
// Checks on the manifest that the schemas cannot express

/// Read-only accessors into a manifest; every accessor tolerates a malformed manifest
/// (the schema reports that), returning `None`.
#[derive(Debug, Clone, Copy)]
pub struct View<'a>(pub &'a Value);

impl<'a> View<'a> {
    /// Value of a root attribute.
    pub fn attr(&self, name: &str) -> Option<&'a Value> {
        self.0.get("attributes")?.get(name)?.get("value")
    }

    pub fn attr_str(&self, name: &str) -> Option<&'a str> {
        self.attr(name)?.as_str()
    }

    pub fn attr_f64(&self, name: &str) -> Option<f64> {
        self.attr(name)?.as_f64()
    }

    pub fn attr_i64(&self, name: &str) -> Option<i64> {
        self.attr(name)?.as_i64()
    }

    /// Value of an attribute of group `group`.
    pub fn group_attr(&self, group: &str, name: &str) -> Option<&'a Value> {
        self.0
            .get("groups")?
            .get(group)?
            .get("attributes")?
            .get(name)?
            .get("value")
    }

    pub fn has_group(&self, group: &str) -> bool {
        self.0.get("groups").and_then(|g| g.get(group)).is_some()
    }

    pub fn has_dataset(&self, path: &str) -> bool {
        self.0.get("datasets").and_then(|d| d.get(path)).is_some()
    }

    /// Shape of a dataset.
    pub fn shape(&self, path: &str) -> Option<Vec<usize>> {
        self.0
            .get("datasets")?
            .get(path)?
            .get("shape")?
            .as_array()?
            .iter()
            .map(|n| n.as_u64().and_then(|n| usize::try_from(n).ok()))
            .collect()
    }

    /// Every dataset path with its shape.
    pub fn datasets(&self) -> Vec<(String, Vec<usize>)> {
        let Some(map) = self.0.get("datasets").and_then(Value::as_object) else {
            return Vec::new();
        };
        map.keys()
            .filter_map(|k| Some((k.clone(), self.shape(k)?)))
            .collect()
    }
}

/// Every dataset's axes in 1..=[`crate::h5io::MAX_AXIS`]: refused from the manifest, before any data
/// is read.
pub fn check_dimensions(m: View<'_>) -> Vec<Error> {
    m.datasets()
        .into_iter()
        .filter_map(|(path, shape)| crate::h5io::check_axes(&path, &shape).err())
        .collect()
}

/// Checks of a Level-1 input or an output product the schema cannot express, on the
/// manifest only: dimensions, shape agreement, ramp length, `t_start_utc` parsing,
/// `t_illuminated_s <= t_exposure_s`, output planes' shapes and thresholds.
pub fn check_exposure_manifest(m: View<'_>, output: bool) -> Vec<Error> {
    let mut errors = check_dimensions(m);
    let image = m.shape("/image");
    if let (Some(image), Some(flags)) = (&image, m.shape("/flags")) {
        if *image != flags {
            errors.push(Error::invalid(
                "/flags",
                format!("shape {flags:?} differs from /image {image:?}"),
            ));
        }
    }
    if let (Some(image), Some(ramp)) = (&image, m.shape("/ramp")) {
        if ramp.len() != 3 || ramp[1..] != image[..] {
            errors.push(Error::invalid(
                "/ramp",
                format!("shape {ramp:?} is not [nsamp, ny, nx] with [ny, nx] = /image {image:?}"),
            ));
        }
        if let Some(times) = m.shape("/ramp_times_s") {
            if ramp.first() != times.first() {
                errors.push(Error::invalid(
                    "/ramp_times_s",
                    format!(
                        "{} sample times for {} ramp samples",
                        times.first().copied().unwrap_or(0),
                        ramp.first().copied().unwrap_or(0)
                    ),
                ));
            }
        }
    }
    if let Some(t) = m.attr_str("t_start_utc") {
        if let Err(e) = UtcSeconds::parse(t) {
            errors.push(Error::invalid("t_start_utc", e));
        }
    }
    if let (Some(ti), Some(te)) = (m.attr_f64("t_illuminated_s"), m.attr_f64("t_exposure_s")) {
        if !(ti > 0.0 && ti <= te) {
            errors.push(Error::invalid(
                "t_illuminated_s",
                format!("is {ti} s, must be in (0, t_exposure_s = {te} s]"),
            ));
        }
    }
    if output {
        for plane in ["/persistence/current", "/persistence/flags"] {
            if let (Some(image), Some(s)) = (&image, m.shape(plane)) {
                if *image != s {
                    errors.push(Error::invalid(
                        plane,
                        format!("shape {s:?} differs from /image {image:?}"),
                    ));
                }
            }
        }
        let hi = m
            .group_attr("/persistence", "threshold_high_e_per_s")
            .and_then(Value::as_f64);
        let lo = m
            .group_attr("/persistence", "threshold_low_e_per_s")
            .and_then(Value::as_f64);
        if let (Some(hi), Some(lo)) = (hi, lo) {
            if lo > hi {
                errors.push(Error::invalid(
                    "/persistence@threshold_low_e_per_s",
                    format!("is {lo} e-/s, above the high threshold {hi} e-/s"),
                ));
            }
        }
    }
    errors
}

/// Merge errors of one file: one error as is; several as one whose field lists every
/// field and whose message gives every reason.
pub fn combine(mut errors: Vec<Error>) -> Error {
    if errors.len() == 1 {
        if let Some(e) = errors.pop() {
            return e;
        }
    }
    if errors.is_empty() {
        return Error::new(ErrorKind::Invalid, "invalid (no reason recorded)");
    }
    let kind = errors[0].kind;
    let path = errors[0].context.path.clone();
    let fields: Vec<String> = errors
        .iter()
        .map(|e| e.context.field.clone().unwrap_or_else(|| "?".into()))
        .collect();
    let reasons: Vec<String> = errors
        .iter()
        .zip(&fields)
        .map(|(e, f)| format!("`{f}`: {}", e.message))
        .collect();
    let mut e = Error::new(
        kind,
        format!("{} problems: {}", errors.len(), reasons.join("; ")),
    )
    .field(fields.join(", "));
    e.context.path = path;
    e
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_schema_compiles() {
        for s in Schema::all() {
            s.validator().unwrap();
            let v: Value = serde_json::from_str(s.text()).unwrap();
            assert!(v["$id"].as_str().unwrap().ends_with(s.file_name()));
            assert!(v["title"].is_string() && v["description"].is_string());
        }
    }

    /// Every property defined has a description, except overlays refining a `$ref`.
    #[test]
    fn every_property_is_described() {
        fn visit(v: &Value, at: &str, missing: &mut Vec<String>) {
            match v {
                Value::Object(o) => {
                    if let Some(Value::Object(props)) = o.get("properties") {
                        let refines = o.contains_key("$ref") || o.contains_key("allOf");
                        for (k, p) in props {
                            if !refines && p.get("description").is_none() {
                                missing.push(format!("{at}/properties/{k}"));
                            }
                        }
                    }
                    for (k, c) in o {
                        visit(c, &format!("{at}/{k}"), missing);
                    }
                }
                Value::Array(a) => {
                    for (i, c) in a.iter().enumerate() {
                        visit(c, &format!("{at}/{i}"), missing);
                    }
                }
                _ => {}
            }
        }
        for s in Schema::all() {
            let v: Value = serde_json::from_str(s.text()).unwrap();
            let mut missing = Vec::new();
            visit(&v, s.file_name(), &mut missing);
            assert!(missing.is_empty(), "no description: {missing:?}");
        }
    }

    /// The output schema carries the input's definitions unchanged (no drift).
    #[test]
    fn output_schema_extends_input_schema() {
        let l1: Value = serde_json::from_str(Schema::L1Exposure.text()).unwrap();
        let l2: Value = serde_json::from_str(Schema::L2Persistence.text()).unwrap();
        let ck: Value = serde_json::from_str(Schema::Checkpoint.text()).unwrap();
        assert_eq!(l1["$defs"], l2["$defs"]);
        assert_eq!(l1["$defs"], ck["$defs"]);
        assert_eq!(
            l1["properties"]["attributes"],
            l2["properties"]["attributes"]
        );
        for (k, v) in l1["properties"]["datasets"]["properties"]
            .as_object()
            .unwrap()
        {
            if k != "/flags" {
                assert_eq!(&l2["properties"]["datasets"]["properties"][k], v, "{k}");
            }
        }
    }

    fn attr(t: &str, dtype: &str, value: Value) -> Value {
        json!({"type": t, "dtype": dtype, "shape": [], "value": value})
    }

    fn good_l1() -> Value {
        json!({
            "attributes": {
                "product": attr("string", "string", json!("spherex.l1.exposure")),
                "schema_version": attr("string", "string", json!("1.0")),
                "detector": attr("integer", "int64", json!(3)),
                "exposure_index": attr("integer", "int64", json!(12)),
                "t_start_utc": attr("string", "string", json!("2026-03-01T00:02:31.500000Z")),
                "t_exposure_s": attr("float", "float64", json!(112.0)),
            },
            "datasets": {
                "/image": {"dtype": "float32", "shape": [8, 8], "attributes": {}},
                "/flags": {"dtype": "uint32", "shape": [8, 8], "attributes": {}},
            },
            "groups": {},
            "links": {},
        })
    }

    fn fields(errors: &[Error]) -> Vec<String> {
        errors
            .iter()
            .map(|e| e.context.field.clone().unwrap())
            .collect()
    }

    #[test]
    fn good_manifest_passes() {
        let p = Path::new("x.h5");
        assert!(validate(Schema::L1Exposure, &good_l1(), p).is_empty());
        assert!(check_exposure_manifest(View(&good_l1()), false).is_empty());
    }

    #[test]
    fn schema_errors_name_fields() {
        let p = Path::new("/in/x.h5");
        let mut m = good_l1();
        m["attributes"]
            .as_object_mut()
            .unwrap()
            .remove("t_exposure_s");
        m["attributes"]["detector"] = attr("string", "string", json!("3"));
        m["datasets"]["/image"]["dtype"] = json!("float64");
        m["datasets"]["/extra"] = json!({"dtype": "uint8", "shape": [1], "attributes": {}});
        m["attributes"]["t_start_utc"]["value"] = json!("yesterday");
        let errors = validate(Schema::L1Exposure, &m, p);
        let f = fields(&errors);
        for want in [
            "t_exposure_s",
            "detector",
            "/image",
            "/extra",
            "t_start_utc",
        ] {
            assert!(f.contains(&want.to_string()), "{want} not in {f:?}");
        }
        assert_eq!(f.len(), 5, "{errors:?}");
        let det = errors
            .iter()
            .find(|e| e.context.field.as_deref() == Some("detector"))
            .unwrap();
        assert!(det
            .to_string()
            .starts_with("/in/x.h5: field `detector`: has HDF5 type"));
        assert!(det.message.contains("integer"), "{det}");
        let img = errors
            .iter()
            .find(|e| e.context.field.as_deref() == Some("/image"))
            .unwrap();
        assert!(img.message.contains("float64") && img.message.contains("float32"));
    }

    #[test]
    fn non_finite_float_refused() {
        let mut m = good_l1();
        m["attributes"]["t_exposure_s"]["value"] = float_value(f64::INFINITY);
        let e = validate(Schema::L1Exposure, &m, Path::new("x.h5"));
        assert_eq!(fields(&e), ["t_exposure_s"]);
        assert!(e[0].message.contains("finite"), "{}", e[0]);
    }

    #[test]
    fn semantic_manifest_checks() {
        let mut m = good_l1();
        m["datasets"]["/flags"]["shape"] = json!([8, 9]);
        m["attributes"]["t_illuminated_s"] = attr("float", "float64", json!(200.0));
        m["datasets"]["/image"]["shape"] = json!([0, 8]);
        let e = check_exposure_manifest(View(&m), false);
        let f = fields(&e);
        assert_eq!(f, ["/image", "/flags", "t_illuminated_s"], "{e:?}");
        assert!(e[0].message.contains("absurd"));
    }

    #[test]
    fn absurd_total_size_refused_from_manifest() {
        let mut m = good_l1();
        m["datasets"]["/ramp"] =
            json!({"dtype": "float32", "shape": [8192, 8192, 8192], "attributes": {}});
        let e = check_dimensions(View(&m));
        assert_eq!(fields(&e), ["/ramp"]);
        assert!(e[0].message.contains("elements"), "{}", e[0]);
    }

    #[test]
    fn combine_names_every_field() {
        let e = combine(vec![
            Error::invalid("a", "bad a").path("f.h5"),
            Error::invalid("b", "bad b").path("f.h5"),
        ]);
        let s = e.to_string();
        assert!(s.starts_with("f.h5: field `a, b`: 2 problems"), "{s}");
        assert!(s.contains("`a`: bad a") && s.contains("`b`: bad b"));
    }
}
