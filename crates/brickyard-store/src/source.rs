//! The interface every importer implements: a volume that can be read
//! region by region, so that nothing ever has to hold a whole large volume.

use crate::error::Result;
use crate::import::scale::ValueScaling;
use brickyard_core::{DType, Dims3};
use std::ops::Range;
use std::path::PathBuf;

/// What an importer knows about its volume.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceMeta {
    /// The file or directory the volume comes from (used in error messages).
    pub path: PathBuf,
    /// Size in voxels, `[z, y, x]`.
    pub dims: Dims3,
    /// Number of channels (1 for a scalar volume).
    pub channels: usize,
    pub dtype: DType,
    /// Voxel spacing `[z, y, x]`, if the file stores one.
    pub spacing: Option<[f64; 3]>,
    /// Physical position of the centre of voxel (0,0,0), `[z, y, x]`, if known.
    pub origin: Option<[f64; 3]>,
    /// Unit of spacing and origin (an OME-NGFF unit name such as `millimeter`).
    pub unit: Option<String>,
    /// Per-channel names, if the file has them.
    pub channel_names: Vec<String>,
    /// How each channel is shown, where the file says (an OME-Zarr's
    /// `omero` channels): empty, or one entry per channel whose fields
    /// are `None` where the file gives none (the converter's defaults
    /// then apply).
    pub channel_display: Vec<ChannelDisplay>,
    /// Whether the volume holds labels (segmentation ids) rather than
    /// intensities; importers set this only when the file says so.
    pub labels: bool,
    /// The rescale of stored numbers into values that the file asks for,
    /// and whether the importer applied it (`dtype` is then the type of the
    /// rescaled values).
    pub scaling: Option<ValueScaling>,
    /// What the importer did, or deliberately did not do, with header fields
    /// that change what the values or positions mean: one sentence each,
    /// for the conversion report.
    pub notes: Vec<String>,
    /// Bytes one read may hold besides its output: the chunks a read is
    /// cut from, decoded whole (and their encoded bytes). The converter
    /// plans this much per thread.
    pub read_bytes: u64,
}

/// How a channel is shown by default, as far as a source says (OME-Zarr
/// `omero` metadata); a field left `None` takes the converter's default.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelDisplay {
    /// Linear RGB colour, 0–255.
    pub color: Option<[u8; 3]>,
    /// Data values `[start, end]` shown from black to full colour.
    pub window: Option<[f64; 2]>,
    /// Whether the channel is shown by default.
    pub active: Option<bool>,
}

impl ChannelDisplay {
    /// Whether the source says nothing of the channel.
    pub fn is_empty(&self) -> bool {
        self == &ChannelDisplay::default()
    }
}

impl SourceMeta {
    pub fn new(path: impl Into<PathBuf>, dims: Dims3, channels: usize, dtype: DType) -> Self {
        SourceMeta {
            path: path.into(),
            dims,
            channels,
            dtype,
            spacing: None,
            origin: None,
            unit: None,
            channel_names: Vec::new(),
            channel_display: Vec::new(),
            labels: false,
            scaling: None,
            notes: Vec::new(),
            read_bytes: 0,
        }
    }

    /// Bytes of one channel of the whole volume.
    pub fn channel_bytes(&self) -> u64 {
        self.dims.iter().product::<u64>() * self.dtype.size() as u64
    }

    /// This volume's grid (a missing spacing is 1, a missing origin 0).
    pub fn grid(&self) -> brickyard_core::grid::Grid<'_> {
        brickyard_core::grid::Grid {
            dims: self.dims,
            spacing: self.spacing.unwrap_or([1.0; 3]),
            origin: self.origin.unwrap_or([0.0; 3]),
            unit: self.unit.as_deref(),
        }
    }

    /// Whether `other` lies on this volume's grid
    /// ([`Grid::same_as`](brickyard_core::grid::Grid::same_as)).
    pub fn same_grid(&self, other: &SourceMeta) -> std::result::Result<(), String> {
        self.grid().same_as(&other.grid())
    }
}

