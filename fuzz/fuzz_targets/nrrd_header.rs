//! NRRD: the header parser on bytes, then the whole file (attached data)
//! opened and read.
#![no_main]

mod common;

use brickyard_store::import::nrrd;
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let _ = nrrd::parse_header(Path::new("fuzz.nrrd"), data);
    let p = common::write("f.nrrd", data);
    if let Ok(src) = nrrd::open(&p) {
        common::read_some(&src);
    }
});
