//! numcodecs' LZ4 compressor, which older Zarr stores use (`"id": "lz4"` in
//! a Zarr v2 `.zarray`, `"name": "numcodecs.lz4"` in a Zarr v3 `zarr.json`
//! written by zarr-python): an LZ4 block after the decoded length as a
//! 4-byte little-endian integer.
//!
//! Registered with zarrs as a bytes-to-bytes codec, so that `convert`,
//! `info` and `info --check` read such stores as any other. The decoded
//! length in a chunk must be the length its array says a chunk holds:
//! a chunk that claims another length is refused before anything is
//! allocated for it, and so is an LZ4 block that decodes to fewer bytes.

use std::borrow::Cow;
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use zarrs::array::codec::api::{
    BytesToBytesCodecTraits, Codec, CodecError, CodecMetadataOptions, CodecOptions, CodecPluginV2,
    CodecPluginV3, CodecTraits, CodecTraitsV2, CodecTraitsV3, PartialDecoderCapability,
    PartialEncoderCapability, RecommendedConcurrency,
};
use zarrs::array::{ArrayBytesRaw, BytesRepresentation};
use zarrs::metadata::v2::MetadataV2;
use zarrs::metadata::v3::MetadataV3;
use zarrs::metadata::Configuration;
use zarrs::plugin::{PluginCreateError, ZarrVersion};

/// numcodecs' default acceleration (`LZ4(acceleration=1)`).
const DEFAULT_ACCELERATION: i64 = 1;

/// The numcodecs LZ4 codec. Its `acceleration` matters to an encoder only;
/// it is kept so that the metadata reads back as it was written.
#[derive(Clone, Debug)]
pub struct NumcodecsLz4 {
    acceleration: i64,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Lz4Configuration {
    #[serde(default = "default_acceleration")]
    acceleration: i64,
}

fn default_acceleration() -> i64 {
    DEFAULT_ACCELERATION
}

zarrs::plugin::impl_extension_aliases!(NumcodecsLz4,
    v3: "numcodecs.lz4", [],
    v2: "lz4", []
);

inventory::submit! {
    CodecPluginV3::new::<NumcodecsLz4>()
}

inventory::submit! {
    CodecPluginV2::new::<NumcodecsLz4>()
}

impl NumcodecsLz4 {
    fn from_configuration(c: Lz4Configuration) -> Arc<Self> {
        Arc::new(Self {
            acceleration: c.acceleration,
        })
    }
}

impl CodecTraitsV3 for NumcodecsLz4 {
    fn create(metadata: &MetadataV3) -> Result<Codec, PluginCreateError> {
        let c: Lz4Configuration = metadata.to_typed_configuration()?;
        Ok(Codec::BytesToBytes(Self::from_configuration(c)))
    }
}

impl CodecTraitsV2 for NumcodecsLz4 {
    fn create(metadata: &MetadataV2) -> Result<Codec, PluginCreateError> {
        let c: Lz4Configuration = metadata.to_typed_configuration()?;
        Ok(Codec::BytesToBytes(Self::from_configuration(c)))
    }
}

impl CodecTraits for NumcodecsLz4 {
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn configuration(
        &self,
        _version: ZarrVersion,
        _options: &CodecMetadataOptions,
    ) -> Option<Configuration> {
        let c = Lz4Configuration {
            acceleration: self.acceleration,
        };
        match serde_json::to_value(c) {
            Ok(serde_json::Value::Object(map)) => Some(map.into()),
            _ => None,
        }
    }

    fn partial_decoder_capability(&self) -> PartialDecoderCapability {
        PartialDecoderCapability {
            partial_read: false,
            partial_decode: false,
        }
    }

    fn partial_encoder_capability(&self) -> PartialEncoderCapability {
        PartialEncoderCapability {
            partial_encode: false,
        }
    }
}

/// The decoded length a numcodecs LZ4 chunk states, and its LZ4 block.
fn split_header(encoded: &[u8]) -> Result<(usize, &[u8]), String> {
    match encoded {
        [a, b, c, d, block @ ..] => Ok((u32::from_le_bytes([*a, *b, *c, *d]) as usize, block)),
        _ => Err(format!(
            "numcodecs lz4: a chunk of {} bytes, shorter than its 4-byte length header",
            encoded.len()
        )),
    }
}

/// Decode one numcodecs LZ4 chunk whose decoded length must be `expected`
/// bytes (`None`: the length its header states).
pub fn decode(encoded: &[u8], expected: Option<usize>) -> Result<Vec<u8>, String> {
    let (stated, block) = split_header(encoded)?;
    if let Some(n) = expected.filter(|&n| n != stated) {
        return Err(format!(
            "numcodecs lz4: the chunk states {stated} decoded bytes, its array's chunks hold {n}"
        ));
    }
    let mut out = vec![0u8; stated];
    let n = lz4_flex::block::decompress_into(block, &mut out)
        .map_err(|e| format!("numcodecs lz4: {e}"))?;
    if n != stated {
        return Err(format!(
            "numcodecs lz4: the chunk decodes to {n} bytes, its header states {stated}"
        ));
    }
    Ok(out)
}

/// Encode `decoded` as numcodecs does (length header, then one LZ4 block).
pub fn encode(decoded: &[u8]) -> Result<Vec<u8>, String> {
    let n = u32::try_from(decoded.len()).map_err(|_| {
        format!(
            "numcodecs lz4: a chunk of {} bytes, more than its 4-byte length header holds",
            decoded.len()
        )
    })?;
    let mut out = vec![0u8; 4 + lz4_flex::block::get_maximum_output_size(decoded.len())];
    out[..4].copy_from_slice(&n.to_le_bytes());
    let k = lz4_flex::block::compress_into(decoded, &mut out[4..])
        .map_err(|e| format!("numcodecs lz4: {e}"))?;
    out.truncate(4 + k);
    Ok(out)
}

impl BytesToBytesCodecTraits for NumcodecsLz4 {
    fn into_dyn(self: Arc<Self>) -> Arc<dyn BytesToBytesCodecTraits> {
        self as Arc<dyn BytesToBytesCodecTraits>
    }

