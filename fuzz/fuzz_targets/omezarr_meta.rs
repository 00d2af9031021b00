//! OME-Zarr group metadata: the JSON parsed and its `multiscales` read as a
//! Zarr v3 group (`zarr.json`) and as Zarr v2 attributes (`.zattrs`).
#![no_main]

use brickyard_store::omezarr;
use libfuzzer_sys::fuzz_target;
use serde_json::Value;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(j) = omezarr::parse_json(Path::new("zarr.json"), data) else {
        return;
    };
    if j.get("node_type").and_then(Value::as_str) == Some("group") {
        let attrs = j.get("attributes").cloned().unwrap_or(Value::Null);
        let _ = omezarr::parse_multiscale(Path::new("zarr.json"), 3, &attrs);
    }
    let _ = omezarr::parse_multiscale(Path::new(".zattrs"), 2, &j);
});
