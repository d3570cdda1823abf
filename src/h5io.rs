//! Low-level HDF5 helpers shared by products ([`crate::product`]) and checkpoints
//! ([`crate::checkpoint`]): deterministic file creation, scalar attributes, dataset
//! layouts, and the atomic publication of a file.
//!
//! Invariants:
//! - **Byte determinism.** Files are created with object modification times turned off
//!   (`obj_track_times = false` on the file creation list, which covers the root group,
//!   and on every group and dataset created here), so the same content written the same
//!   way gives the same bytes.
//! - **Atomic publication.** [`publish`] writes under `.NAME.part` in the destination
//!   directory (a name watchers ignore), closes, re-opens and validates the temporary
//!   file, `fsync`s it, renames it into place and `fsync`s the directory. On any failure
//!   the temporary file is removed: a file under its final name is always complete and
//!   valid. (A failed `fsync` of the directory after the rename is reported; the file
//!   it leaves published is complete and synced.)
//! - Errors name the file (the final name, not the temporary one).

use crate::error::{Error, ErrorKind, Result};
use hdf5::types::VarLenUnicode;
use ndarray::{ArrayView, Dimension};
use std::path::{Path, PathBuf};

/// Largest accepted size of any axis of any dataset (an H2RG is 2048 x 2048).
pub const MAX_AXIS: usize = 8192;

/// Largest accepted number of elements of any dataset (2^31: a 2040 x 2040 ramp of 500
/// samples); larger would only exhaust memory.
pub const MAX_ELEMENTS: usize = 1 << 31;

/// Deflate level of the compressed flag planes (mostly zeros: level 1 already gives
/// most of the gain at a fraction of the time).
pub const FLAG_DEFLATE_LEVEL: u8 = 1;

/// Target size of one chunk of a compressed plane, bytes.
const CHUNK_BYTES: usize = 256 * 1024;

/// The temporary name `path` is written under: `.NAME.part` in the same directory.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.part"))
}

/// Is this file name a temporary one (`.*` or `*.part`)?
pub fn is_temp_name(name: &str) -> bool {
    name.starts_with('.') || name.ends_with(".part")
}

/// Open an HDF5 file for reading; errors name the file (a file still being written
/// by another process gives [`ErrorKind::NotReady`]).
/// Errors about the file as a whole have the field `/` (the root group).
pub fn open(path: &Path) -> Result<hdf5::File> {
    if let Err(e) = std::fs::metadata(path) {
        return Err(Error::io(path, e).field("/"));
    }
    hdf5::File::open(path)
        .map(close_on_exec)
        .map_err(|e| open_error(e).path(path))
}

/// Files this crate creates are never locked (`create`, `open_as`): they are written
/// under hidden temporary names and renamed into place, so no reader can see them half
/// written, and an unlocked file cannot be held locked by a child process that
/// inherited its descriptor during libhdf5's create call (the window close-on-exec
/// cannot close). Files read by name (`open`) keep libhdf5's locking: a product still
/// being written in place by another program is "not ready".
///
/// Mark an open HDF5 file's descriptor close-on-exec, and return the file.
///
/// libhdf5 opens files without `O_CLOEXEC` and `flock`s them. A child process started
/// while a file is open (the bench's children, a test harness's `persist` runs) would
/// inherit the descriptor, and with it the lock, for its whole life: a later open of the
/// file anywhere then fails with "unable to lock file". (A fork in the instant between
/// libhdf5's `open` and this call can still inherit it; that window is microseconds.)
pub fn close_on_exec(file: hdf5::File) -> hdf5::File {
    let id = file.id();
    let mut handle: *mut std::ffi::c_void = std::ptr::null_mut();
    // SAFETY: `id` is a live file id; with the default (sec2) driver the handle is a
    // pointer to the file's `int` descriptor, read once and only if the call succeeded.
    let fd = hdf5::sync::sync(|| unsafe {
        let rc = hdf5_sys::h5f::H5Fget_vfd_handle(id, hdf5_sys::h5p::H5P_DEFAULT, &mut handle);
        (rc >= 0 && !handle.is_null()).then(|| *(handle as *const std::ffi::c_int))
    });
    if let Some(fd) = fd {
        // SAFETY: fcntl on a descriptor this process owns; failure leaves it unchanged.
        unsafe {
            let flags = libc::fcntl(fd, libc::F_GETFD);
            if flags >= 0 {
                libc::fcntl(fd, libc::F_SETFD, flags | libc::FD_CLOEXEC);
            }
        }
    }
    file
}

