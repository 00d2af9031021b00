//! Test data shared by the renderer tests.

use brickyard_core::camera::{world_extent, Camera, Projection, Vec3};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::reference::{ChannelStyle, RenderMode, RenderParams, Volume};
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

/// The two channels' styles: channel 0 orange-red over 0–255, channel 1
/// cyan over 40–200.
pub fn two_channel_styles() -> Vec<ChannelStyle> {
    vec![
        ChannelStyle {
            channel: 0,
            color: [1.0, 0.2, 0.0],
            window: [0.0, 255.0],
            tf: None,
            levels: None,
        },
        ChannelStyle {
            channel: 1,
            color: [0.0, 0.8, 1.0],
            window: [40.0, 200.0],
            tf: None,
            levels: None,
        },
    ]
}

/// Views of the two-channel store (72×60, both channels added up), each
/// with the level it is drawn at and a pool budget: an oblique slice at
/// level 0 (its bricks and their stand-ins fit the whole volume's bytes),
/// a MIP at level 1 through a pool of half the volume.
pub fn two_channel_views(extent: Vec3) -> Vec<(RenderParams, usize, u64)> {
    let vol_bytes = 2 * 40 * 48 * 64;
    let tf = TransferFunction::preset("linear", [0.0, 255.0]).unwrap();
    let (origin, normal) = (
        [extent[0] * 0.5, extent[1] * 0.5, extent[2] * 0.45],
        [0.1, -0.05, 1.0],
    );
    let slice = (
        RenderMode::Slice { origin, normal },
        Camera::facing_plane(origin, normal, extent[0] * 1.1),
        0,
        vol_bytes,
    );
    let mip = (
        RenderMode::Mip,
        Camera::fit(
            extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 40.0 },
        ),
        1,
        vol_bytes / 2,
    );
    [slice, mip]
        .into_iter()
        .map(|(mode, cam, level, pool)| {
            let mut p = RenderParams::new(72, 60, cam, tf.clone(), mode);
            p.channels = two_channel_styles();
            (p, level, pool)
        })
        .collect()
}
