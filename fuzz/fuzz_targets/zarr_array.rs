//! Zarr arrays: the input is an array's metadata (`zarr.json`, or
//! `.zarray` when it says `"zarr_format": 2`), then a NUL byte, then the
//! bytes of its first chunk (or shard). The array is opened as an importer
//! would and read, through the shard index check for sharded arrays.
#![no_main]

mod common;

use brickyard_store::import::zarr::ZarrSource;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let (meta, chunk) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let dir = common::scratch().join("array");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let j = serde_json::from_slice::<serde_json::Value>(meta).ok();
    let v2 = j.as_ref().and_then(|j| j.get("zarr_format")?.as_u64()) == Some(2);
    let name = if v2 { ".zarray" } else { "zarr.json" };
    std::fs::write(dir.join(name), meta).unwrap();
    // The first chunk, under the default key encoding for the shape's axes.
    let n = j
        .as_ref()
        .and_then(|j| j.get("shape")?.as_array().map(Vec::len))
        .unwrap_or(0);
    if (1..=8).contains(&n) {
        let key = if v2 {
            vec!["0"; n].join(".")
        } else {
            format!("c/{}", vec!["0"; n].join("/"))
        };
        let p = dir.join(key);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, chunk).unwrap();
    }
    if let Ok(src) = ZarrSource::open_level_array(&dir) {
        common::read_some(&src);
    }
});
