//! In the browser (wasm32, run by `wasm-bindgen-test-runner` in headless
//! Chromium): a sharded Zarr v3 store held in memory is read through the
//! web client's `Fetch`, decoded, cut into bricks, streamed into the
//! virtual memory and drawn by the CPU renderer, compiled to WebAssembly;
//! bricks must equal clamped crops of the array and the complete image the
//! in-core reference. Natively this file is empty: `tests/source.rs`
//! checks the same path against the native loader.
#![cfg(target_arch = "wasm32")]

use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{Camera, Projection};
use brickyard_core::TransferFunction;
use brickyard_render::cpu::Lod;
use brickyard_render::{RenderMode, RenderParams, Volume};
use brickyard_web::session::{Spawn, WebSession};
use brickyard_web::source::{Fetch, LocalFuture, Range, WebSource};
use std::collections::HashMap;
use std::io::Write;
use std::rc::Rc;
use wasm_bindgen_test::*;

wasm_bindgen_test_configure!(run_in_browser);

const DIMS: [u64; 3] = [40, 36, 44];

fn value(z: u64, y: u64, x: u64) -> u16 {
    let (fz, fy, fx) = (z as f64 / 40.0, y as f64 / 36.0, x as f64 / 44.0);
    let r = ((fz - 0.5).powi(2) + (fy - 0.45).powi(2) + (fx - 0.55).powi(2)).sqrt();
    (60000.0 * (1.0 - (r / 0.6).min(1.0)).powi(2) + 300.0 * ((x * 7 + y * 3 + z) % 11) as f64)
        as u16
}

struct MemFetch(HashMap<String, Vec<u8>>);

impl Fetch for MemFetch {
    fn get(&self, path: &str, range: Range) -> LocalFuture<Result<Option<Vec<u8>>, String>> {
        let r = self.0.get(path).map(|b| match range {
            Range::All => b.clone(),
            Range::Span { start, len } => b[start as usize..(start + len) as usize].to_vec(),
            Range::Suffix(n) => b[b.len() - n as usize..].to_vec(),
        });
        Box::pin(async move { Ok(r) })
    }
}