/// A readable volume.
///
/// `read_region` fills `out` with the voxels of channel `c` in the box
/// `z × y × x` as a dense native-endian array in C order (x fastest).
/// `out.len()` equals the box's voxel count times the voxel size. Regions are
/// always inside the volume. Implementations must be callable from several
/// threads at once.
/// Why [`VolumeSource::chunk_absent`] calls a chunk absent.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Absence {
    /// The chunk's file (its shard's, when sharded) is gone.
    FileMissing,
    /// The file is there, but its shard's index has no entry for the chunk
    /// (the words say which inner chunk).
    NoEntry(String),
    /// The chunk was absent from what the read used (a shard index kept
    /// from before, while the file was missing or held no entry for it)
    /// but is in the file now: the source forgot what it kept, and a read
    /// again gets the data. The words say what changed.
    ChangedSince(String),
}

/// How the message of an [`Absence::ChangedSince`] read ends
/// ([`StoreError::Changed`](crate::StoreError::Changed)).
pub const READ_AGAIN: &str = "(it is read again next time)";

pub trait VolumeSource: Send + Sync {
    fn meta(&self) -> &SourceMeta;

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()>;

    /// Read `region` (`[z, y, x]` ranges) of channel `c` into a larger box
    /// of `dims` voxels (z, y, x order, C order) held by `out`, the
    /// region's first voxel at `at`; the rest of the box is left as it is.
    /// The loader reads a brick's apron this way, straight into the
    /// brick's final layout. The default reads the region into a buffer
    /// and copies it row by row; sources that can write into the box
    /// directly override it.
    fn read_region_into(
        &self,
        c: usize,
        region: [Range<u64>; 3],
        out: &mut [u8],
        dims: Dims3,
        at: Dims3,
    ) -> Result<()> {
        read_region_into_by_copy(self, c, region, out, dims, at)
    }

    /// The box shape `[z, y, x]` the source reads most efficiently, e.g.
    /// whole slices for a stack of images or one chunk for a Zarr array.
    /// The pyramid builder uses it to choose its read pattern.
    fn preferred_read(&self) -> Dims3 {
        let d = self.meta().dims;
        [1, d[1], d[2]]
    }

    /// Whether the store has no data for the chunk that holds voxel `v`
    /// (`[z, y, x]`) of channel `c`, for sources stored as files of chunks
    /// or shards: `Some((file, why))` when its file is missing or its
    /// shard's index has no entry for it ([`Absence`]). A Zarr reader reads such a chunk as the
    /// fill value; callers that know data should be there (the store's
    /// statistics say so) report it. `None`: present, or not such a source.
    fn chunk_absent(&self, _c: usize, _v: Dims3) -> Option<(std::path::PathBuf, Absence)> {
        None
    }

    /// The file that holds the chunk of voxel `v` of channel `c` (its
    /// shard's, when sharded), for sources stored as files; `None`
    /// otherwise. For reports.
    fn chunk_file(&self, _c: usize, _v: Dims3) -> Option<std::path::PathBuf> {
        None
    }

    /// A hint that `region` (`[z, y, x]` ranges) of channel `c` will be
    /// read soon: sources on disk ask the system to start reading its
    /// stored bytes now, without waiting, so that the read finds them in
    /// memory. The loader hints the bricks queued next while it decodes
    /// the current ones, which keeps the disk busy beside the cores.
    /// Returns how many byte ranges were hinted (0: nothing to do, the
    /// default). Only a hint: errors surface when the region is read.
    fn prefetch(&self, _c: usize, _region: [Range<u64>; 3]) -> usize {
        0
    }
}

/// Check that a region request is inside the volume and that the buffer has
/// the right size. Importers call this first in `read_region`.
pub fn check_region(
    meta: &SourceMeta,
    c: usize,
    z: &Range<u64>,
    y: &Range<u64>,
    x: &Range<u64>,
    out: &[u8],
) {
    assert!(c < meta.channels, "channel {c} out of range");
    for (r, d) in [z, y, x].iter().zip(meta.dims) {
        assert!(
            r.start <= r.end && r.end <= d,
            "region {r:?} outside 0..{d}"
        );
    }
    let n = (z.end - z.start) * (y.end - y.start) * (x.end - x.start);
    assert_eq!(
        out.len() as u64,
        n * meta.dtype.size() as u64,
        "buffer size"
    );
}

