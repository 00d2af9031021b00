//! Sort-last rendering in one process, against the single render: the
//! volume split into k-d regions, each region drawn alone (rays clipped to
//! its box, on the whole ray's step grid), the partial images composited
//! in visibility order — plainly, by binary swap and by direct send —
//! equal the image of the whole volume within 1e-5: DVR without early
//! termination, MIP by the maxima before the transfer function.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_dist::composite::{in_order, simulate_binary_swap, simulate_direct_send, Operator};
use brickyard_dist::kd::{eye_side, KdTree};
use brickyard_render::cpu::{render_tiles, Lod, Scene, Tiles};
use brickyard_render::image::Image;
use brickyard_render::optics::mip_color;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// Draw `p` until every tile is settled (a pool that holds everything).
fn complete(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> Image {
    let mut img = Image::new(p.width, p.height);
    let mut tiles = Tiles::all(p.width, p.height);
    for _ in 0..200 {
        s.begin_frame();
        let (_, reqs) = render_tiles(s.vm(), scene, p, lod, &mut img, &mut tiles);
        s.finish_frame(reqs.iter());
        if tiles.count() == 0 {
            return img;
        }
    }
    panic!("the view did not complete");
}

/// The world box `[x, y, z]` of a region of `brick`-voxel bricks.
fn world_box(
    r: &brickyard_dist::kd::Region,
    brick: u64,
    dims: [u64; 3],
    spacing: [f64; 3],
) -> [[f64; 3]; 2] {
    let (lo, hi) = r.voxels([brick; 3], dims);
    let w = |v: [u64; 3]| [0, 1, 2].map(|a| v[2 - a] as f64 * spacing[2 - a]);
    [w(lo), w(hi)]
}

#[test]
fn regions_composited_in_visibility_order_equal_the_whole_render() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    let dims = [72, 80, 96];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U16);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .collect();
    let spacing = levels[0].spacing;
    let extent = world_extent(levels[0].dims, spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let cfg = VmConfig {
        brick: [8; 3],
        pool_bytes: 64 << 20,
        request_cap: 4096,
        ..Default::default()
    };
    let mut s = Session::open(&store, cfg, 64 << 20, 2).unwrap();
    s.set_batch(Some(Duration::from_secs(30)));
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    let tf = TransferFunction::preset("soft", [0.0, 65535.0]).unwrap();
    let brick = 8u64;
    let nb = dims.map(|d| d.div_ceil(brick));
    let lod = Lod::Auto { bias: 0.0 };
    for (azimuth, elevation, ortho) in [
        (30.0, 20.0, false),
        (-120.0, -35.0, false),
        (75.0, 60.0, true),
    ] {
        let projection = if ortho {
            Projection::Orthographic {
                height: extent[1] * 1.3,
            }
        } else {
            Projection::Perspective { fov_y_deg: 35.0 }
        };
        let cam = Camera::fit(extent, azimuth, elevation, projection);
        // The eye for the order: far back along the view for orthographic.
        let eye = if ortho {
            let d: Vec<f64> = (0..3).map(|a| cam.target[a] - cam.eye[a]).collect();
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            [0, 1, 2].map(|a| cam.target[a] - d[a] / l * 1e7)
        } else {
            cam.eye
        };
        for mip in [false, true] {
            let mode = if mip {
                RenderMode::Mip
            } else {
                RenderMode::Dvr
            };
            let mut p = RenderParams::new(90, 70, cam, tf.clone(), mode);
            p.reference_step = Some(scene.voxel(0));
            p.early_termination = false;
            let whole = complete(&mut s, &scene, &p, lod);
            let lit = whole.rgba.iter().filter(|c| c[3] > 0.05).count();
            assert!(lit > whole.rgba.len() / 10, "{lit} pixels drawn");
            for n in [1usize, 2, 3, 4, 5, 8] {
                let tree = KdTree::build(nb, n, &|_| 1.0);
                let side = eye_side(eye, [brick; 3], spacing);
                let order = tree.order(&side);
                let parts: Vec<Vec<[f32; 4]>> = tree
                    .regions()
                    .iter()
                    .map(|r| {
                        let mut q = p.clone();
                        q.clip = Some(Box::new(world_box(r, brick, dims, spacing)));
                        q.mip_values = mip;
                        q.validate().unwrap();
                        complete(&mut s, &scene, &q, lod).rgba
                    })
                    .collect();
                let op = if mip { Operator::Max } else { Operator::Over };
                let front = |a: std::ops::Range<usize>, b: std::ops::Range<usize>| {
                    tree.front(a, b, &side).unwrap()
                };
                let mut results = vec![
                    ("in order", in_order(op, &parts, &order)),
                    ("direct send", simulate_direct_send(op, &parts, &order)),
                ];
                if n.is_power_of_two() {
                    results.push(("binary swap", simulate_binary_swap(op, &parts, &front)));
                }
                for (how, mut img) in results {
                    if mip {
                        for px in &mut img {
                            *px = mip_color(&tf, px[3] > 0.0, px[0]);
                        }
                    }
                    let got = Image {
                        width: p.width,
                        height: p.height,
                        rgba: img,
                    };
                    let d = got.max_abs_diff(&whole);
                    assert!(
                        d <= 1e-5,
                        "{} az {azimuth} ortho {ortho}, {n} regions, {how}: max abs diff {d}",
                        if mip { "MIP" } else { "DVR" }
                    );
                }
            }
        }
    }
    // A wrong order is caught: back to front differs.
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let mut p = RenderParams::new(90, 70, cam, tf.clone(), RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    p.early_termination = false;
    let whole = complete(&mut s, &scene, &p, lod);
    let tree = KdTree::build(nb, 4, &|_| 1.0);
    let mut order = tree.order(&eye_side(cam.eye, [brick; 3], spacing));
    order.reverse();
    let parts: Vec<Vec<[f32; 4]>> = tree
        .regions()
        .iter()
        .map(|r| {
            let mut q = p.clone();
            q.clip = Some(Box::new(world_box(r, brick, dims, spacing)));
            complete(&mut s, &scene, &q, lod).rgba
        })
        .collect();
    let wrong = Image {
        width: p.width,
        height: p.height,
        rgba: in_order(Operator::Over, &parts, &order),
    };
    assert!(wrong.max_abs_diff(&whole) > 0.05);
}
