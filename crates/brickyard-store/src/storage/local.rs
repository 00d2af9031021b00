//! Local files: positioned reads, through the page cache or around it.

use super::Span;
use crate::error::{IoContext, Result, StoreError};
use std::cell::RefCell;
use std::fs::File;
use std::io::ErrorKind;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

fn open(p: &Path) -> Result<Option<File>> {
    match File::open(p) {
        Ok(f) => Ok(Some(f)),
        Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StoreError::io(p, e)),
    }
}

pub(super) fn size(p: &Path) -> Result<Option<u64>> {
    match std::fs::metadata(p) {
        Ok(m) if m.is_file() => Ok(Some(m.len())),
        Ok(_) => Ok(None),
        Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
        Err(e) => Err(StoreError::io(p, e)),
    }
}

pub(super) fn read_spans(p: &Path, spans: &[Span]) -> Result<Option<Vec<Vec<u8>>>> {
    let Some(f) = open(p)? else {
        return Ok(None);
    };
    let meta = f.metadata().at(p)?;
    if meta.is_dir() {
        return Ok(None);
    }
    let len = meta.len();
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

/// The alignment of reads that bypass the page cache (offset, length and
/// buffer address): the largest logical block size of common disks.
pub(super) const DIRECT_ALIGN: usize = 4096;

/// A read buffer a thread keeps between reads up to this size (larger ones
/// are freed after their read), so that reads do not each take fresh memory.
const KEEP_BUFFER: usize = 4 << 20;

static DIRECT_READ: AtomicU64 = AtomicU64::new(0);
static DIRECT_STAGED: AtomicU64 = AtomicU64::new(0);

pub(super) fn direct_read_counts() -> super::DirectReads {
    super::DirectReads {
        read: DIRECT_READ.load(Ordering::Relaxed),
        staged: DIRECT_STAGED.load(Ordering::Relaxed),
    }
}

thread_local! {
    static READ_BUF: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

/// Run `f` with a slice of at least `len` bytes of this thread's read
/// buffer that starts at an address aligned to [`DIRECT_ALIGN`].
fn with_buffer<R>(len: usize, f: impl FnOnce(&mut [u8]) -> R) -> R {
    READ_BUF.with(|b| {
        let mut b = b.borrow_mut();
        if b.len() < len + DIRECT_ALIGN {
            *b = vec![0u8; len + DIRECT_ALIGN];
        }
        let skip = b.as_ptr().align_offset(DIRECT_ALIGN);
        let r = f(&mut b[skip..skip + len]);
        if b.len() > KEEP_BUFFER {
            *b = Vec::new();
        }
        r
    })
}

/// Open `p` for reads that bypass the page cache; `None` where the file
/// system does not take them (the caller then reads through the cache).
#[cfg(target_os = "linux")]
pub(super) fn open_direct(p: &Path) -> Result<Option<Option<File>>> {
    use std::os::unix::fs::OpenOptionsExt;
    match std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_DIRECT)
        .open(p)
    {
        Ok(f) => Ok(Some(Some(f))),
        Err(e) if e.kind() == ErrorKind::NotFound => Ok(Some(None)),
        Err(e) if e.raw_os_error() == Some(libc::EINVAL) => Ok(None),
        Err(e) => Err(StoreError::io(p, e)),
    }
}

#[cfg(not(target_os = "linux"))]
pub(super) fn open_direct(_p: &Path) -> Result<Option<Option<File>>> {
    Ok(None)
}

/// Read `spans` of `p` and hand each to `f` (its position in `spans`, its
/// bytes) in turn, from one read buffer this thread keeps. `direct`: read
/// around the page cache (`O_DIRECT`, whole aligned blocks) where the file
/// system allows it. `Ok(false)`: no such file.
pub(super) fn read_spans_with(
    p: &Path,
    spans: &[Span],
    direct: bool,
    mut f: impl FnMut(usize, &[u8]) -> Result<()>,
) -> Result<bool> {
    let (f_in, direct) = match direct.then(|| open_direct(p)).transpose()?.flatten() {
        Some(None) => return Ok(false),
        Some(Some(file)) => (file, true),
        None => match open(p)? {
            Some(file) => (file, false),
            None => return Ok(false),
        },
    };
    let meta = f_in.metadata().at(p)?;
    if meta.is_dir() {
        return Ok(false);
    }
    let len = meta.len();
    for (i, s) in spans.iter().enumerate() {
        let r = s.within(len).ok_or_else(|| past_end(p, s, len))?;
        let (start, end) = if direct {
            let a = DIRECT_ALIGN as u64;
            (r.start / a * a, r.end.div_ceil(a) * a)
        } else {
            (r.start, r.end)
        };
        let skip = (r.start - start) as usize;
        let want = (r.end - r.start) as usize;
        #[cfg(target_os = "linux")]
        if direct {
            // Read ahead by a hint ([`super::staged`]): taken from there.
            let staged = super::staged::global().take(p, start..end, |b| {
                (b.len() >= skip + want).then(|| f(i, &b[skip..skip + want]))
            });
            if let Some(Some(done)) = staged {
                DIRECT_STAGED.fetch_add(1, Ordering::Relaxed);
                done?;
                continue;
            }
        }
        with_buffer((end - start) as usize, |buf| -> Result<()> {
            if direct {
                // The last block may reach past the end of the file: a short
                // read there is expected, short of the span is not.
                let got = read_up_to(&f_in, buf, start).at(p)?;
                DIRECT_READ.fetch_add(1, Ordering::Relaxed);
                if got < skip + want {
                    return Err(past_end(p, s, start + got as u64));
                }
            } else {
                read_exact_at(&f_in, buf, start).at(p)?;
            }
            f(i, &buf[skip..skip + want])
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

/// Read into `buf` from `at` until it is full or the file ends; the bytes read.
#[cfg(unix)]
pub(super) fn read_up_to(f: &File, buf: &mut [u8], at: u64) -> std::io::Result<usize> {
    use std::os::unix::fs::FileExt;
    let mut got = 0;
    while got < buf.len() {
        match f.read_at(&mut buf[got..], at + got as u64) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

#[cfg(not(unix))]
pub(super) fn read_up_to(f: &File, buf: &mut [u8], at: u64) -> std::io::Result<usize> {
    read_exact_at(f, buf, at).map(|()| buf.len())
}

/// Read `ranges` of `p` ahead, around the page cache ([`super::staged`]).
#[cfg(target_os = "linux")]
pub(super) fn stage(p: &Path, ranges: &[std::ops::Range<u64>]) -> usize {
    super::staged::global().hint(p, ranges, DIRECT_ALIGN as u64)
}

#[cfg(not(target_os = "linux"))]
pub(super) fn stage(_p: &Path, _ranges: &[std::ops::Range<u64>]) -> usize {
    0
}

#[cfg(target_os = "linux")]
pub(super) fn will_need(p: &Path, ranges: &[std::ops::Range<u64>]) -> usize {
    use std::os::fd::AsRawFd;
    let Ok(f) = File::open(p) else {
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
