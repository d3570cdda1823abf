//! `persist validate`: recognise what a file is and check it fully.
//!
//! Sits above [`crate::product`], [`crate::checkpoint`] and [`crate::model_file`] (it
//! dispatches to each), so that none of those needs to know the others: checkpoints
//! reuse the product schema checks, and products know nothing of checkpoints.

use crate::error::Error;
use crate::h5io;
use crate::product::schema::{self, View};
use crate::product::{exposure, read};
use crate::{checkpoint, model_file};
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
        return model_file::check(path).map(|_| ProductKind::Model);
    }
    let file = h5io::open(path).map_err(|e| vec![e])?;
    let m = schema::manifest(&file).map_err(|e| vec![e.path(path)])?;
    let view = View(&m);
    match view.attr_str("product") {
        Some(exposure::PRODUCT_L1) if view.has_group("/persistence") => {
            read::read_l2(&file, path).map(|_| ProductKind::L2Persistence)
        }
        Some(exposure::PRODUCT_L1) => read::read_l1(&file, path).map(|_| ProductKind::L1Exposure),
        Some(checkpoint::PRODUCT) => {
            checkpoint::check_file(&file, path).map(|_| ProductKind::Checkpoint)
        }
        Some(other) => Err(vec![Error::invalid(
            "product",
            format!(
                "`{other}` is not a known product (expected `{}` or `{}`)",
                exposure::PRODUCT_L1,
                checkpoint::PRODUCT
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
