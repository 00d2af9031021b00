//! NIfTI-1/2 (`.nii`, gzip-compressed or not): the file opened (header
//! parsed and checked against the data) and read.
#![no_main]

mod common;

use brickyard_store::import::nifti;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let p = common::write("f.nii", data);
    if let Ok(src) = nifti::open(&p) {
        common::read_some(&src);
    }
});
