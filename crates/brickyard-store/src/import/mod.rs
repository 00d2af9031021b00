//! Importers: one module per input format, each returning a [`VolumeSource`].

mod chunks;
mod flip;
pub mod nifti;
pub mod nrrd;
pub mod raw;
pub mod scale;
pub mod stack;
pub mod tiff;
pub mod zarr;

/// Most bytes a deflate stream (gzip, zlib) inflates to per byte of input:
/// the longest match, 258 bytes, coded in 2 bits. A gzip file of `n` bytes
/// cannot hold more than `n × MAX_DEFLATE_RATIO` bytes of data, so a header
/// claiming more is refused before anything is decompressed.
pub const MAX_DEFLATE_RATIO: u64 = 1032;

/// Reverse the byte order of every `size`-byte element of `buf` in place
/// (used for big-endian inputs).
pub fn swap_bytes_in_place(buf: &mut [u8], size: usize) {
    if size > 1 {
        for e in buf.chunks_exact_mut(size) {
            e.reverse();
        }
    }
}

use crate::error::{IoContext, Result, StoreError};
use crate::source::VolumeSource;
use std::io::Read;
use std::path::Path;

/// How to read an input whose format cannot describe itself (raw), and
/// which level of a multiscale input to take.
#[derive(Debug, Clone, Default)]
pub struct ImportOptions {
    /// Raw description from the command line; a `FILE.json` sidecar is used
    /// when this is `None`.
    pub raw: Option<raw::RawOptions>,
    /// Level of an OME-Zarr input to read (0 = full resolution).
    pub zarr_level: usize,
    /// Keep the numbers as stored: do not apply a rescale the file asks for
    /// (NIfTI `scl_slope`/`scl_inter`).
    pub raw_values: bool,
}

/// The input formats brickyard reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Raw,
    Tiff,
    TiffGlob,
    TiffDir,
    Nrrd,
    Nifti,
    Zarr,
}

impl Format {
    /// The format as messages name an input of it ("a TIFF file").
    pub fn describe(self) -> &'static str {
        match self {
            Format::Raw => "raw data",
            Format::Tiff => "a TIFF file",
            Format::TiffGlob | Format::TiffDir => "a stack of TIFF slices",
            Format::Nrrd => "an NRRD file",
            Format::Nifti => "a NIfTI file",
            Format::Zarr => "a Zarr store",
        }
    }
}

/// Decide the format of `path` from its name and first bytes.
pub fn detect(path: &Path) -> Result<Format> {
    let s = path.to_string_lossy();
    if s.contains('*') || s.contains('?') {
        return Ok(Format::TiffGlob);
    }
    // A class (`img_[0-2].tif`) unless a file is named so.
    let remote = crate::storage::is_remote(path);
    if s.contains('[') && !path.exists() && !remote {
        return Ok(Format::TiffGlob);
    }
    if s.contains('{') && !path.exists() && !remote {
        return Err(StoreError::unsupported(
            path,
            "glob",
            "patterns take *, ? and [...] (no file is named so, and {...} lists are not \
             patterns here): e.g. 'slices/img_*.tif'",
        ));
    }
    if crate::storage::is_remote(path) {
        if zarr::is_zarr(path) {
            return Ok(Format::Zarr);
        }
        return Err(StoreError::unsupported(
            path,
            "input",
            "a URL is read only as a Zarr store, and no zarr.json, .zarray or .zgroup \
             could be read under it",
        ));
    }
    if path.is_dir() {
        if zarr::is_zarr(path) {
            return Ok(Format::Zarr);
        }
        return Ok(Format::TiffDir);
    }
    let lower = s.to_ascii_lowercase();
    let mut magic = [0u8; 4];
    let n = std::fs::File::open(path)
        .at(path)?
        .read(&mut magic)
        .at(path)?;
    let magic = &magic[..n];
    if magic.starts_with(b"NRRD") || lower.ends_with(".nrrd") || lower.ends_with(".nhdr") {
        return Ok(Format::Nrrd);
    }
    if magic.starts_with(b"II*\0")
        || magic.starts_with(b"MM\0*")
        || magic.starts_with(b"II+\0")
        || magic.starts_with(b"MM\0+")
    {
        return Ok(Format::Tiff);
    }
    if lower.ends_with(".nii") || lower.ends_with(".nii.gz") || lower.ends_with(".hdr") {
        return Ok(Format::Nifti);
    }
    if lower.ends_with(".tif") || lower.ends_with(".tiff") {
        return Ok(Format::Tiff);
    }
    Ok(Format::Raw)
}

/// Open any supported input. Options that do not apply to its format are
/// refused, not ignored.
pub fn open_input(path: &Path, opts: &ImportOptions) -> Result<Box<dyn VolumeSource>> {
    let fmt = detect(path)?;
    if opts.zarr_level > 0 && fmt != Format::Zarr {
        return Err(StoreError::invalid(
            path,
            "level",
            format!(
                "picks a level of a Zarr/OME-Zarr input, and this input is read as {}",
                fmt.describe()
            ),
        ));
    }
    if opts.raw_values && fmt != Format::Nifti {
        return Err(StoreError::invalid(
            path,
            "raw values",
            format!(
                "keep a NIfTI file's numbers without its scl_slope/scl_inter, and this input is read as {}",
                fmt.describe()
            ),
        ));
    }
    if opts.raw.is_some() && fmt != Format::Raw {
        return Err(StoreError::invalid(
            path,
            "raw description",
            format!(
                "describes raw data, and this input is read as {} (its header describes it)",
                fmt.describe()
            ),
        ));
    }
    Ok(match fmt {
        Format::Raw => {
            let ro = match &opts.raw {
                Some(r) => r.clone(),
                None => {
                    let side = raw::RawOptions::sidecar_path(path);
                    if !side.exists() {
                        return Err(StoreError::invalid(
                            path,
                            "format",
                            format!(
                                "not a TIFF, NRRD, NIfTI or Zarr input; for raw data give --dims, --dtype \
                                 (and --endian, --spacing) or write a sidecar {}",
                                side.display()
                            ),
                        ));
                    }
                    raw::RawOptions::read_sidecar(&side)?
                }
            };
            Box::new(raw::open(path, &ro)?)
        }
        Format::Tiff | Format::TiffDir => Box::new(tiff::open(path)?),
        Format::TiffGlob => Box::new(tiff::open_glob(&path.to_string_lossy())?),
        Format::Nrrd => Box::new(nrrd::open(path)?),
        Format::Nifti => Box::new(nifti::open_with(path, opts.raw_values)?),
        Format::Zarr => {
            // A brickyard store's lost chunks fail the conversion instead
            // of passing for empty.
            let mut src = zarr::open(path, opts.zarr_level)?;
            src.check_against_stats();
            Box::new(src)
        }
    })
}
