//! `brickyard bench views`: several views in one frame against one view
//! and against the views drawn one by one, warm (every brick resident):
//! an N-view super-slice (the thesis's multi-view microscope: Δx = 4
//! pixels, Δz = 1 slice) against one plain slice, one view of the
//! super-slice drawn alone and the N views drawn alone one after the
//! other; stereo DVR against mono DVR. Also from cold: the bricks the
//! N-view frame reads against one view's (shared, not N times).

use crate::vmbench::store;
use anyhow::Result;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{length, scale, sub, world_extent, Camera, Projection};
use brickyard_core::views::Views;
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::reference::{RenderMode, RenderParams};
use brickyard_store::import::zarr;
use brickyard_store::VolumeSource;
use serde_json::json;
use std::path::Path;

/// One case: a name and its parameters.
struct Case {
    name: String,
    params: Vec<RenderParams>,
}

pub fn views(
    dir: &Path,
    dims: Dims3,
    dtype: DType,
    image: [u32; 2],
    count: u32,
    repeat: usize,
    backends: &[String],
) -> Result<()> {
    let st = store(dir, dims, dtype)?;
    let spacing = zarr::open(&st, 0)?.meta().spacing.unwrap_or([1.0; 3]);
    let mut levels = vec![];
    while let Ok(s) = zarr::open(&st, levels.len()) {
        levels.push(s.meta().dims);
    }
    let extent = world_extent(dims, spacing);
    let mut scene = Scene::new(extent, levels);
    let max = match dtype {
        DType::U8 => 255.0,
        DType::U16 => 65535.0,
        _ => 1.0,
    };
    let [w, h] = image;
    let voxel = scene.voxel(0);
    // Slices: the plane through the middle, seen face on; a transfer
    // function with opacity, so that every slice of the stack shows.
    let centre = scale(extent, 0.5);
    let normal = [0.0, 0.0, 1.0];
    let slice_cam = Camera::facing_plane(centre, normal, extent[0].max(extent[1]) * 1.05);
    let slice_tf = TransferFunction::preset("soft", [0.0, max])?;
    let mode = RenderMode::Slice {
        origin: centre,
        normal,
    };
    let stack = Views {
        count,
        separation: 0.0,
        parallax: 4.0,
        spacing: voxel,
        alone: None,
    };
    let p = |width: u32, views: Option<Views>| {
        let mut p = RenderParams::new(width, h, slice_cam, slice_tf.clone(), mode.clone());
        p.views = views;
        p
    };
    let dvr_cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let dvr_tf = TransferFunction::preset("soft", [0.0, max])?;
    let dvr = |width: u32, views: Option<Views>| {
        let mut p = RenderParams::new(width, h, dvr_cam, dvr_tf.clone(), RenderMode::Dvr);
        p.reference_step = Some(voxel);
        p.views = views;
        p
    };
    let eyes = Views {
        count: 2,
        separation: length(sub(dvr_cam.target, dvr_cam.eye)) / 30.0,
        parallax: 0.0,
        spacing: 0.0,
        alone: None,
    };
    let cases = vec![
        Case {
            name: "slice".into(),
            params: vec![p(w, None)],
        },
        Case {
            name: "super-slice, one view alone".into(),
            params: vec![p(
                w,
                Some(Views {
                    alone: Some(count / 2),
                    ..stack
                }),
            )],
        },
        Case {
            name: format!("super-slice, {count} views in one frame"),
            params: vec![p(count * w, Some(stack))],
        },
        Case {
            name: format!("super-slice, {count} views drawn alone one by one"),
            params: (0..count)
                .map(|v| {
                    p(
                        w,
                        Some(Views {
                            alone: Some(v),
                            ..stack
                        }),
                    )
                })
                .collect(),
        },
        Case {
            name: "dvr, mono".into(),
            params: vec![dvr(w, None)],
        },
        Case {
            name: "dvr, stereo pair in one frame".into(),
            params: vec![dvr(2 * w, Some(eyes))],
        },
    ];
    let vox: u64 = dims.iter().product();
    let cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: vox * dtype.size() as u64 * 2 + (64 << 20),
        pt_cache_blocks: 4096,
        request_cap: 4096,
        upload_bytes_per_frame: 1 << 30,
        ..Default::default()
    };
    for name in backends {
        let mut results = vec![];
        for case in &cases {
            // A case the device cannot draw (its image over a buffer limit,
            // say) is reported and the others go on.
            let mut run = || -> anyhow::Result<(String, f64, u64)> {
                // From cold: a fresh session (bricks read for this case only).
                let mut s = Session::open(&st, cfg.clone(), 1 << 30, 2)?;
                scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
                let mut backend = crate::backend::Backend::choose(
                    name,
                    crate::backend::GpuUpdate::Device,
                    &mut s,
                    1,
                )?;
                backend.set_read_image(false);
                let mut frames = 0;
                for p in &case.params {
                    loop {
                        let f = backend.frame(&mut s, &scene, p, Lod::Fixed(0))?;
                        frames += 1;
                        if f.stats.completeness() >= 1.0 || frames > 2000 {
                            break;
                        }
                    }
                }
                let bytes_read = s.loader().bytes_read();
                let resident = s.vm().resident_bricks();
                // Warm: the best of `repeat` passes over the case's frames.
                let mut best = f64::INFINITY;
                let mut samples = 0;
                for _ in 0..repeat.max(1) {
                    let mut ms = 0.0;
                    samples = 0;
                    for p in &case.params {
                        let f = backend.frame(&mut s, &scene, p, Lod::Fixed(0))?;
                        ms += f.render_ms;
                        samples += f.stats.samples;
                    }
                    best = best.min(ms);
                }
                let describe = backend.describe();
                outln!(
                    "{}",
                    json!({"scenario": "views", "backend": describe, "case": case.name,
                        "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(), "view": [w, h],
                        "views": count, "warm_ms": best, "samples": samples,
                        "bytes_read_from_cold": bytes_read, "resident_bricks": resident,
                        "threads": rayon::current_num_threads()})
                );
                Ok((case.name.clone(), best, bytes_read))
            };
            match run() {
                Ok(r) => results.push(r),
                Err(e) => {
                    outln!(
                        "{}",
                        json!({"scenario": "views", "backend": name, "case": case.name,
                            "error": format!("{e:#}")})
                    );
                    results.push((case.name.clone(), f64::NAN, 0));
                }
            }
        }
        let t = |i: usize| results[i].1;
        outln!(
            "{}",
            json!({"scenario": "views", "summary": true, "backend": name,
                "super_slice_views_in_one_frame_over_one_view_alone": t(2) / t(1),
                "super_slice_views_one_by_one_over_in_one_frame": t(3) / t(2),
                "super_slice_view_alone_over_plain_slice": t(1) / t(0),
                "stereo_over_mono_dvr": t(5) / t(4),
                "bytes_read_views_in_one_frame_over_one_view": results[2].2 as f64 / results[1].2.max(1) as f64})
        );
    }
    Ok(())
}
