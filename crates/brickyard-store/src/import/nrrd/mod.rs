//! NRRD importer: attached (`.nrrd`) and detached (`.nhdr`) headers, `raw` and
//! `gzip` encodings, read region by region with bounded memory.
//!
//! The header is parsed by hand following the NRRD0001..NRRD0005 format
//! (<https://teem.sourceforge.net/nrrd/format.html>):
//!
//! * fields `type`, `dimension`, `sizes`, `endian`, `encoding`, `byte skip`,
//!   `line skip`, `data file` (single file, `LIST [subdim]` and the printf form
//!   `fmt min max step [subdim]`), `space`, `space dimension`,
//!   `space directions`, `space origin`, `spacings`, `kinds`, `space units`,
//!   `units`; other standard fields (`content`, `centers`, `axis mins` ...),
//!   comments (`#`) and `key:=value` pairs are ignored. Field names are matched
//!   ignoring case, spaces and underscores, so `datafile` and `byteskip` work.
//! * NRRD lists axes fastest first (x, y, z); brickyard uses `[z, y, x]`.
//!   A 3-D file is one channel; a 2-D file is a single z slice. The first
//!   (fastest) axis becomes the channel axis when its kind is not a domain
//!   kind (`list`, `vector`, `RGB-color`, ...) or its space direction is
//!   `none`; the last (slowest) axis does when its kind says so explicitly.
//!   With that, 4-D files (and 3-D files holding a 2-D image with channels)
//!   are read; anything else is [`StoreError::Unsupported`].
//! * Spacing comes from the norms of `space directions` (so a flipped axis
//!   still has a positive spacing) or from `spacings`; a 2-D image gets a z
//!   spacing of 1. brickyard keeps only a scale and a translation: when
//!   every spatial axis points along its own world axis only, an axis that
//!   points backwards (a negative step) is read reversed
//!   (`import::flip::Flip`) and its origin moved to the file's last voxel
//!   along it, so that world positions are the file's (noted); rotations and
//!   permuted axes are dropped (noted):
//!   the origin of an axis is the `space origin` component along which that
//!   axis mostly points. Reversing z of gzip data reads the slices back to
//!   front, so each slab read decompresses the stream again from its start:
//!   such files convert correctly but more slowly.
//!   The unit comes from `space units` (or `units`); a `space` that is
//!   anatomical or `scanner-xyz`, given without units, means millimetres.
//!
//! Data access streams: `raw` data is read with positioned reads of just the
//! rows a region needs. `gzip` data cannot be seeked, so each source keeps a
//! decoder cursor and decompresses forwards, only as far as the last byte a
//! request needs; a request that lies before the cursor restarts the stream
//! from the beginning of its file. **For gzip input, read regions in
//! increasing z order** (as the pyramid builder does) or each backwards step
//! costs a fresh decompression from the start. Channels stored one after the
//! other get a cursor each; for interleaved channels the last decompressed
//! span is kept (at most twice the bytes of the region times the channel
//! count) so that reading the other channels of the same region is free.
//!
//! Files: `header` (the grammar), `fields` (what the fields mean: the
//! plan), `read` (locating and reading the data); tests in `tests/`.

mod fields;
mod header;
mod read;
#[cfg(test)]
mod tests;

use crate::error::{IoContext, Result};
use crate::import::flip::Flip;
use crate::source::SourceMeta;
use fields::interpret;
use header::read_header;
use read::{DataFile, GzState};
use std::fs::File;
use std::path::Path;
use std::sync::Mutex;

/// Open a NRRD file (`.nrrd` with attached data, or a detached `.nhdr`
/// header) and check that its data is present.
///
/// The header is parsed completely and validated; raw data files are checked
/// to be large enough, gzip data files to start with a gzip stream. Voxels
/// are read later, on demand, through [`VolumeSource::read_region`].
pub fn open(path: &Path) -> Result<NrrdSource> {
    let file = File::open(path).at(path)?;
    let header = read_header(path, &file)?;
    let plan = interpret(path, &header)?;
    NrrdSource::new(path, file, header.end, plan)
}

/// Parse and check a NRRD header held in memory (the start of a `.nrrd` file
/// or a whole `.nhdr`): everything [`open`] decides from the header alone,
/// without touching any data. `path` names the file in errors and anchors
/// relative data file names.
pub fn parse_header(path: &Path, bytes: &[u8]) -> Result<SourceMeta> {
    let header = read_header(path, bytes)?;
    Ok(interpret(path, &header)?.meta)
}

/// A NRRD volume opened for streaming reads; see the [module docs](self).
///
/// `read_region` may be called from several threads. For `gzip` data the
/// decoder state is shared behind a mutex, so such calls are serialised and
/// are cheapest in increasing z order.
pub struct NrrdSource {
    meta: SourceMeta,
    layout: Layout,
    encoding: Encoding,
    big_endian: bool,
    files: Vec<DataFile>,
    /// Payload bytes held by each data file (all files hold the same amount).
    per_file: u64,
    /// gzip only: decompressed bytes to skip at the start of each file.
    gz_skip: u64,
    /// Whether the data is in the header's own file.
    attached: bool,
    /// The data file kept open when there is a single raw one.
    raw_file: Option<File>,
    /// gzip decoder cursors: one per channel when channels are stored one
    /// after the other, else a single one.
    gz: Vec<Mutex<GzState>>,
    /// Axes read reversed (their space direction points backwards).
    flip: Flip,
    /// Number of gzip streams opened (tests check that reads stream forwards).
    #[cfg(test)]
    gz_opens: std::sync::atomic::AtomicUsize,
}

impl std::fmt::Debug for NrrdSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NrrdSource")
            .field("meta", &self.meta)
            .field("encoding", &self.encoding)
            .field("big_endian", &self.big_endian)
            .field("data_files", &self.files.len())
            .finish_non_exhaustive()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Raw,
    Gzip,
}

/// Where the voxels of one channel lie in the payload, in elements.
#[derive(Debug, Clone, Copy)]
struct Layout {
    /// Strides of z, y and x (z stride is 0 for a 2-D image).
    stride: [u64; 3],
    /// Offset between channels when they are stored one after the other.
    channel_stride: u64,
    /// Channels interleaved voxel by voxel (channel axis fastest).
    interleaved: bool,
}
