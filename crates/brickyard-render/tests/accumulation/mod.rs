//! The view that the accumulation tests share (`savr.rs` on the CPU,
//! `savr_device.rs` on the device): a generated 48×64×56 Marschner–Lobb
//! store in 16³ bricks, a faint transfer function (rays go deep before
//! they stop), a 40×30 perspective view.
#![allow(dead_code)]

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::cpu::Scene;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::Path;
use std::sync::atomic::AtomicBool;

pub fn session(store: &Path, pool_bytes: u64) -> Session {
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes,
        pt_cache_blocks: 256,
        request_cap: 64,
        upload_bytes_per_frame: 48 * 18 * 18 * 18 * 2,
    };
    Session::open(store, cfg, 8 << 20, 2).unwrap()
}

pub struct Fixture {
    pub _dir: tempfile::TempDir,
    pub store: std::path::PathBuf,
    pub levels: Vec<Volume>,
    pub scene: Scene,
    pub params: RenderParams,
    pub bytes: u64,
}

pub fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [48, 64, 56];
    let src = Procedural::new(Kind::MarschnerLobb, dims, DType::U8);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .collect();
    let extent = world_extent(dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    // A faint transfer function: rays go deep before they stop.
    let mut tf = TransferFunction::preset("viridis", [0.0, 255.0]).unwrap();
    scale_opacity(&mut tf, 0.25);
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut params = RenderParams::new(40, 30, cam, tf, RenderMode::Dvr);
    params.reference_step = Some(scene.voxel(0));
    let bytes = dims.iter().product::<u64>();
    Fixture {
        _dir: dir,
        store,
        levels,
        scene,
        params,
        bytes,
    }
}

pub fn scale_opacity(tf: &mut TransferFunction, s: f32) {
    for p in tf.opacity.iter_mut() {
        p[1] *= s;
    }
}
