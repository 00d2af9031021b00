//! Byte-range reads of a store, local or remote. Every read of a Zarr
//! store — group and array metadata, shard indexes, chunks, statistics —
//! goes through here, so a store on a web server reads exactly as one on
//! disk.
//!
//! A store *location* is a `Path` whose text is either a local path, an
//! `http://` / `https://` URL or an `s3://bucket/key` location
//! ([`is_remote`]; S3 requests are HTTPS requests made by [`s3`]); joining keys onto it with
//! `Path::join` gives the location of a key either way, so the readers keep
//! their `&Path` signatures. [`StoreAt`] adapts a location to the Zarr
//! library's storage traits.

pub mod http;
mod local;
pub(crate) use local::open_regular;
pub mod s3;
mod zarr;

pub use zarr::StoreAt;

use crate::error::Result;
use std::ops::Range;
use std::path::Path;

/// A part of a value (file) to read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Span {
    /// The whole value.
    All,
    /// Bytes `start..end`.
    Range(Range<u64>),
    /// From an offset to the end.
    From(u64),
    /// The last `n` bytes (a shard index at the end of its shard).
    Suffix(u64),
}

impl Span {
    /// The byte range this span covers in a value of `len` bytes; `None`
    /// when it reaches past the end.
    pub fn within(&self, len: u64) -> Option<Range<u64>> {
        match *self {
            Span::All => Some(0..len),
            Span::Range(ref r) => (r.start <= r.end && r.end <= len).then(|| r.clone()),
            Span::From(o) => (o <= len).then_some(o..len),
            Span::Suffix(n) => (n <= len).then(|| len - n..len),
        }
    }
}

/// Whether `p` names a remote store (an `http://` or `https://` URL, or
/// an `s3://` location).
pub fn is_remote(p: &Path) -> bool {
    p.to_str().is_some_and(|s| {
        let l = s.get(..8).unwrap_or(s).to_ascii_lowercase();
        l.starts_with("http://") || l.starts_with("https://") || s3::is_s3(s)
    })
}

/// The location's text as given (a URL keeps its `//`).
pub(crate) fn url_of(p: &Path) -> &str {
    p.to_str().unwrap_or_default()
}

/// Read the whole value at `p`; `Ok(None)` when there is none.
pub fn read(p: &Path) -> Result<Option<Vec<u8>>> {
    Ok(read_spans(p, &[Span::All])?.map(|mut v| v.swap_remove(0)))
}

/// Read `spans` of the value at `p`, in the order given; `Ok(None)` when
/// there is no such value. Remote reads of nearby ranges are coalesced
/// into one request.
pub fn read_spans(p: &Path, spans: &[Span]) -> Result<Option<Vec<Vec<u8>>>> {
    if is_remote(p) {
        http::client().read_spans(url_of(p), spans)
    } else {
        local::read_spans(p, spans)
    }
}

/// Read `spans` of the value at `p` in order and hand each to `f` (its
/// position in `spans`, its bytes), which must not keep them: local reads
/// go into one buffer the thread keeps, not into new memory each.
/// `Ok(false)` when there is no such value.
pub fn read_spans_with(
    p: &Path,
    spans: &[Span],
    mut f: impl FnMut(usize, &[u8]) -> Result<()>,
) -> Result<bool> {
    if is_remote(p) {
        let Some(bufs) = http::client().read_spans(url_of(p), spans)? else {
            return Ok(false);
        };
        for (i, b) in bufs.iter().enumerate() {
            f(i, b)?;
        }
        return Ok(true);
    }
    local::read_spans_with(p, spans, f)
}

/// The last `n` bytes of the value at `p` (all of it when it is shorter)
/// and its length; `Ok(None)` when there is none. Remote: one ranged GET,
/// cached (a shard index and the shard's size without a HEAD request).
pub fn read_suffix(p: &Path, n: u64) -> Result<Option<(Vec<u8>, u64)>> {
    if is_remote(p) {
        return Ok(http::client()
            .suffix(url_of(p), n)?
            .map(|(b, len)| (b.to_vec(), len)));
    }
    let Some(len) = local::size(p)? else {
        return Ok(None);
    };
    let Some(mut v) = local::read_spans(p, &[Span::Suffix(n.min(len))])? else {
        return Ok(None);
    };
    Ok(Some((v.swap_remove(0), len)))
}

/// Tell the system that `ranges` of the value at `p` will be read soon,
/// so that it starts reading them while the caller works on other data
/// (on Linux, `posix_fadvise(WILLNEED)`: the kernel queues the reads and
/// returns at once). Returns how many ranges were handed over; 0 where
/// there is no such hint (remote stores, other systems) or no such file.
/// Only a hint: nothing depends on it but speed, so errors are ignored.
pub fn will_need(p: &Path, ranges: &[Range<u64>]) -> usize {
    if is_remote(p) {
        0
    } else {
        local::will_need(p, ranges)
    }
}

/// The size of the value at `p`; `Ok(None)` when there is none.
pub fn size(p: &Path) -> Result<Option<u64>> {
    if is_remote(p) {
        http::client().size(url_of(p))
    } else {
        local::size(p)
    }
}

/// Whether there is a value (a file, for local stores) at `p`. Errors
/// other than "not found" count as present, so that the read that follows
/// reports them.
pub fn exists(p: &Path) -> bool {
    if is_remote(p) {
        !matches!(size(p), Ok(None))
    } else {
        p.exists()
    }
}

/// What tells a local store from its replacement (written again with
/// `--overwrite`, or moved away and another put in its place): its root
/// metadata file (`zarr.json`, `.zgroup` or `.zarray`) and that file's
/// device, inode and change time. A reader that caches shard indexes,
/// statistics and bricks checks it before reading, so that it never
/// reads half from what it cached and half from new files (at the old
/// offsets).
#[derive(Clone, Debug)]
pub struct StoreIdentity {
    file: std::path::PathBuf,
    id: (u64, u64, i64, i64),
}

impl StoreIdentity {
    /// The identity of the store at `root` now; `None` for a remote store
    /// or one without root metadata.
    pub fn of(root: &Path) -> Option<StoreIdentity> {
        if is_remote(root) {
            return None;
        }
        ["zarr.json", ".zgroup", ".zarray"]
            .iter()
            .map(|n| root.join(n))
            .find_map(|file| file_id(&file).map(|id| StoreIdentity { file, id }))
    }

    /// `Err` saying what changed when the store was replaced or removed
    /// since [`of`](Self::of) (the caller names the store).
    pub fn check(&self) -> std::result::Result<(), String> {
        if file_id(&self.file) == Some(self.id) {
            return Ok(());
        }
        Err(format!(
            "the store was replaced or removed since it was opened (its {} changed): open it \
             again",
            self.file
                .file_name()
                .map_or(String::new(), |n| n.to_string_lossy().into())
        ))
    }
}

#[cfg(unix)]
fn file_id(p: &Path) -> Option<(u64, u64, i64, i64)> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(p).ok()?;
    Some((m.dev(), m.ino(), m.ctime(), m.ctime_nsec()))
}

#[cfg(not(unix))]
fn file_id(p: &Path) -> Option<(u64, u64, i64, i64)> {
    let m = std::fs::metadata(p).ok()?;
    let t = m
        .modified()
        .ok()?
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?;
    Some((0, m.len(), t.as_secs() as i64, t.subsec_nanos() as i64))
}
