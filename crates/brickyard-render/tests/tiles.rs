//! Drawing again only the tiles that were not settled gives, frame after
//! frame while bricks stream in, exactly the image (and the same set of
//! unsettled tiles) that drawing the whole frame gives, in DVR, MIP and
//! slice mode; and the tiles left to draw shrink to none.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::cpu::{render_tiles, Lod, Scene, Tiles};
use brickyard_render::image::Image;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

#[test]
fn redrawing_unsettled_tiles_equals_whole_frames() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    let src = Procedural::new(Kind::Mandelbulb, [96; 3], DType::U16);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .collect();
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let tf = TransferFunction::preset("soft", [0.0, 65535.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let modes = [
        RenderMode::Dvr,
        RenderMode::Mip,
        RenderMode::Slice {
            origin: [extent[0] * 0.5, extent[1] * 0.45, extent[2] * 0.5],
            normal: [0.2, 1.0, 0.3],
        },
    ];
    for mode in modes {
        // A pool for everything, few bricks a frame: residency grows
        // over many frames.
        let cfg = VmConfig {
            brick: [8; 3],
            pool_bytes: 64 << 20,
            request_cap: 24,
            ..Default::default()
        };
        let mut s = Session::open(&store, cfg, 64 << 20, 2).unwrap();
        s.set_batch(Some(Duration::from_secs(30)));
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
        // 150 × 110: tiles cut at both edges.
        let mut p = RenderParams::new(150, 110, cam, tf.clone(), mode.clone());
        p.reference_step = Some(scene.voxel(0));
        let lod = Lod::Auto { bias: 0.0 };
        let mut img = Image::new(p.width, p.height);
        let mut tiles = Tiles::all(p.width, p.height);
        let total = tiles.count();
        let (mut drawn, mut frames, mut partial) = (0, 0, false);
        loop {
            s.begin_frame();
            let before = tiles.count();
            drawn += before;
            partial |= before > 0 && before < total;
            let (_, reqs) = render_tiles(s.vm(), &scene, &p, lod, &mut img, &mut tiles);
            // The whole frame, from nothing, on the same residency.
            let mut whole = Image::new(p.width, p.height);
            let mut all = Tiles::all(p.width, p.height);
            render_tiles(s.vm(), &scene, &p, lod, &mut whole, &mut all);
            assert_eq!(
                img.max_abs_diff(&whole),
                0.0,
                "{mode:?}, frame {frames}: tiles drawn again differ from the whole frame"
            );
            assert_eq!(tiles, all, "{mode:?}, frame {frames}: unsettled tiles");
            s.finish_frame(reqs.iter());
            frames += 1;
            if tiles.count() == 0 {
                break;
            }
            assert!(frames < 300, "{mode:?}: {} tiles unsettled", tiles.count());
        }
        assert!(
            frames >= 3,
            "{mode:?}: {frames} frames; the test needs streaming"
        );
        assert!(partial, "{mode:?}: no frame drew only some tiles");
        assert!(
            drawn < frames * total,
            "{mode:?}: {drawn} tiles drawn in {frames} frames of {total}"
        );
        let lit = img.rgba.iter().filter(|c| c[3] > 0.05).count();
        assert!(
            lit > img.rgba.len() / 20,
            "{mode:?}: {lit} pixels with content"
        );
    }
}