/// An HDF5 open failure: not ready (locked by a writer) or not readable as HDF5.
fn open_error(e: hdf5::Error) -> Error {
    let mut err = Error::from(e).field("/");
    if err.kind == ErrorKind::Hdf5 {
        err.message = format!(
            "not a readable HDF5 file (truncated or corrupt?): {}",
            err.message
        );
    } else if err.kind == ErrorKind::NotReady {
        err.message = format!("still being written by another process: {}", err.message);
    }
    err
}

/// Create (truncate) an HDF5 file with object times off. (No path in the error: the
/// caller names the file, usually the final name of a temporary file.)
///
/// Data sieving is off (`sieve_buf_size(0)`): HDF5 1.10 keeps small contiguous
/// datasets in its sieve buffer and writes them later, from a path that drops a
/// failed write (an ENOSPC or EIO injected into that `pwrite64` gave a published file
/// with a hole and no error, tests/ops_write_faults.rs); written at once, a failure is
/// the dataset write's error. The file's bytes are the same.
pub fn create(path: &Path) -> hdf5::Result<hdf5::File> {
    hdf5::File::with_options()
        .with_fcpl(|p| p.obj_track_times(false))
        .with_fapl(|p| p.file_locking(false).sieve_buf_size(0))
        .create(path)
        .map(close_on_exec)
}

/// Open `tmp` for validation; errors name `name`.
pub fn open_as(tmp: &Path, name: &Path) -> Result<hdf5::File> {
    hdf5::File::with_options()
        .with_fapl(|p| p.file_locking(false))
        .open(tmp)
        .map(close_on_exec)
        .map_err(|e| open_error(e).path(name))
}

/// Open an existing file for editing in place, unlocked and close-on-exec, as
/// [`create`] does: for the tests' and tools' edits of a file no other program writes.
/// With libhdf5's lock, a child process started between its `open` and
/// [`close_on_exec`] (another test's `persist` run) inherits the descriptor and keeps
/// the file locked for its life, and the next open fails "unable to lock file"
/// (seen once in a fresh-clone CI run, `tests/products.rs` `ramp_times_not_increasing`).
pub fn open_rw_unlocked(path: &Path) -> hdf5::Result<hdf5::File> {
    hdf5::File::with_options()
        .with_fapl(|p| p.file_locking(false))
        .open_rw(path)
        .map(close_on_exec)
}

/// Create a group with object times off.
pub fn create_group(parent: &hdf5::Group, name: &str) -> hdf5::Result<hdf5::Group> {
    parent
        .create_group_builder()
        .obj_track_times(false)
        .create(name)
}

/// Write a contiguous, uncompressed dataset (images, currents, state).
pub fn write_plain<T, D>(
    parent: &hdf5::Group,
    name: &str,
    data: ArrayView<'_, T, D>,
) -> hdf5::Result<()>
where
    T: hdf5::H5Type + Clone,
    D: Dimension,
{
    let data = data.as_standard_layout();
    parent
        .new_dataset_builder()
        .obj_track_times(false)
        .with_data(&data)
        .create(name)?;
    Ok(())
}

/// An integer flag word: the element types of the flag planes (`u8`, `u32`).
pub trait FlagWord: hdf5::H5Type + Copy + Default + Send + Sync + sealed::Sealed {}
impl FlagWord for u8 {}
impl FlagWord for u32 {}

mod sealed {
    pub trait Sealed {}
    impl Sealed for u8 {}
    impl Sealed for u32 {}
}

