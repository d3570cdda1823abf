//! Level-1 input and persistence output products (ICD), in memory and in HDF5.

pub mod exposure;

pub use exposure::{Exposure, ExposureMeta, PersistenceAttrs, PersistencePlanes};
