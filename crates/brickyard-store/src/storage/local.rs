//! Local files: positioned reads.

use super::Span;
use crate::error::{IoContext, Result, StoreError};
use std::fs::File;
use std::io::ErrorKind;
use std::path::Path;

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
            let r = s.within(len).ok_or_else(|| {
                StoreError::io(
                    p,
                    std::io::Error::new(
                        ErrorKind::UnexpectedEof,
                        format!("bytes {s:?} asked for, but the file holds {len}"),
                    ),
                )
            })?;
            let mut buf = vec![0u8; (r.end - r.start) as usize];
            read_exact_at(&f, &mut buf, r.start).at(p)?;
            Ok(buf)
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
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