    fn recommended_concurrency(
        &self,
        _decoded_representation: &BytesRepresentation,
    ) -> Result<RecommendedConcurrency, CodecError> {
        Ok(RecommendedConcurrency::new_maximum(1))
    }

    fn encode<'a>(
        &self,
        decoded_value: ArrayBytesRaw<'a>,
        _options: &CodecOptions,
    ) -> Result<ArrayBytesRaw<'a>, CodecError> {
        encode(&decoded_value)
            .map(Cow::Owned)
            .map_err(CodecError::Other)
    }

    fn decode<'a>(
        &self,
        encoded_value: ArrayBytesRaw<'a>,
        decoded_representation: &BytesRepresentation,
        _options: &CodecOptions,
    ) -> Result<ArrayBytesRaw<'a>, CodecError> {
        let expected = decoded_representation
            .size()
            .map(|n| usize::try_from(n).unwrap_or(usize::MAX));
        decode(&encoded_value, expected)
            .map(Cow::Owned)
            .map_err(CodecError::Other)
    }

    fn encoded_representation(
        &self,
        decoded_representation: &BytesRepresentation,
    ) -> BytesRepresentation {
        decoded_representation
            .size()
            .map_or(BytesRepresentation::UnboundedSize, |n| {
                let n = usize::try_from(n).unwrap_or(usize::MAX);
                BytesRepresentation::BoundedSize(
                    4 + lz4_flex::block::get_maximum_output_size(n) as u64,
                )
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bytes numcodecs 0.16.6 writes for `LZ4().encode(bytes(range(16)) * 4)`:
    /// the length 64, then one LZ4 block: a token (15+ literals, match of
    /// 4 + 15+ bytes), 15 + 1 literals, offset 16, match 4 + 15 + 24 = 43
    /// bytes, and the last sequence's token (5 literals) with its literals.
    #[test]
    fn decodes_the_bytes_numcodecs_writes() {
        let data: Vec<u8> = (0..16u8).cycle().take(64).collect();
        let mut chunk = vec![64, 0, 0, 0, 0xFF, 1];
        chunk.extend(0..16u8);
        chunk.extend([16, 0, 24, 0x50, 11, 12, 13, 14, 15]);
        assert_eq!(decode(&chunk, Some(64)).unwrap(), data);
        assert_eq!(decode(&chunk, None).unwrap(), data);
    }

    #[test]
    fn round_trips_and_refuses_what_does_not_fit() {
        let data: Vec<u8> = (0..10_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let enc = encode(&data).unwrap();
        assert_eq!(&enc[..4], &10_000u32.to_le_bytes());
        assert_eq!(decode(&enc, Some(data.len())).unwrap(), data);
        // Another length than the array's chunk: refused, nothing allocated for it.
        let e = decode(&enc, Some(9_999)).unwrap_err();
        assert!(e.contains("states 10000 decoded bytes"), "{e}");
        // A header that lies about the length of its block.
        let mut lie = enc.clone();
        lie[..4].copy_from_slice(&20_000u32.to_le_bytes());
        let e = decode(&lie, None).unwrap_err();
        assert!(e.contains("numcodecs lz4"), "{e}");
        // Truncated block, short header.
        assert!(decode(&enc[..enc.len() / 2], Some(data.len())).is_err());
        assert!(decode(&enc[..3], None)
            .unwrap_err()
            .contains("4-byte length header"));
    }

    #[test]
    fn zarr_metadata_of_either_version_makes_the_codec() {
        let v2: MetadataV2 = serde_json::from_str(r#"{"id": "lz4", "acceleration": 3}"#).unwrap();
        let Codec::BytesToBytes(c) = Codec::from_metadata(&v2).unwrap() else {
            panic!("lz4 is a bytes-to-bytes codec");
        };
        let conf = c
            .configuration_v3(&CodecMetadataOptions::default())
            .unwrap();
        assert_eq!(conf.get("acceleration"), Some(&serde_json::json!(3)));
        let v3: MetadataV3 = serde_json::from_str(r#"{"name": "numcodecs.lz4"}"#).unwrap();
        assert!(matches!(
            Codec::from_metadata(&v3).unwrap(),
            Codec::BytesToBytes(_)
        ));
        let bad: MetadataV3 = serde_json::from_str(
            r#"{"name": "numcodecs.lz4", "configuration": {"acceleration": "fast"}}"#,
        )
        .unwrap();
        assert!(Codec::from_metadata(&bad).is_err());
    }
}