/// Check a [`VolumeSource::read_region_into`] request: the region inside
/// the volume, the box large enough for it at `at`, the buffer the box's
/// size.
pub fn check_box(
    meta: &SourceMeta,
    c: usize,
    region: &[Range<u64>; 3],
    out: &[u8],
    dims: Dims3,
    at: Dims3,
) {
    assert!(c < meta.channels, "channel {c} out of range");
    for a in 0..3 {
        let r = &region[a];
        assert!(
            r.start <= r.end && r.end <= meta.dims[a],
            "region {r:?} outside 0..{}",
            meta.dims[a]
        );
        assert!(
            at[a] + (r.end - r.start) <= dims[a],
            "region {r:?} at {} outside a box of {}",
            at[a],
            dims[a]
        );
    }
    assert_eq!(
        out.len() as u64,
        dims.iter().product::<u64>() * meta.dtype.size() as u64,
        "buffer size"
    );
}

/// [`VolumeSource::read_region_into`] by a read into a buffer and a copy.
pub fn read_region_into_by_copy<S: VolumeSource + ?Sized>(
    src: &S,
    c: usize,
    region: [Range<u64>; 3],
    out: &mut [u8],
    dims: Dims3,
    at: Dims3,
) -> Result<()> {
    check_box(src.meta(), c, &region, out, dims, at);
    let es = src.meta().dtype.size();
    let r: Dims3 = [0, 1, 2].map(|a| region[a].end - region[a].start);
    let mut buf = vec![0u8; (r.iter().product::<u64>() as usize) * es];
    let [z, y, x] = region;
    src.read_region(c, z, y, x, &mut buf)?;
    let row = r[2] as usize * es;
    if row == 0 {
        return Ok(());
    }
    for (i, src_row) in buf.chunks_exact(row).enumerate() {
        let (k, j) = (i as u64 / r[1].max(1), i as u64 % r[1].max(1));
        let o = (((at[0] + k) * dims[1] + at[1] + j) * dims[2] + at[2]) as usize * es;
        out[o..o + row].copy_from_slice(src_row);
    }
    Ok(())
}

/// Helpers for importer tests.
#[cfg(test)]
pub(crate) mod test_util {
    use super::VolumeSource;
    use brickyard_core::Dims3;

    /// Read the whole of channel `c`.
    pub fn read_all(src: &dyn VolumeSource, c: usize) -> Vec<u8> {
        let m = src.meta();
        let mut out = vec![0u8; m.channel_bytes() as usize];
        let [z, y, x] = m.dims;
        src.read_region(c, 0..z, 0..y, 0..x, &mut out).unwrap();
        out
    }

    /// Read channel `c` block by block, last block first (so that requests
    /// go backwards), and stitch the blocks together.
    pub fn read_stitched(src: &dyn VolumeSource, c: usize, block: Dims3) -> Vec<u8> {
        let m = src.meta();
        let s = m.dtype.size();
        let d = m.dims;
        let mut out = vec![0u8; m.channel_bytes() as usize];
        let mut boxes = Vec::new();
        for z0 in (0..d[0]).step_by(block[0] as usize) {
            for y0 in (0..d[1]).step_by(block[1] as usize) {
                for x0 in (0..d[2]).step_by(block[2] as usize) {
                    boxes.push([
                        z0..(z0 + block[0]).min(d[0]),
                        y0..(y0 + block[1]).min(d[1]),
                        x0..(x0 + block[2]).min(d[2]),
                    ]);
                }
            }
        }
        boxes.reverse();
        for [z, y, x] in boxes {
            let (nz, ny, nx) = (z.end - z.start, y.end - y.start, x.end - x.start);
            let mut buf = vec![0u8; (nz * ny * nx) as usize * s];
            src.read_region(c, z.clone(), y.clone(), x.clone(), &mut buf)
                .unwrap();
            for k in 0..nz {
                for j in 0..ny {
                    let src_off = ((k * ny + j) * nx) as usize * s;
                    let dst_off =
                        (((z.start + k) * d[1] + y.start + j) * d[2] + x.start) as usize * s;
                    out[dst_off..dst_off + nx as usize * s]
                        .copy_from_slice(&buf[src_off..src_off + nx as usize * s]);
                }
            }
        }
        out
    }
}
