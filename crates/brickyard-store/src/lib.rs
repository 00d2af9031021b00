//! brickyard-store: OME-Zarr read/write, importers and the streaming
//! pyramid builder with per-brick statistics.

pub mod brick_stats;
pub mod builder;
pub mod codec;
pub mod downsample;
pub mod error;
pub mod generate;
pub mod import;
pub mod info;
pub mod lock;
pub mod numcodecs_lz4;
pub mod omezarr;
pub mod shard;
pub mod source;
pub mod storage;

pub use builder::{convert, ConvertOptions, ConvertReport, NoProgress, Progress};
pub use codec::Compression;
pub use error::{Result, StoreError};
pub use source::{ChannelDisplay, SourceMeta, VolumeSource};