/// Level `l`: 32³ shards of 16³ gzip chunks, index at the end with its
/// CRC32C; level 1 is level 0 subsampled.
fn store() -> MemFetch {
    let mut files = HashMap::new();
    files.insert(
        "zarr.json".to_string(),
        br#"{"zarr_format":3,"node_type":"group","attributes":{"ome":{"version":"0.5","multiscales":[{"axes":[{"name":"z","type":"space"},{"name":"y","type":"space"},{"name":"x","type":"space"}],"datasets":[{"path":"0","coordinateTransformations":[{"type":"scale","scale":[1,1,1]}]},{"path":"1","coordinateTransformations":[{"type":"scale","scale":[2,2,2]}]}]}]}}}"#.to_vec(),
    );
    for l in 0..2u64 {
        let d = DIMS.map(|v| v.div_ceil(1 << l));
        let at = |z: u64, y: u64, x: u64| value(z << l, y << l, x << l);
        files.insert(
            format!("{l}/zarr.json"),
            format!(r#"{{"zarr_format":3,"node_type":"array","shape":{d:?},"data_type":"uint16","chunk_grid":{{"name":"regular","configuration":{{"chunk_shape":[32,32,32]}}}},"chunk_key_encoding":{{"name":"default","configuration":{{"separator":"/"}}}},"fill_value":0,"codecs":[{{"name":"sharding_indexed","configuration":{{"chunk_shape":[16,16,16],"codecs":[{{"name":"bytes","configuration":{{"endian":"little"}}}},{{"name":"gzip","configuration":{{"level":1}}}}],"index_codecs":[{{"name":"bytes","configuration":{{"endian":"little"}}}},{{"name":"crc32c"}}],"index_location":"end"}}}}]}}"#).into_bytes(),
        );
        for sz in 0..d[0].div_ceil(32) {
            for sy in 0..d[1].div_ceil(32) {
                for sx in 0..d[2].div_ceil(32) {
                    let (mut body, mut index) = (vec![], vec![]);
                    for iz in 0..2 {
                        for iy in 0..2 {
                            for ix in 0..2 {
                                let o = [sz * 32 + iz * 16, sy * 32 + iy * 16, sx * 32 + ix * 16];
                                if (0..3).any(|a| o[a] >= d[a]) {
                                    index.extend(u64::MAX.to_le_bytes());
                                    index.extend(u64::MAX.to_le_bytes());
                                    continue;
                                }
                                let mut raw = vec![];
                                for z in o[0]..o[0] + 16 {
                                    for y in o[1]..o[1] + 16 {
                                        for x in o[2]..o[2] + 16 {
                                            let v = if z < d[0] && y < d[1] && x < d[2] {
                                                at(z, y, x)
                                            } else {
                                                0
                                            };
                                            raw.extend(v.to_le_bytes());
                                        }
                                    }
                                }
                                let mut e = flate2::write::GzEncoder::new(
                                    vec![],
                                    flate2::Compression::fast(),
                                );
                                e.write_all(&raw).unwrap();
                                let c = e.finish().unwrap();
                                index.extend((body.len() as u64).to_le_bytes());
                                index.extend((c.len() as u64).to_le_bytes());
                                body.extend(c);
                            }
                        }
                    }
                    let crc = crc32c::crc32c(&index);
                    body.extend(index);
                    body.extend(crc.to_le_bytes());
                    files.insert(format!("{l}/c/{sz}/{sy}/{sx}"), body);
                }
            }
        }
    }
    MemFetch(files)
}

async fn open() -> WebSource {
    WebSource::open(Rc::new(store()), 16, 1, 1 << 20)
        .await
        .expect("open")
}

#[wasm_bindgen_test]
async fn bricks_in_the_browser_equal_clamped_crops() {
    let src = open().await;
    let g = src.geometry.clone();
    assert_eq!(g.levels, vec![DIMS, [20, 18, 22]]);
    let p = g.padded();
    let mut checked = 0;
    for key in g.keys(0, 0) {
        let b = src.load(key).await.expect("brick");
        let dense = b.content.to_dense(g.voxels_per_brick() as usize, g.dtype);
        let po = g.padded_origin_of(&key);
        for i in 0..p[0] as i64 {
            for j in 0..p[1] as i64 {
                for k in 0..p[2] as i64 {
                    let cl = |v: i64, n: u64| v.clamp(0, n as i64 - 1) as u64;
                    let want = value(
                        cl(po[0] + i, DIMS[0]),
                        cl(po[1] + j, DIMS[1]),
                        cl(po[2] + k, DIMS[2]),
                    );
                    let o = (((i * p[1] as i64 + j) * p[2] as i64 + k) * 2) as usize;
                    assert_eq!(
                        u16::from_ne_bytes([dense[o], dense[o + 1]]),
                        want,
                        "{key:?} ({i},{j},{k})"
                    );
                }
            }
        }
        checked += 1;
    }
    assert_eq!(checked, 3 * 3 * 3);
}

/// Let the page's event loop run the loads.
async fn yield_now() {
    let p = js_sys::Promise::new(&mut |resolve, _| {
        web_sys::window()
            .unwrap()
            .set_timeout_with_callback_and_timeout_and_arguments_0(&resolve, 0)
            .unwrap();
    });
    wasm_bindgen_futures::JsFuture::from(p).await.unwrap();
}

#[wasm_bindgen_test]
async fn a_streamed_dvr_in_the_browser_equals_the_reference() {
    let src = Rc::new(open().await);
    let spawn: Spawn = Rc::new(wasm_bindgen_futures::spawn_local);
    // A pool of 64 bricks: the level-0 working set streams in.
    let cfg = VmConfig {
        brick: [16; 3],
        pool_bytes: 64 * 18 * 18 * 18 * 2,
        ..Default::default()
    };
    let mut s = WebSession::new(src, cfg, spawn, 8).expect("session");
    let e = s.scene.extent;
    let tf = TransferFunction::preset("soft", [0.0, 60000.0]).unwrap();
    let mut p = RenderParams::new(
        96,
        80,
        Camera::fit(e, 30.0, 20.0, Projection::Perspective { fov_y_deg: 35.0 }),
        tf,
        RenderMode::Dvr,
    );
    p.reference_step = Some(s.scene.voxel(0));
    let mut frames = 0;
    loop {
        yield_now().await;
        let out = s.frame_cpu(&p, Lod::Fixed(0));
        frames += 1;
        if out.complete {
            assert_eq!(out.bias, 0.0);
            break;
        }
        assert!(frames < 400, "not complete after 400 frames");
    }
    assert!(
        s.loads.loaded() > 8,
        "the view streamed only {} bricks",
        s.loads.loaded()
    );
    let vol = Volume::from_fn(DIMS, [1.0; 3], |z, y, x| value(z, y, x) as f32);
    let want = brickyard_render::render(&vol, &p);
    let got = s.image();
    let lit = want.rgba.iter().filter(|px| px[3] > 0.05).count();
    assert!(
        lit > 96 * 80 / 10,
        "the reference is nearly blank ({lit} lit pixels)"
    );
    let d = got
        .rgba
        .iter()
        .zip(&want.rgba)
        .flat_map(|(a, b)| (0..4).map(move |i| (a[i] - b[i]).abs()))
        .fold(0f32, f32::max);
    assert!(
        d <= 1e-4,
        "the browser's image differs from the reference by {d} after {frames} frames"
    );
}

/// The device side in the browser: WebGPU's adapter (SwiftShader in
/// headless Chromium, `--enable-unsafe-webgpu`) opens through the same
/// `Gpu` type, and the renderer's WGSL module (DVR, MIP, slices, the
/// octree traversal, accumulation) passes the browser's own shader
/// compiler, not only naga's validation: a step toward drawing through
/// WebGPU in the page, which waits on read-backs that do not block.
#[wasm_bindgen_test]
async fn the_renderers_wgsl_compiles_in_the_browsers_webgpu() {
    let gpu = brickyard_gpu::Gpu::new_web()
        .await
        .expect("a WebGPU adapter (run Chromium with --enable-unsafe-webgpu)");
    let scope = gpu.device.push_error_scope(wgpu::ErrorFilter::Validation);
    let _r = brickyard_render::gpu::GpuRenderer::new(&gpu);
    let err = scope.pop().await;
    assert!(
        err.is_none(),
        "the browser refused the render kernel on {}: {err:?}",
        gpu.describe()
    );
}

/// The other device kernels pass the browser's compiler too: the cache's
/// (LRU compaction, request lists, update step, page tables) and the
/// residency octree's update passes.
#[wasm_bindgen_test]
async fn the_cache_and_octree_kernels_compile_in_the_browsers_webgpu() {
    let gpu = brickyard_gpu::Gpu::new_web()
        .await
        .expect("a WebGPU adapter");
    for (name, src) in brickyard_gpu::shaders()
        .into_iter()
        .chain(brickyard_render::device_shaders())
    {
        let scope = gpu.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let _m = gpu
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(src.into()),
            });
        let err = scope.pop().await;
        assert!(err.is_none(), "the browser refused {name}: {err:?}");
    }
}
