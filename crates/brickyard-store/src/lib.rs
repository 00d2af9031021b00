//! brickyard-store: OME-Zarr read/write, importers and the streaming
//! pyramid builder with per-brick statistics.

pub mod error;
pub mod import;
pub mod source;

pub use error::{Result, StoreError};
pub use source::{SourceMeta, VolumeSource};
