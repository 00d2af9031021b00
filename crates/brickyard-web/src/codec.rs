//! Decoding chunks in the browser (pure Rust, no C): Blosc 1 frames with
//! LZ4, Zstandard or Zlib inside and byte shuffling, Zstandard and gzip
//! streams, Zarr v3 `bytes` endianness and CRC32C checksums. Every error
//! says what was wrong with the bytes.

use crate::zarr::Codec;
use std::io::Read;

fn u32_at(b: &[u8], o: usize) -> Option<u32> {
    Some(u32::from_le_bytes(b.get(o..o + 4)?.try_into().ok()?))
}

/// Decode one Blosc 1 frame (as numcodecs and zarrs write them).
pub fn blosc(src: &[u8]) -> Result<Vec<u8>, String> {
    if src.len() < 16 {
        return Err(format!(
            "blosc: a frame of {} bytes is shorter than its 16-byte header",
            src.len()
        ));
    }
    let flags = src[2];
    let typesize = (src[3] as usize).max(1);
    let nbytes = u32_at(src, 4).unwrap() as usize;
    let blocksize = u32_at(src, 8).unwrap() as usize;
    let cbytes = u32_at(src, 12).unwrap() as usize;
    if cbytes > src.len() {
        return Err(format!(
            "blosc: the header says {cbytes} compressed bytes, the frame has {}",
            src.len()
        ));
    }
    if nbytes > 1 << 31 {
        return Err(format!(
            "blosc: {nbytes} bytes decoded is more than a chunk can be"
        ));
    }
    let memcpyed = flags & 0x2 != 0;
    let shuffle = flags & 0x1 != 0;
    if flags & 0x4 != 0 {
        return Err(
            "blosc: bit shuffling is not supported in the browser (byte shuffling is)".into(),
        );
    }
    if memcpyed {
        let data = src
            .get(16..16 + nbytes)
            .ok_or("blosc: an uncompressed frame shorter than its size")?;
        return Ok(data.to_vec());
    }
    if nbytes == 0 {
        return Ok(vec![]);
    }
    if blocksize == 0 {
        return Err("blosc: block size 0".into());
    }
    let compressor = flags >> 5;
    let nblocks = nbytes.div_ceil(blocksize);
    let mut out = vec![0u8; nbytes];
    let mut tmp = vec![0u8; blocksize];
    let dont_split = flags & 0x10 != 0;
    for j in 0..nblocks {
        let bsize = if j + 1 == nblocks {
            nbytes - j * blocksize
        } else {
            blocksize
        };
        let start = u32_at(src, 16 + 4 * j).ok_or("blosc: block offsets cut short")? as usize;
        let nsplits =
            if !dont_split && typesize <= 16 && bsize / typesize >= 128 && bsize % typesize == 0 {
                typesize
            } else {
                1
            };
        let neblock = bsize / nsplits;
        let mut at = start;
        let dst: &mut [u8] = if shuffle && typesize > 1 {
            &mut tmp[..bsize]
        } else {
            &mut out[j * blocksize..j * blocksize + bsize]
        };
        for s in 0..nsplits {
            let cs = u32_at(src, at).ok_or("blosc: a stream's size cut short")? as usize;
            at += 4;
            let stream = src
                .get(at..at + cs)
                .ok_or("blosc: a stream runs past the frame")?;
            at += cs;
            let part = &mut dst[s * neblock..(s + 1) * neblock];
            if cs == neblock {
                part.copy_from_slice(stream);
                continue;
            }
            match compressor {
                1 => {
                    let n = lz4_flex::block::decompress_into(stream, part)
                        .map_err(|e| format!("blosc: LZ4 stream: {e}"))?;
                    if n != neblock {
                        return Err(format!("blosc: an LZ4 stream gave {n} bytes, not {neblock}"));
                    }
                }
                4 => {
                    let d = zstd(stream)?;
                    if d.len() != neblock {
                        return Err(format!("blosc: a Zstandard stream gave {} bytes, not {neblock}", d.len()));
                    }
                    part.copy_from_slice(&d);
                }
                3 => {
                    let mut d = vec![];
                    flate2::read::ZlibDecoder::new(stream)
                        .read_to_end(&mut d)
                        .map_err(|e| format!("blosc: zlib stream: {e}"))?;
                    if d.len() != neblock {
                        return Err(format!("blosc: a zlib stream gave {} bytes, not {neblock}", d.len()));
                    }
                    part.copy_from_slice(&d);
                }
                0 => return Err("blosc: the blosclz compressor is not supported in the browser (lz4, zstd and zlib are)".into()),
                2 => return Err("blosc: the snappy compressor is not supported in the browser (lz4, zstd and zlib are)".into()),
                c => return Err(format!("blosc: unknown compressor code {c}")),
            }
        }
        if shuffle && typesize > 1 {
            let o = &mut out[j * blocksize..j * blocksize + bsize];
            unshuffle(&tmp[..bsize], o, typesize);
        }
    }
    Ok(out)
}

