//! Level-1 input and persistence output products (ICD), in memory and in HDF5.
//!
//! This is the only code that knows the HDF5 layout of the ICD. Files are checked
//! against the JSON Schemas of `schemas/` through a manifest of their layout
//! ([`schema`]), then against what a schema cannot express ([`read`]).

pub mod exposure;
pub mod read;
pub mod schema;
pub mod synthetic;
pub mod write;

pub use exposure::{Exposure, ExposureMeta, PersistenceAttrs, PersistencePlanes};
pub use read::{read_exposure, read_output};
pub use write::{write_exposure, write_output};

use crate::error::Error;
use crate::h5io;
use schema::View;
use std::fmt;
use std::path::Path;

/// What a file is, as [`validate_path`] recognises it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ProductKind {
    /// `product = spherex.l1.exposure` without `/persistence`.
    L1Exposure,
    /// `product = spherex.l1.exposure` with `/persistence`.
    L2Persistence,
    /// `product = persist.checkpoint`.
    Checkpoint,
    /// A `.json` path: a model file.
    Model,
}

impl ProductKind {
    pub fn name(self) -> &'static str {
        match self {
            ProductKind::L1Exposure => "l1_exposure",
            ProductKind::L2Persistence => "l2_persistence",
            ProductKind::Checkpoint => "checkpoint",
            ProductKind::Model => "model",
        }
    }
}

impl fmt::Display for ProductKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Recognise a file's kind (a `.json` path is a model file; otherwise the root
/// attribute `product`, and the presence of `/persistence`) and validate it fully:
/// schema, manifest checks, data checks. Returns every error found, each naming the
/// file and the field.
pub fn validate_path(path: &Path) -> Result<ProductKind, Vec<Error>> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
    {
        return crate::model_file::check(path).map(|_| ProductKind::Model);
    }
    let file = h5io::open(path).map_err(|e| vec![e])?;
    let m = schema::manifest(&file).map_err(|e| vec![e.path(path)])?;
    let view = View(&m);
    match view.attr_str("product") {
        Some(exposure::PRODUCT_L1) if view.has_group("/persistence") => {
            read::read_l2(&file, path).map(|_| ProductKind::L2Persistence)
        }
        Some(exposure::PRODUCT_L1) => read::read_l1(&file, path).map(|_| ProductKind::L1Exposure),
        Some(crate::checkpoint::PRODUCT) => {
            crate::checkpoint::check_file(&file, path).map(|_| ProductKind::Checkpoint)
        }
        Some(other) => Err(vec![Error::invalid(
            "product",
            format!(
                "`{other}` is not a known product (expected `{}` or `{}`)",
                exposure::PRODUCT_L1,
                crate::checkpoint::PRODUCT
            ),
        )
        .path(path)]),
        None => Err(vec![Error::invalid(
            "product",
            "missing or not a string: cannot tell what this file is",
        )
        .path(path)]),
    }
}
