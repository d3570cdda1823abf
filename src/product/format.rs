//! The stage's one door to product files: "the next exposure" ([`read_input`]) and
//! "this output" ([`stage_output`]), in whichever format the input came in.
//!
//! Invariants:
//! - The format is decided by the file's content ([`format_of`]: the HDF5 signature or
//!   FITS's `SIMPLE  =` card in its first bytes), and only by its name when the content
//!   is neither (a truncated or corrupt file then gets its format's reader's error, which
//!   names the file and the reason).
//! - An output is written in its input's format: HDF5 in, HDF5 out
//!   ([`super::write::stage_output`]); FITS in, a copy of the input FITS with the
//!   persistence extensions ([`super::fits::write_output`]). Both validate before they
//!   publish.
//! - Nothing above `product/` tests for a format: the stage, the tile jobs and the
//!   assembly call only this module.

use super::exposure::{Exposure, ExposureMeta, PersistenceAttrs, PersistencePlanes};
use super::fits::{self, FitsConfig, FitsInput};
use crate::error::Result;
use crate::h5io;
use std::io::Read;
use std::path::Path;

/// The 8-byte signature an HDF5 superblock starts with.
const HDF5_SIGNATURE: &[u8; 8] = b"\x89HDF\r\n\x1a\n";
/// Offsets an HDF5 superblock may start at (after a user block of 0, 512, 1024, ... bytes).
const HDF5_OFFSETS: [u64; 5] = [0, 512, 1024, 2048, 4096];
/// The first card of every FITS file (FITS Standard 4.0, section 4.4.1.1).
const FITS_SIGNATURE: &[u8; 9] = b"SIMPLE  =";

/// A product file's format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Hdf5,
    Fits,
}

/// The format of `path`: by its first bytes, or by its name (`*.fits`, `*.fit`,
/// `*.fts`: FITS; anything else: HDF5) when the bytes are neither or cannot be read.
pub fn format_of(path: &Path) -> Format {
    sniff(path).unwrap_or(if fits::is_fits(path) {
        Format::Fits
    } else {
        Format::Hdf5
    })
}

/// The format the file's bytes show, if any.
fn sniff(path: &Path) -> Option<Format> {
    let mut f = std::fs::File::open(path).ok()?;
    let mut head = [0u8; 9];
    f.read_exact(&mut head).ok()?;
    if &head == FITS_SIGNATURE {
        return Some(Format::Fits);
    }
    if head[..8] == HDF5_SIGNATURE[..] {
        return Some(Format::Hdf5);
    }
    use std::io::{Seek, SeekFrom};
    for &at in &HDF5_OFFSETS[1..] {
        let mut sig = [0u8; 8];
        if f.seek(SeekFrom::Start(at)).is_err() || f.read_exact(&mut sig).is_err() {
            return None;
        }
        if &sig == HDF5_SIGNATURE {
            return Some(Format::Hdf5);
        }
    }
    None
}

/// An input exposure as read, with what its output must carry over from the input file.
#[derive(Debug, Clone)]
pub struct InputProduct {
    pub exposure: Exposure,
    /// FITS inputs: the conversion of the image to e-/s and the exposure index's
    /// source, recorded in the output; `None` for HDF5.
    pub fits: Option<FitsInput>,
}

/// Read the exposure in `path` (validated), in its format.
pub fn read_input(path: &Path, cfg: &FitsConfig) -> Result<InputProduct> {
    match format_of(path) {
        Format::Fits => {
            let (exposure, read) = fits::read_exposure(path, cfg)?;
            Ok(InputProduct {
                exposure,
                fits: Some(read),
            })
        }
        Format::Hdf5 => Ok(InputProduct {
            exposure: super::read::read_exposure(path)?,
            fits: None,
        }),
    }
}

/// The metadata of the input product in `path`, and whether its exposure index is a
/// start time (a FITS exposure without a sequence number,
/// [`fits::Sequence::StartTime`]).
pub fn read_input_sequence(path: &Path, cfg: &FitsConfig) -> Result<(ExposureMeta, bool)> {
    match format_of(path) {
        Format::Fits => fits::read_meta_sequence(path, cfg).map(|(m, s)| (m, s.is_start_time())),
        Format::Hdf5 => super::read::read_meta(path).map(|m| (m, false)),
    }
}

/// [`read_input_sequence`] without the index's source.
pub fn read_input_meta(path: &Path, cfg: &FitsConfig) -> Result<ExposureMeta> {
    read_input_sequence(path, cfg).map(|(meta, _)| meta)
}

/// Write the output of `read` (its exposure's flags carrying the `PERSIST` bits) to
/// `out`, in the input's format, validated under its temporary name. HDF5 outputs are
/// returned staged (the caller commits them, possibly on another thread); FITS outputs
/// are published here (`None`).
pub fn stage_output(
    input: &Path,
    out: &Path,
    read: &InputProduct,
    planes: &PersistencePlanes,
    attrs: &PersistenceAttrs,
    cfg: &FitsConfig,
) -> Result<Option<h5io::Staged>> {
    match &read.fits {
        Some(f) => fits::write_output(input, out, &read.exposure, planes, attrs, f, &cfg.keywords)
            .map(|()| None),
        None => super::write::stage_output(out, &read.exposure, planes, attrs).map(Some),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_format_is_read_from_the_bytes_before_the_name() {
        let dir = tempfile::tempdir().unwrap();
        let fits_named_h5 = dir.path().join("a.h5");
        let mut card = b"SIMPLE  =                    T".to_vec();
        card.resize(2880, b' ');
        std::fs::write(&fits_named_h5, &card).unwrap();
        assert_eq!(format_of(&fits_named_h5), Format::Fits);
        let h5_named_fits = dir.path().join("b.fits");
        let mut bytes = HDF5_SIGNATURE.to_vec();
        bytes.resize(64, 0);
        std::fs::write(&h5_named_fits, &bytes).unwrap();
        assert_eq!(format_of(&h5_named_fits), Format::Hdf5);
        // Neither signature: the name decides.
        let junk = dir.path().join("c.fits");
        std::fs::write(&junk, b"not a product at all").unwrap();
        assert_eq!(format_of(&junk), Format::Fits);
        assert_eq!(format_of(&dir.path().join("missing.h5")), Format::Hdf5);
    }
}