/// Undo Blosc's byte shuffle of one block: byte `b` of element `i` sits
/// at `b · n + i` (`n` whole elements); a tail shorter than an element
/// is copied as it is.
pub fn unshuffle(src: &[u8], dst: &mut [u8], typesize: usize) {
    let n = src.len() / typesize;
    for i in 0..n {
        for b in 0..typesize {
            dst[i * typesize + b] = src[b * n + i];
        }
    }
    let tail = n * typesize;
    dst[tail..].copy_from_slice(&src[tail..]);
}

/// Decode a Zstandard frame.
pub fn zstd(src: &[u8]) -> Result<Vec<u8>, String> {
    let mut r = src;
    let mut d =
        ruzstd::decoding::StreamingDecoder::new(&mut r).map_err(|e| format!("zstd: {e}"))?;
    let mut out = vec![];
    d.read_to_end(&mut out).map_err(|e| format!("zstd: {e}"))?;
    Ok(out)
}

/// Decode a gzip (or, failing its magic bytes, zlib) stream.
pub fn gzip(src: &[u8]) -> Result<Vec<u8>, String> {
    let mut out = vec![];
    if src.starts_with(&[0x1f, 0x8b]) {
        flate2::read::GzDecoder::new(src)
            .read_to_end(&mut out)
            .map_err(|e| format!("gzip: {e}"))?;
    } else {
        flate2::read::ZlibDecoder::new(src)
            .read_to_end(&mut out)
            .map_err(|e| format!("zlib: {e}"))?;
    }
    Ok(out)
}

/// Run a codec chain backwards over `bytes` (the `bytes` codec's byte
/// order is returned: the caller swaps values when it is big-endian).
/// Sharding is not decoded here (the source reads shards piece by piece).
pub fn decode_chain(codecs: &[Codec], mut bytes: Vec<u8>) -> Result<(Vec<u8>, bool), String> {
    let mut big = false;
    for c in codecs.iter().rev() {
        bytes = match c {
            Codec::Blosc => blosc(&bytes)?,
            Codec::Zstd => zstd(&bytes)?,
            Codec::Gzip => gzip(&bytes)?,
            Codec::Crc32c => {
                if bytes.len() < 4 {
                    return Err("crc32c: fewer than 4 bytes".into());
                }
                let (body, sum) = bytes.split_at(bytes.len() - 4);
                let want = u32::from_le_bytes(sum.try_into().unwrap());
                let got = crc32c::crc32c(body);
                if got != want {
                    return Err(format!(
                        "crc32c: checksum {got:#010x} where {want:#010x} is stored (damaged bytes)"
                    ));
                }
                bytes.truncate(bytes.len() - 4);
                bytes
            }
            Codec::Bytes { big_endian } => {
                big = *big_endian;
                bytes
            }
            Codec::Sharding { .. } => return Err("sharding inside a shard is not supported".into()),
        };
    }
    Ok((bytes, big))
}

/// Swap every value of `es` bytes in place (big-endian to native).
pub fn swap_bytes(b: &mut [u8], es: usize) {
    if es > 1 {
        for v in b.chunks_exact_mut(es) {
            v.reverse();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unshuffle_reverses_the_shuffle() {
        let n = 10;
        let data: Vec<u8> = (0..(n * 4 + 3) as u8).collect();
        let mut shuffled = data.clone();
        for i in 0..n {
            for b in 0..4 {
                shuffled[b * n + i] = data[i * 4 + b];
            }
        }
        let mut out = vec![0; data.len()];
        unshuffle(&shuffled, &mut out, 4);
        assert_eq!(out, data);
    }

    #[test]
    fn damaged_frames_are_errors_not_panics() {
        assert!(blosc(&[2, 1, 0x21, 1]).is_err());
        let mut f = vec![2u8, 1, 0x20, 1];
        f.extend(1000u32.to_le_bytes());
        f.extend(1000u32.to_le_bytes());
        f.extend(24u32.to_le_bytes());
        f.extend(20u32.to_le_bytes());
        f.extend(4u32.to_le_bytes());
        assert!(blosc(&f).unwrap_err().contains("LZ4") || blosc(&f).is_err());
        assert!(zstd(b"not zstd").is_err());
    }
}
