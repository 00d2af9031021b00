//! The shard index reader: byte 0 picks the layout (bit 0: index at the
//! start, bit 1: big-endian, bit 2: no CRC32C), bytes 1-2 the number of
//! inner chunks (little-endian u16), the rest is the shard file. An index
//! that passes the check must only name bytes inside the shard's data.
#![no_main]

use brickyard_store::shard::{parse_index, IndexLayout, IndexLocation};
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if data.len() < 3 {
        return;
    }
    let layout = IndexLayout {
        entries: u16::from_le_bytes([data[1], data[2]]) as u64,
        location: if data[0] & 1 != 0 {
            IndexLocation::Start
        } else {
            IndexLocation::End
        },
        big_endian: data[0] & 2 != 0,
        crc32c: data[0] & 4 == 0,
    };
    let shard = &data[3..];
    if let Ok(index) = parse_index(Path::new("c/0/0/0"), shard, &layout) {
        let len = shard.len() as u64;
        let ib = layout.index_bytes();
        let data_range = match layout.location {
            IndexLocation::End => 0..len - ib,
            IndexLocation::Start => ib..len,
        };
        assert_eq!(index.len() as u64, layout.entries);
        for &[off, n] in &index {
            if off == u64::MAX && n == u64::MAX {
                continue;
            }
            assert!(off >= data_range.start && off + n <= data_range.end);
        }
    }
});
