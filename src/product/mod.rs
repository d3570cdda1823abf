//! Level-1 input and persistence output products (ICD), in memory and in HDF5.
//!
//! This is the only code that knows the HDF5 layout of the ICD. Files are checked
//! against the JSON Schemas of `schemas/` through a manifest of their layout
//! ([`schema`]), then against what a schema cannot express ([`read`]).
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
