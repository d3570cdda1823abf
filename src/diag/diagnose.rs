//! `persist diagnose`: which library effect is missing from a fitted model.
use crate::error::{Error, ErrorKind, Result};
use std::path::Path;

pub fn run(
    _input: &Path,
    _model: &Path,
    _json: Option<&Path>,
    _bootstrap: usize,
    _seed: u64,
) -> Result<String> {
    Err(Error::new(
        ErrorKind::Usage,
        "diagnose: not implemented yet",
    ))
}