/// Write a flag plane `[ny, nx]`, chunked by rows, shuffled then deflated.
///
/// The dataset carries the standard filter pipeline (HDF5's shuffle, then deflate at
/// [`FLAG_DEFLATE_LEVEL`]), so any HDF5 reader (h5py, the library) reads it. The
/// filters themselves run here, one chunk per task on the rayon pool, with the same
/// zlib call and the same byte transposition as the library's filters
/// (`compress2(level)` on the shuffled chunk, edge chunks padded with the fill value
/// 0), and the filtered chunks are written in chunk order with `H5Dwrite_chunk`: the
/// file is byte-identical to the library's own filtered write, which would compress
/// the chunks one after another under HDF5's global lock.
pub fn write_flags<T: FlagWord>(
    parent: &hdf5::Group,
    name: &str,
    data: ArrayView<'_, T, ndarray::Ix2>,
) -> hdf5::Result<()> {
    use rayon::prelude::*;
    let (ny, nx) = data.dim();
    let size = std::mem::size_of::<T>();
    let rows = (CHUNK_BYTES / (nx.max(1) * size).max(1)).clamp(1, ny.max(1));
    let ds = parent
        .new_dataset::<T>()
        .obj_track_times(false)
        .chunk((rows, nx.max(1)))
        .shuffle()
        .deflate(FLAG_DEFLATE_LEVEL)
        .shape((ny, nx))
        .create(name)?;
    if ny == 0 || nx == 0 {
        return Ok(());
    }
    let data = data.as_standard_layout();
    let plane = data.as_slice().ok_or("flag plane not contiguous")?;
    // SAFETY: `T` is `u8` or `u32` (sealed): plain integers, no padding, any bit
    // pattern valid; the byte view covers exactly the slice's memory.
    let bytes = unsafe {
        std::slice::from_raw_parts(plane.as_ptr().cast::<u8>(), std::mem::size_of_val(plane))
    };
    let row_bytes = nx * size;
    let chunks: Vec<Vec<u8>> = bytes
        .par_chunks(rows * row_bytes)
        .map(|part| filter_chunk(part, rows * row_bytes, size))
        .collect::<std::result::Result<_, String>>()?;
    for (k, chunk) in chunks.iter().enumerate() {
        let offset: [hdf5_sys::h5::hsize_t; 2] = [(k * rows) as _, 0];
        hdf5::h5call!(unsafe {
            hdf5_sys::h5d::H5Dwrite_chunk(
                ds.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
                0,
                offset.as_ptr(),
                chunk.len(),
                chunk.as_ptr().cast(),
            )
        })?;
    }
    Ok(())
}

#[link(name = "z")]
extern "C" {
    fn compress2(
        dest: *mut u8,
        dest_len: *mut std::ffi::c_ulong,
        source: *const u8,
        source_len: std::ffi::c_ulong,
        level: std::ffi::c_int,
    ) -> std::ffi::c_int;
    fn compressBound(source_len: std::ffi::c_ulong) -> std::ffi::c_ulong;
}

/// HDF5's shuffle then deflate filters on one chunk of `chunk_bytes` (`part` padded
/// with zeros to that length): the bytes the library stores for it.
fn filter_chunk(
    part: &[u8],
    chunk_bytes: usize,
    size: usize,
) -> std::result::Result<Vec<u8>, String> {
    let mut padded = vec![0u8; chunk_bytes];
    padded[..part.len()].copy_from_slice(part);
    let src = if size > 1 {
        // H5Z_filter_shuffle: byte j of element i goes to j * n + i.
        let n = chunk_bytes / size;
        let mut out = vec![0u8; chunk_bytes];
        for (i, e) in padded.chunks_exact(size).enumerate() {
            for (j, b) in e.iter().enumerate() {
                out[j * n + i] = *b;
            }
        }
        out
    } else {
        padded
    };
    // SAFETY: `compressBound` is pure; `compress2` writes at most `dest_len` bytes into
    // `dst`, which holds that many, and reads `src.len()` bytes of `src`.
    unsafe {
        let mut dest_len = compressBound(src.len() as _);
        let mut dst = vec![0u8; dest_len as usize];
        let rc = compress2(
            dst.as_mut_ptr(),
            &mut dest_len,
            src.as_ptr(),
            src.len() as _,
            std::ffi::c_int::from(FLAG_DEFLATE_LEVEL),
        );
        if rc != 0 {
            return Err(format!("zlib compress2 failed ({rc})"));
        }
        dst.truncate(dest_len as usize);
        Ok(dst)
    }
}

