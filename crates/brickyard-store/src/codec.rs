//! Compression of bricks (the inner chunks of a shard), through the codecs
//! of the `zarrs` crate so that what we write is exactly what Zarr readers
//! decode.

use brickyard_core::DType;
use serde_json::{json, Value};
use std::borrow::Cow;
use zarrs::array::codec::api::{BytesToBytesCodecTraits, CodecOptions};
use zarrs::array::codec::{
    BloscCodec, BloscCompressionLevel, BloscCompressor, BloscShuffleMode, ZstdCodec,
};

/// Compression of the bricks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Compression {
    /// blosc with LZ4 and byte shuffle (the default).
    Lz4,
    /// zstd at the given level.
    Zstd(i32),
    /// No compression.
    None,
}

impl Compression {
    /// What [`Compression::parse`] takes, for messages.
    pub const EXPECTED: &'static str = "lz4, zstd, zstd:LEVEL (LEVEL from -131072 to 22) or none";

    pub fn parse(s: &str) -> Option<Compression> {
        match s {
            "lz4" | "blosc" | "blosc-lz4" => Some(Compression::Lz4),
            "zstd" => Some(Compression::Zstd(3)),
            "none" | "raw" => Some(Compression::None),
            _ => {
                // zstd's levels: negative (fast) ones down to -131072, up
                // to 22 (what Zarr readers accept in the metadata).
                let l: i32 = s.strip_prefix("zstd:")?.parse().ok()?;
                (-131072..=22).contains(&l).then_some(Compression::Zstd(l))
            }
        }
    }

    /// The Zarr v3 codec list of an inner chunk (bytes codec first).
    pub fn codecs_json(self, dtype: DType) -> Value {
        let bytes = json!({"name": "bytes", "configuration": {"endian": "little"}});
        match self {
            Compression::Lz4 => json!([bytes, {"name": "blosc", "configuration": {
                "cname": "lz4", "clevel": 5, "shuffle": if dtype.size() > 1 {"shuffle"} else {"noshuffle"},
                "typesize": dtype.size(), "blocksize": 0}}]),
            Compression::Zstd(level) => json!([bytes, {"name": "zstd", "configuration": {
                "level": level, "checksum": false}}]),
            Compression::None => json!([bytes]),
        }
    }
}

/// Encodes bricks with a fixed compression.
pub struct BrickEncoder {
    kind: Kind,
}

enum Kind {
    Blosc(BloscCodec),
    Zstd(ZstdCodec),
    None,
}

impl BrickEncoder {
    pub fn new(c: Compression, dtype: DType) -> BrickEncoder {
        let kind = match c {
            Compression::Lz4 => Kind::Blosc(
                BloscCodec::new(
                    BloscCompressor::LZ4,
                    BloscCompressionLevel::try_from(5u8).expect("valid level"),
                    None,
                    if dtype.size() > 1 {
                        BloscShuffleMode::Shuffle
                    } else {
                        BloscShuffleMode::NoShuffle
                    },
                    Some(dtype.size()),
                )
                .expect("blosc lz4 is built in"),
            ),
            Compression::Zstd(l) => Kind::Zstd(ZstdCodec::new(l, false)),
            Compression::None => Kind::None,
        };
        BrickEncoder { kind }
    }

    /// Encode the little-endian bytes of one brick.
    pub fn encode(&self, raw: &[u8]) -> Vec<u8> {
        let opts = CodecOptions::default();
        match &self.kind {
            Kind::Blosc(c) => c
                .encode(Cow::Borrowed(raw), &opts)
                .expect("blosc encoding cannot fail")
                .into_owned(),
            Kind::Zstd(c) => c
                .encode(Cow::Borrowed(raw), &opts)
                .expect("zstd encoding cannot fail")
                .into_owned(),
            Kind::None => raw.to_vec(),
        }
    }
}
