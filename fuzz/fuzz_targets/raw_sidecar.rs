//! Raw volumes: the JSON sidecar parsed, then the raw file opened against
//! a data file of a fixed size and, when the sidecar describes a small
//! volume, against one of exactly the right size, and read.
#![no_main]

mod common;

use brickyard_store::import::raw::{self, RawOptions};
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(opts) = RawOptions::parse_sidecar(Path::new("fuzz.raw.json"), data) else {
        return;
    };
    let p = common::write("fixed.raw", &[7u8; 4096]);
    if let Ok(src) = raw::open(&p, &opts) {
        common::read_some(&src);
    }
    let [x, y, z] = opts.dims;
    let need = x
        .checked_mul(y)
        .and_then(|v| v.checked_mul(z))
        .and_then(|v| v.checked_mul(opts.channels as u64))
        .and_then(|v| v.checked_mul(opts.dtype.size() as u64))
        .and_then(|v| v.checked_add(opts.header_bytes));
    if let Some(n) = need.filter(|&n| n <= 1 << 20) {
        let bytes: Vec<u8> = (0..n).map(|i| i as u8).collect();
        let p = common::write("exact.raw", &bytes);
        if let Ok(src) = raw::open(&p, &opts) {
            common::read_some(&src);
        }
    }
});
