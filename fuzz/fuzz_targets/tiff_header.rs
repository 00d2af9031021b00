//! TIFF / BigTIFF: the file opened (IFD chain walked, every page checked)
//! and read.
#![no_main]

mod common;

use brickyard_store::import::tiff;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let p = common::write("f.tif", data);
    if let Ok(src) = tiff::open(&p) {
        common::read_some(&src);
    }
});
