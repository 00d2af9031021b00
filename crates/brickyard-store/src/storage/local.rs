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
