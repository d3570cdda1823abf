//! Level-1 input and persistence output products (ICD), in memory, in HDF5 and in
//! SPHEREx's FITS layout ([`fits`]).
//!
//! This is the only code that knows the product layouts, and [`mod@format`] the only place
//! that chooses between them (by a file's content): the stage asks it for the next
//! exposure and hands it the output. Files are checked against the JSON Schemas of
//! `schemas/` through a manifest of their layout ([`schema`]), then against what a
//! schema cannot express ([`read`]).
//!
//! Layering: `product` depends on nothing above it; [`crate::checkpoint`] reuses its
//! schema checks, and [`crate::validate`] recognises any file (product, checkpoint or
//! model file).

pub mod exposure;
pub mod fits;
pub mod format;
pub mod read;
pub mod schema;
pub mod synthetic;
pub mod write;

pub use exposure::{
    Exposure, ExposureMeta, FlagStats, PersistenceAttrs, PersistencePlanes, WarmupAttrs,
};
pub use read::{read_exposure, read_output};
pub use write::{write_exposure, write_output};