pub fn attr_str(loc: &hdf5::Location, name: &str, value: &str) -> Result<()> {
    let v: VarLenUnicode = value
        .parse()
        .map_err(|e| Error::invalid(name, format!("cannot be stored as an HDF5 string: {e}")))?;
    loc.new_attr::<VarLenUnicode>()
        .create(name)
        .and_then(|a| a.write_scalar(&v))
        .map_err(|e| Error::from(e).field(name))
}

pub fn attr_f64(loc: &hdf5::Location, name: &str, value: f64) -> Result<()> {
    loc.new_attr::<f64>()
        .create(name)
        .and_then(|a| a.write_scalar(&value))
        .map_err(|e| Error::from(e).field(name))
}

pub fn attr_i64(loc: &hdf5::Location, name: &str, value: i64) -> Result<()> {
    loc.new_attr::<i64>()
        .create(name)
        .and_then(|a| a.write_scalar(&value))
        .map_err(|e| Error::from(e).field(name))
}

/// The version of the HDF5 library this program runs with (`MAJOR.MINOR.RELEASE`),
/// recorded as `hdf5_version` in every output product and checkpoint.
pub fn library_version() -> String {
    let (a, b, c) = hdf5::library_version();
    format!("{a}.{b}.{c}")
}

/// Check that a 2-D plane about to be written has sane dimensions.
pub fn check_plane(field: &str, dim: (usize, usize)) -> Result<()> {
    check_axes(field, &[dim.0, dim.1])
}

/// Every axis in 1..=[`MAX_AXIS`], at most [`MAX_ELEMENTS`] in all.
pub fn check_axes(field: &str, shape: &[usize]) -> Result<()> {
    if let Some((k, n)) = shape
        .iter()
        .enumerate()
        .find(|(_, &n)| n == 0 || n > MAX_AXIS)
    {
        return Err(Error::invalid(
            field,
            format!(
                "absurd dimensions {shape:?}: axis {k} is {n}, every axis must be 1..={MAX_AXIS}"
            ),
        ));
    }
    let total = shape
        .iter()
        .try_fold(1usize, |acc, &n| acc.checked_mul(n))
        .unwrap_or(usize::MAX);
    if total > MAX_ELEMENTS {
        return Err(Error::invalid(
            field,
            format!("absurd dimensions {shape:?}: {total} elements, at most {MAX_ELEMENTS}"),
        ));
    }
    Ok(())
}

/// Write `path` atomically (module docs): `write` fills the temporary file it is given,
/// `validate` checks the closed temporary file (errors should name `path`).
pub fn publish(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<()>,
    validate: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    write_temp(path, write, validate)?.commit()
}

/// A file written and validated under its temporary name, not yet published: the
/// first half of [`publish`]. [`Staged::commit`] is the second half (sync, rename,
/// sync the directory); it needs no HDF5 call and no data in memory, so it can run on
/// another thread. The temporary file and its directory are opened by [`write_temp`],
/// on the writing thread, so that the commit makes no `open` of its own: every `open`
/// of a publication is made in one thread, in order. Dropped without a commit, the
/// temporary file is removed.
#[derive(Debug)]
pub struct Staged {
    tmp: Option<PathBuf>,
    path: PathBuf,
    /// The temporary file (read-only: `fsync` needs no write access) and the directory.
    handles: Option<(std::fs::File, std::fs::File)>,
}

impl Staged {
    /// The final name.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// `fsync` the temporary file, rename it into place, `fsync` the directory.
    ///
    /// A failure before the rename removes the temporary file: nothing is published.
    /// A failure of the directory's `fsync` after the rename leaves the complete,
    /// synced file published under its final name (the rename is not known to be
    /// durable); the error says so, and the stage syncs the directory of an output it
    /// finds published before it checkpoints past it.
    pub fn commit(mut self) -> Result<()> {
        let (Some(tmp), Some((file, dir))) = (self.tmp.take(), self.handles.take()) else {
            return Ok(());
        };
        let path = &self.path;
        if let Err(e) = file.sync_all().and_then(|()| std::fs::rename(&tmp, path)) {
            let _ = std::fs::remove_file(&tmp);
            return Err(Error::io(path, e));
        }
        drop(file);
        dir.sync_all().map_err(|e| {
            Error::new(
                ErrorKind::Io,
                format!("published, but the fsync of its directory failed: {e}"),
            )
            .path(path)
        })
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if let Some(tmp) = self.tmp.take() {
            let _ = std::fs::remove_file(tmp);
        }
    }
}

