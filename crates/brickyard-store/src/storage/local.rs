//! Local files: positioned reads.

use super::Span;
use crate::error::{IoContext, Result, StoreError};
use std::cell::RefCell;
use std::fs::File;
use std::io::ErrorKind;
use std::path::Path;

/// Open `p` for reading without waiting on it: a FIFO (or another special
/// file) put where a store's file belongs would otherwise block the reader
/// until something writes into it. A directory opens (the callers treat it
/// as no file); anything else but a regular file is refused, by name.
pub(crate) fn open_regular(p: &Path) -> std::io::Result<File> {
    open_regular_with(p).map(|(f, _)| f)
}

/// [`open_regular`], with the metadata it looked at (one `fstat`).
fn open_regular_with(p: &Path) -> std::io::Result<(File, std::fs::Metadata)> {
    let mut o = std::fs::OpenOptions::new();
    o.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.custom_flags(libc::O_NONBLOCK);
    }
    let f = o.open(p)?;
    let meta = f.metadata()?;
    let kind = meta.file_type();
    if kind.is_file() || kind.is_dir() {
        Ok((f, meta))
    } else {
        Err(not_regular())
    }
}

/// A folder where a value's file belongs: damage, not an absent value
/// (read as absent, a shard turned folder was reported as an index
/// without the chunk).
fn a_folder() -> std::io::Error {
    std::io::Error::new(
        ErrorKind::IsADirectory,
        "a folder stands where a store's file belongs",
    )
}

fn not_regular() -> std::io::Error {
    std::io::Error::new(
        ErrorKind::InvalidInput,
        "not a regular file (a FIFO, socket or device stands where a store's file belongs)",
    )
}

pub(super) fn size(p: &Path) -> Result<Option<u64>> {
    match std::fs::metadata(p) {
        Ok(m) if m.is_file() => Ok(Some(m.len())),
        Ok(m) if m.is_dir() => Err(StoreError::io(p, a_folder())),
        Ok(_) => Err(StoreError::io(p, not_regular())),
        Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StoreError::io(p, e)),
    }
}

/// `p` opened, and its length; `None` when there is no such file (a
/// folder there: an error, [`a_folder`]).
fn open_file(p: &Path) -> Result<Option<(File, u64)>> {
    match open_regular_with(p) {
        Ok((_, meta)) if meta.is_dir() => Err(StoreError::io(p, a_folder())),
        Ok((f, meta)) => Ok(Some((f, meta.len()))),
        Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StoreError::io(p, e)),
    }
}

pub(super) fn read_spans(p: &Path, spans: &[Span]) -> Result<Option<Vec<Vec<u8>>>> {
    let Some((f, len)) = open_file(p)? else {
        return Ok(None);
    };
    spans
        .iter()
        .map(|s| {
            let r = s.within(len).ok_or_else(|| past_end(p, s, len))?;
            let mut buf = vec![0u8; (r.end - r.start) as usize];
            read_exact_at(&f, &mut buf, r.start).at(p)?;
            Ok(buf)
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}

/// A read buffer a thread keeps between reads up to this size (larger ones
/// are freed after their read), so that reads do not each take fresh memory.
const KEEP_BUFFER: usize = 1 << 20;

thread_local! {
    static READ_BUF: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

/// Run `f` with `len` bytes of this thread's read buffer (of a new one
/// when a read within `f` asks while the thread's is in use).
fn with_buffer<R>(len: usize, f: impl FnOnce(&mut [u8]) -> R) -> R {
    READ_BUF.with(|b| {
        let Ok(mut b) = b.try_borrow_mut() else {
            return f(&mut vec![0u8; len]);
        };
        if b.len() < len {
            *b = vec![0u8; len];
        }
        let r = f(&mut b[..len]);
        if b.len() > KEEP_BUFFER {
            *b = Vec::new();
        }
        r
    })
}

/// Read `spans` of `p` and hand each to `f` (its position in `spans`, its
/// bytes) in turn, from one read buffer this thread keeps. `Ok(false)`: no
/// such file.
pub(super) fn read_spans_with(
    p: &Path,
    spans: &[Span],
    mut f: impl FnMut(usize, &[u8]) -> Result<()>,
) -> Result<bool> {
    let Some((file, len)) = open_file(p)? else {
        return Ok(false);
    };
    for (i, s) in spans.iter().enumerate() {
        let r = s.within(len).ok_or_else(|| past_end(p, s, len))?;
        with_buffer((r.end - r.start) as usize, |buf| -> Result<()> {
            read_exact_at(&file, buf, r.start).at(p)?;
            f(i, buf)
        })?;
    }
    Ok(true)
}

fn past_end(p: &Path, s: &Span, len: u64) -> StoreError {
    StoreError::io(
        p,
        std::io::Error::new(
            ErrorKind::UnexpectedEof,
            format!("bytes {s:?} asked for, but the file holds {len}"),
        ),
    )
}

#[cfg(target_os = "linux")]
pub(super) fn will_need(p: &Path, ranges: &[std::ops::Range<u64>]) -> usize {
    use std::os::fd::AsRawFd;
    let Ok(f) = open_regular(p) else {
        return 0;
    };
    ranges
        .iter()
        .filter(|r| {
            let (Ok(at), Ok(len)) = (
                libc::off_t::try_from(r.start),
                libc::off_t::try_from(r.end.saturating_sub(r.start)),
            ) else {
                return false;
            };
            // SAFETY: a plain system call on an open descriptor.
            len > 0
                && unsafe { libc::posix_fadvise(f.as_raw_fd(), at, len, libc::POSIX_FADV_WILLNEED) }
                    == 0
        })
        .count()
}

#[cfg(not(target_os = "linux"))]
pub(super) fn will_need(_p: &Path, _ranges: &[std::ops::Range<u64>]) -> usize {
    0
}

#[cfg(unix)]
fn read_exact_at(f: &File, buf: &mut [u8], at: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(f, buf, at)
}

#[cfg(windows)]
fn read_exact_at(f: &File, mut buf: &mut [u8], mut at: u64) -> std::io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match f.seek_read(buf, at)? {
            0 => return Err(ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                at += n as u64;
            }
        }
    }
    Ok(())
}
