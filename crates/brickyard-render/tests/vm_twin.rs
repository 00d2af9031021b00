//! The reference renderer's sampler and the virtual memory's lookup use the
//! same clamp-to-edge trilinear rule: fully resident, they agree bit for bit.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::DType;
use brickyard_render::reference::Volume;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::sync::atomic::AtomicBool;

#[test]
fn resident_virtual_memory_samples_equal_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("t.ome.zarr");
    let src = Procedural::new(Kind::MarschnerLobb, [30, 41, 52], DType::U16);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..3)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let cfg = VmConfig {
        brick: [8; 3],
        pool_bytes: 64 << 20,
        pt_cache_blocks: 1024,
        request_cap: 4096,
        upload_bytes_per_frame: u64::MAX,
        max_dir_entries: 16,
        ..Default::default()
    };
    let mut s = Session::open(&store, cfg, 64 << 20, 2).unwrap();
    let mut r = 1u64;
    let mut next = move || {
        r = r
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (r >> 11) as f64 / (1u64 << 53) as f64 * 1.2 - 0.1
    };
    let pts: Vec<(usize, [f64; 3])> = (0..5000)
        .map(|i| (i % 3, [next(), next(), next()]))
        .collect();
    for frame in 0..500 {
        s.begin_frame();
        let mut req = s.vm().requests();
        let mut exact = 0;
        for &(l, p) in &pts {
            let got = s.vm().sample(l, 0, p, true, &mut req);
            if got.level == Some(l as u8) {
                let want = levels[l].sample(p);
                assert_eq!(got.value.to_bits(), want.to_bits(), "level {l} p {p:?}");
                exact += 1;
            }
        }
        s.finish_frame([&req]);
        if exact == pts.len() {
            return;
        }
        assert!(frame < 499, "never fully resident");
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
}
