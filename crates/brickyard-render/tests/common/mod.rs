//! Test data shared by the renderer tests.

use brickyard_core::camera::{world_extent, Vec3};
use brickyard_core::{DType, Dims3};
use brickyard_render::reference::Volume;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

/// A two-channel u8 store in `dir` (a Mandelbulb, then a Marschner–Lobb,
/// 64×48×40, bricks 16³): the store, its world extent and the voxels of
/// each level.
pub fn two_channel_store(dir: &Path) -> (PathBuf, Vec3, Vec<Dims3>) {
    let dims = [40u64, 48, 64];
    let raw = dir.join("two.raw");
    let mut bytes = vec![];
    for kind in [Kind::Mandelbulb, Kind::MarschnerLobb] {
        let g = Procedural::new(kind, dims, DType::U8);
        for z in 0..dims[0] {
            for y in 0..dims[1] {
                for x in 0..dims[2] {
                    bytes.push((g.value(z, y, x) * 255.0).round() as u8);
                }
            }
        }
    }
    std::fs::write(&raw, &bytes).unwrap();
    let opts: brickyard_store::import::raw::RawOptions =
        serde_json::from_str(r#"{"dims":[64,48,40],"dtype":"u8","channels":2}"#).unwrap();
    let src = brickyard_store::import::raw::open(&raw, &opts).unwrap();
    let store = dir.join("two.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let extent = world_extent(dims, Volume::from_store(&store, 0, 0).unwrap().spacing);
    let levels = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap().dims)
        .collect();
    (store, extent, levels)
}