/// The first half of [`publish`]: write and validate under the temporary name, then
/// open the temporary file and its directory for [`Staged::commit`].
pub fn write_temp(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<()>,
    validate: impl FnOnce(&Path) -> Result<()>,
) -> Result<Staged> {
    let tmp = temp_path(path);
    let mut staged = Staged {
        tmp: Some(tmp.clone()),
        path: path.to_path_buf(),
        handles: None,
    };
    // On error `staged` is dropped, which removes the temporary file (best effort: it
    // may not exist if the failure came before its creation).
    write(&tmp).map_err(|e| e.path(path))?;
    validate(&tmp).map_err(|e| e.path(path))?;
    let file = std::fs::File::open(&tmp).map_err(|e| Error::io(path, e))?;
    let dir = std::fs::File::open(dir_of(path)).map_err(|e| {
        Error::new(ErrorKind::Io, format!("cannot open its directory: {e}")).path(path)
    })?;
    staged.handles = Some((file, dir));
    Ok(staged)
}

/// The directory holding `path` (`.` for a bare name).
fn dir_of(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// `fsync` the directory holding `path`, so that a rename into it is durable.
pub fn sync_dir(path: &Path) -> Result<()> {
    sync_dir_itself(dir_of(path))
}

/// `fsync` the directory `dir` itself (what makes the renames into it durable).
pub fn sync_dir_itself(dir: &Path) -> Result<()> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| Error::new(ErrorKind::Io, format!("fsync of directory: {e}")).path(dir))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    /// The library's own filtered write, as `write_flags` did before it ran the filters
    /// itself.
    fn library_write<T: FlagWord>(path: &Path, a: &Array2<T>) {
        let (ny, nx) = a.dim();
        let rows = (CHUNK_BYTES / (nx * std::mem::size_of::<T>())).clamp(1, ny);
        let file = create(path).unwrap();
        file.new_dataset_builder()
            .obj_track_times(false)
            .chunk((rows, nx))
            .shuffle()
            .deflate(FLAG_DEFLATE_LEVEL)
            .with_data(a)
            .create("flags")
            .unwrap();
        file.close().unwrap();
    }

    /// `write_flags` (filters on the rayon pool, `H5Dwrite_chunk`) writes the same file
    /// bytes as HDF5's filter pipeline, for both flag types, with partial edge chunks
    /// (1000 rows of 1003: u32 in 15 chunks of 65 rows and one of 25, u8 in 3 chunks of
    /// 261 rows and one of 217), and the values read back are the same.
    #[test]
    fn parallel_filters_write_the_library_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let (ny, nx) = (1000, 1003);
        let u32s = Array2::from_shape_fn((ny, nx), |(y, x)| {
            if (y * 31 + x * 7) % 97 == 0 {
                1u32 << ((y + x) % 20)
            } else {
                0
            }
        });
        let u8s = u32s.mapv(|v| (v % 251) as u8);
        fn check<T: FlagWord + PartialEq + std::fmt::Debug>(dir: &Path, a: &Array2<T>, tag: &str) {
            let (ours, theirs) = (
                dir.join(format!("{tag}_a.h5")),
                dir.join(format!("{tag}_b.h5")),
            );
            let file = create(&ours).unwrap();
            write_flags(&file, "flags", a.view()).unwrap();
            file.close().unwrap();
            library_write(&theirs, a);
            assert!(
                std::fs::read(&ours).unwrap() == std::fs::read(&theirs).unwrap(),
                "{tag}: bytes differ from the library's filtered write"
            );
            let back: Array2<T> = open(&ours)
                .unwrap()
                .dataset("flags")
                .unwrap()
                .read_2d()
                .unwrap();
            assert_eq!(&back, a);
        }
        check(dir.path(), &u32s, "u32");
        check(dir.path(), &u8s, "u8");
    }
}
