//! FITS for the command line: the layout itself (read, write, keywords, the stage's
//! FITS inputs and outputs) is [`crate::product::fits`], re-exported here; this folder
//! adds `persist export` ([`export`]: HDF5 products to FITS), which sits above
//! [`crate::validate`] and so cannot live in `product/`.

pub mod export;

pub use crate::product::fits::*;
