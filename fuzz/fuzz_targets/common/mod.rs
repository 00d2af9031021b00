//! Helpers shared by the fuzz targets.

#![allow(dead_code)]

use brickyard_store::VolumeSource;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// A scratch directory of this fuzzing process (inputs that the parsers
/// only take as files are written here).
pub fn scratch() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("brickyard-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    })
}

/// Write `bytes` to `name` in the scratch directory and return its path.
pub fn write(name: &str, bytes: &[u8]) -> PathBuf {
    let p = scratch().join(name);
    if let Some(d) = p.parent() {
        std::fs::create_dir_all(d).unwrap();
    }
    std::fs::write(&p, bytes).unwrap();
    p
}

/// Most voxels read from an opened source per input.
const READ_VOXELS: u64 = 1 << 16;

/// Read from an opened source as the converter and the viewer do: a small
/// corner box (a part of a chunk, strip or shard) and the last voxel of
/// every channel (at most four), then the whole volume when it is small.
/// Errors are fine; panics are what the fuzzer looks for.
pub fn read_some(src: &dyn VolumeSource) {
    let m = src.meta().clone();
    let [dz, dy, dx] = m.dims;
    let es = m.dtype.size() as u64;
    let voxels = dz.saturating_mul(dy).saturating_mul(dx);
    // An importer must refuse a volume without voxels or channels.
    assert!(
        voxels > 0 && m.channels > 0,
        "an importer accepted an empty volume: {m:?}"
    );
    for c in 0..m.channels.min(4) {
        let (nz, ny, nx) = (dz.min(2), dy.min(3), dx.min(3));
        let mut out = vec![0u8; (nz * ny * nx * es) as usize];
        let _ = src.read_region(c, 0..nz, 0..ny, 0..nx, &mut out);
        let mut one = vec![0u8; es as usize];
        let _ = src.read_region(c, dz - 1..dz, dy - 1..dy, dx - 1..dx, &mut one);
        if voxels <= READ_VOXELS {
            let mut out = vec![0u8; (voxels * es) as usize];
            let _ = src.read_region(c, 0..dz, 0..dy, 0..dx, &mut out);
        }
    }
}
