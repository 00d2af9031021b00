//! Importers: one module per input format, each returning a [`VolumeSource`].

pub mod nifti;
pub mod nrrd;
pub mod tiff;

/// Reverse the byte order of every `size`-byte element of `buf` in place
/// (used for big-endian inputs).
pub fn swap_bytes_in_place(buf: &mut [u8], size: usize) {
    if size > 1 {
        for e in buf.chunks_exact_mut(size) {
            e.reverse();
        }
    }
}
