//! The in-core reference renderer against analytic results.

use brickyard_core::camera::{intersect_box, Projection};
use brickyard_core::transfer::{ColorMap, Preset};
use brickyard_core::{Camera, TransferFunction};
use brickyard_render::reference::{step_t, EARLY_TERMINATION};
use brickyard_render::{render, Image, RenderMode, RenderParams, Volume};

fn constant_tf(alpha: f32, rgb: [f32; 3]) -> TransferFunction {
    TransferFunction::new(
        [0.0, 10.0],
        vec![[0.0, alpha]],
        ColorMap::Points(vec![[0.0, rgb[0], rgb[1], rgb[2]]]),
    )
    .unwrap()
}

/// Number of samples the step rule takes on `[t0, t1)`.
fn count_steps(t0: f64, t1: f64, dt: f64) -> u64 {
    let mut k = 0;
    while step_t(t0, k, dt) < t1 {
        k += 1;
    }
    k
}

/// Expected DVR alpha of a constant volume after `n` steps of per-step
/// opacity `a` (already corrected), with early termination.
fn analytic_alpha(a: f64, n: u64) -> f64 {
    let mut acc = 0.0;
    for _ in 0..n {
        acc = 1.0 - (1.0 - a) * (1.0 - acc);
        if acc >= EARLY_TERMINATION as f64 {
            break;
        }
    }
    acc
}

fn top_down(extent_xy: [f64; 2], z_eye: f64) -> Camera {
    let (x, y) = (extent_xy[0] / 2.0, extent_xy[1] / 2.0);
    Camera::look_at(
        [x, y, z_eye],
        [x, y, 0.0],
        [0.0, 1.0, 0.0],
        Projection::Orthographic {
            height: extent_xy[1],
        },
    )
}

#[test]
fn constant_volume_dvr_is_analytic() {
    let rgb = [0.2, 0.4, 0.6];
    // 16 voxels deep along z, 8×8 across; the camera looks down -z through
    // voxel centres.
    for (spacing, alpha, spv, reference_step) in [
        ([1.0, 1.0, 1.0], 0.1, 1.0, None),
        ([1.0, 1.0, 1.0], 0.1, 2.0, None),
        ([1.0, 1.0, 1.0], 0.1, 2.5, None),
        ([1.0, 1.0, 1.0], 0.1, 0.5, None),
        ([1.0, 1.0, 1.0], 0.1, 1.0, Some(2.0)),
        ([2.0, 1.0, 1.0], 0.1, 1.0, None),
        ([1.0, 0.5, 0.5], 0.05, 1.0, None),
        ([1.0, 1.0, 1.0], 0.5, 1.0, None),
        ([1.0, 1.0, 1.0], 0.5, 3.0, None),
    ] {
        let vol = Volume::from_fn([16, 8, 8], spacing, |_, _, _| 5.0);
        let ext = vol.extent();
        let cam = top_down([ext[0], ext[1]], ext[2] + 20.0);
        let mut p = RenderParams::new(8, 8, cam, constant_tf(alpha, rgb), RenderMode::Dvr);
        p.samples_per_voxel = spv;
        p.reference_step = reference_step;
        let img = render(&vol, &p);
        let dt = vol.voxel_size() / spv;
        let e = dt / reference_step.unwrap_or(vol.voxel_size());
        let n = count_steps(20.0, 20.0 + ext[2], dt);
        assert_eq!(n as f64, (ext[2] / dt).round(), "steps through the depth");
        let a = 1.0 - (1.0 - alpha as f64).powf(e);
        let expect = analytic_alpha(a, n);
        if alpha == 0.1 && n as f64 * e < 40.0 {
            // No early termination: the closed form.
            let closed = 1.0 - (1.0 - alpha as f64).powf(n as f64 * e);
            assert!((expect - closed).abs() < 1e-12);
        }
        for px in &img.rgba {
            assert!(
                (px[3] as f64 - expect).abs() < 1e-4,
                "alpha {} vs {expect} (spacing {spacing:?}, spv {spv})",
                px[3]
            );
            for c in 0..3 {
                assert!((px[c] as f64 - rgb[c] as f64 * expect).abs() < 1e-4);
            }
        }
    }
    // Early termination: alpha 0.5 stops after 7 steps (1 − 0.5⁷ ≥ 0.99).
    assert!((analytic_alpha(0.5, 16) - (1.0 - 0.5f64.powi(7))).abs() < 1e-15);
}

#[test]
fn constant_volume_dvr_in_perspective() {
    let vol = Volume::from_fn([10, 12, 14], [1.5, 1.0, 0.75], |_, _, _| 5.0);
    let ext = vol.extent();
    let cam = Camera::fit(ext, 35.0, 25.0, Projection::Perspective { fov_y_deg: 30.0 });
    let (alpha, rgb) = (0.04, [1.0, 0.5, 0.25]);
    let p = RenderParams::new(48, 40, cam, constant_tf(alpha, rgb), RenderMode::Dvr);
    let img = render(&vol, &p);
    let dt = vol.voxel_size();
    let (mut hits, mut misses) = (0, 0);
    for j in 0..40 {
        for i in 0..48 {
            let ray = cam.ray(i as f64 + 0.5, j as f64 + 0.5, 48, 40);
            let px = img.get(i, j);
            let expect = match intersect_box(&ray, [0.0; 3], ext) {
                Some((t0, t1)) => analytic_alpha(alpha as f64, count_steps(t0, t1, dt)),
                None => 0.0,
            };
            if expect > 0.0 {
                hits += 1;
            } else {
                misses += 1;
            }
            assert!((px[3] as f64 - expect).abs() < 1e-4, "({i}, {j})");
            assert!((px[1] as f64 - 0.5 * expect).abs() < 1e-4);
        }
    }
    assert!(hits > 100 && misses > 100, "{hits} {misses}");
    // Deterministic.
    assert_eq!(render(&vol, &p), img);
}

#[test]
fn sampling_rule() {
    let vol = Volume::from_fn([4, 5, 6], [1.0, 2.0, 3.0], |z, y, x| {
        (100 * z + 10 * y + x) as f32
    });
    let d = vol.dims;
    // Voxel centres give the voxel exactly.
    for z in 0..4 {
        for y in 0..5 {
            for x in 0..6 {
                let p = [
                    (z as f64 + 0.5) / d[0] as f64,
                    (y as f64 + 0.5) / d[1] as f64,
                    (x as f64 + 0.5) / d[2] as f64,
                ];
                assert_eq!(vol.sample(p), vol.voxel(z, y, x));
            }
        }
    }
    // Half-way between centres: the mean; beyond the outer centres: clamped.
    let p = [1.0 / 4.0, 1.5 / 5.0, 1.0 / 6.0];
    // z 0.5 → 50, y 1 → 10, x 0.5 → 0.5.
    assert!((vol.sample(p) - 60.5).abs() < 1e-4);
    assert_eq!(vol.sample([0.0, 0.0, 0.0]), 0.0);
    assert_eq!(vol.sample([1.0, 1.0, 1.0]), 345.0);
    assert_eq!(vol.sample([-3.0, 7.0, 0.5 / 6.0]), 40.0);
    // World sampling goes through world_to_normalized: voxel (z 1, y 2, x 3)
    // has its centre at world ((3.5)·3, (2.5)·2, (1.5)·1).
    assert_eq!(vol.sample_world([10.5, 5.0, 1.5], vol.extent()), 123.0);
}

#[test]
fn mip_shows_a_single_bright_voxel_at_its_projection() {
    let (bz, by, bx) = (5u64, 9u64, 3u64);
    let vol = Volume::from_fn([16, 16, 16], [1.0; 3], |z, y, x| {
        if (z, y, x) == (bz, by, bx) {
            100.0
        } else {
            0.0
        }
    });
    let tf = TransferFunction::new([0.0, 100.0], vec![[0.0, 1.0]], ColorMap::default()).unwrap();
    // Orthographic, straight down through voxel centres: exactly one pixel.
    let cam = top_down([16.0, 16.0], 100.0);
    let img = render(
        &vol,
        &RenderParams::new(16, 16, cam, tf.clone(), RenderMode::Mip),
    );
    let centre = [bx as f64 + 0.5, by as f64 + 0.5, bz as f64 + 0.5];
    let q = cam.project(centre, 16, 16).unwrap();
    assert_eq!(q, [3.5, 6.5]);
    for j in 0..16 {
        for i in 0..16 {
            let expect = if (i, j) == (3, 6) { 1.0 } else { 0.0 };
            assert_eq!(img.get(i, j), [expect, expect, expect, 1.0], "({i}, {j})");
        }
    }
    // Perspective from an angle: the brightest pixel is where the voxel
    // centre projects.
    for (az, el) in [(30.0, 20.0), (-100.0, 45.0), (200.0, -30.0)] {
        let cam = Camera::fit(
            vol.extent(),
            az,
            el,
            Projection::Perspective { fov_y_deg: 25.0 },
        );
        let mut p = RenderParams::new(64, 64, cam, tf.clone(), RenderMode::Mip);
        p.samples_per_voxel = 4.0;
        let img = render(&vol, &p);
        let (mut best, mut at) = (-1.0f32, (0, 0));
        for j in 0..64 {
            for i in 0..64 {
                if img.get(i, j)[0] > best {
                    best = img.get(i, j)[0];
                    at = (i, j);
                }
            }
        }
        let q = cam.project(centre, 64, 64).unwrap();
        assert!(
            (at.0 as f64 + 0.5 - q[0]).abs() <= 1.0 && (at.1 as f64 + 0.5 - q[1]).abs() <= 1.0,
            "max at {at:?}, voxel projects to {q:?}"
        );
        assert!(best > 0.5);
        // Alpha 1 exactly where rays hit the box.
        for j in 0..64 {
            for i in 0..64 {
                let ray = cam.ray(i as f64 + 0.5, j as f64 + 0.5, 64, 64);
                // At least one sample on the ray (a ray that only grazes an
                // edge may take none).
                let hit = intersect_box(&ray, [0.0; 3], vol.extent())
                    .is_some_and(|(t0, t1)| count_steps(t0, t1, 0.25) > 0);
                assert_eq!(img.get(i, j)[3], if hit { 1.0 } else { 0.0 });
            }
        }
    }
}

/// `v = x + 2y + 3z` (voxel indices): clamp-to-edge trilinear of a linear
/// function is the function of the clamped voxel coordinates.
fn ramp_expect(w: [f64; 3], dims: [u64; 3], spacing: [f64; 3]) -> f64 {
    let q = |a_world: usize, a_zyx: usize| {
        (w[a_world] / spacing[a_zyx] - 0.5).clamp(0.0, (dims[a_zyx] - 1) as f64)
    };
    q(0, 2) + 2.0 * q(1, 1) + 3.0 * q(2, 0)
}

#[test]
fn slice_of_a_linear_ramp_equals_the_ramp_through_the_tf() {
    let dims = [16, 12, 8];
    let spacing = [2.0, 1.0, 0.5];
    let vol = Volume::from_fn(dims, spacing, |z, y, x| (x + 2 * y + 3 * z) as f32);
    let ext = vol.extent(); // [4, 12, 32]
    let vmax = 7.0 + 22.0 + 45.0;
    let tf = TransferFunction::new([0.0, vmax], vec![[0.0, 0.3]], ColorMap::default()).unwrap();
    let centre = [ext[0] / 2.0, ext[1] / 2.0, ext[2] / 2.0];
    let (w, h) = (40u32, 50u32);
    for (origin, normal, height) in [
        (centre, [0.0, 0.0, 1.0], 14.0),
        ([1.3, 4.1, 9.7], [0.0, 0.0, -1.0], 20.0),
        (centre, [1.0, 0.0, 0.0], 40.0),
        (centre, [1.0, 0.5, 1.0], 40.0),
    ] {
        let cam = Camera::facing_plane(origin, normal, height);
        let mode = RenderMode::Slice { origin, normal };
        let img = render(&vol, &RenderParams::new(w, h, cam, tf.clone(), mode));
        let (mut inside, mut outside) = (0, 0);
        for j in 0..h {
            for i in 0..w {
                // The world point: the ray of a face-on orthographic camera
                // meets the plane at the eye's distance.
                let ray = cam.ray(i as f64 + 0.5, j as f64 + 0.5, w, h);
                let p = ray.at(height);
                let px = img.get(i, j);
                let margin = (0..3)
                    .map(|a| p[a].min(ext[a] - p[a]))
                    .fold(f64::MAX, f64::min);
                if margin.abs() < 1e-6 {
                    continue;
                }
                if margin < 0.0 {
                    outside += 1;
                    assert_eq!(px, [0.0; 4]);
                    continue;
                }
                inside += 1;
                let g = (ramp_expect(p, dims, spacing) / vmax as f64) as f32;
                assert_eq!(px[3], 1.0);
                for v in &px[..3] {
                    assert!(
                        (v - g).abs() < 1e-5,
                        "({i}, {j}) {normal:?} at {p:?}: {v} vs {g}"
                    );
                }
            }
        }
        assert!(inside > 100, "{normal:?}: {inside} inside");
        if normal != [0.0, 0.0, 1.0] {
            assert!(outside > 20, "{normal:?}: {outside} outside");
        }
    }
    // Axis-aligned slice through the centres of the voxels z = 3, square
    // pixels of one voxel: the image is that slice of the array.
    let vol = Volume::from_fn(dims, [2.0, 1.0, 1.0], |z, y, x| (x + 2 * y + 3 * z) as f32);
    let ext = vol.extent();
    let z = 3.5 * 2.0;
    let origin = [ext[0] / 2.0, ext[1] / 2.0, z];
    let cam = Camera::facing_plane(origin, [0.0, 0.0, 1.0], ext[1]);
    let (w, h) = (8u32, 12u32); // one pixel per voxel
    let tf = TransferFunction::new([0.0, vmax], vec![[0.0, 1.0]], ColorMap::default()).unwrap();
    let img = render(
        &vol,
        &RenderParams::new(
            w,
            h,
            cam,
            tf.clone(),
            RenderMode::Slice {
                origin,
                normal: [0.0, 0.0, 1.0],
            },
        ),
    );
    for y in 0..h {
        for x in 0..w {
            // x right, y down: pixel (x, y) is voxel (3, y, x).
            let expect = tf.lookup(vol.voxel(3, y as u64, x as u64));
            let px = img.get(x, y);
            assert!((px[0] - expect[0]).abs() < 1e-6, "({x}, {y})");
        }
    }
}

#[test]
fn image_comparisons() {
    let mut a = Image::new(4, 3);
    let b = a.clone();
    assert_eq!(a.max_abs_diff(&b), 0.0);
    assert_eq!(a.psnr(&b), f64::INFINITY);
    a.set(1, 2, [0.5, 0.0, 0.0, 0.5]);
    assert_eq!(a.max_abs_diff(&b), 0.5);
    assert!((a.mean_abs_diff(&b) - 1.0 / 48.0).abs() < 1e-12);
    // MSE = 0.5 / 48.
    assert!((a.psnr(&b) - 10.0 * (48.0f64 / 0.5).log10()).abs() < 1e-9);
    assert_eq!(a.coverage(0.5), 1.0 / 12.0);
    // Over a white opaque background: 0.5 premultiplied red at alpha 0.5.
    let px = &a.to_rgba8([1.0, 1.0, 1.0, 1.0])[(2 * 4 + 1) * 4..][..4];
    assert_eq!(px, [255, 128, 128, 255]);
    // Over nothing: straight alpha.
    let px = &a.to_rgba8([0.0; 4])[(2 * 4 + 1) * 4..][..4];
    assert_eq!(px, [255, 0, 0, 128]);
}

#[test]
fn params_json_and_validation() {
    let cam = Camera::orbit(
        [0.0; 3],
        5.0,
        0.0,
        0.0,
        Projection::Perspective { fov_y_deg: 30.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 1.0]).unwrap();
    let p = RenderParams::new(
        8,
        8,
        cam,
        tf.clone(),
        RenderMode::Slice {
            origin: [1.0, 2.0, 3.0],
            normal: [0.0, 1.0, 0.0],
        },
    );
    p.validate().unwrap();
    let s = serde_json::to_string(&p).unwrap();
    let q: RenderParams = serde_json::from_str(&s).unwrap();
    assert_eq!(q.mode, p.mode);
    assert_eq!(q.tf, p.tf);
    let mut bad = p.clone();
    bad.samples_per_voxel = 0.0;
    assert!(bad
        .validate()
        .unwrap_err()
        .to_string()
        .contains("samples_per_voxel"));
    let mut bad = p.clone();
    bad.mode = RenderMode::Slice {
        origin: [0.0; 3],
        normal: [0.0; 3],
    };
    assert!(bad.validate().unwrap_err().to_string().contains("normal"));
    let m: RenderMode = serde_json::from_str(r#"{"mode": "mip"}"#).unwrap();
    assert_eq!(m, RenderMode::Mip);
    // A preset colour map works through MIP too.
    let tf =
        TransferFunction::new([0.0, 1.0], vec![[0.0, 0.0]], ColorMap::Preset(Preset::Hot)).unwrap();
    let vol = Volume::from_fn([2, 2, 2], [1.0; 3], |_, _, _| 1.0);
    let cam = Camera::fit(
        vol.extent(),
        0.0,
        0.0,
        Projection::Orthographic { height: 1.0 },
    );
    let img = render(&vol, &RenderParams::new(4, 4, cam, tf, RenderMode::Mip));
    assert_eq!(img.get(2, 2), [1.0, 1.0, 1.0, 1.0]);
}

#[test]
fn channels_add_up_as_defined() {
    use brickyard_render::reference::{render_channels, ChannelStyle};
    // Channel 0 holds 50 over the window [0, 200] in green (intensity
    // 0.25); channel 1 holds 200 over [100, 300] in magenta (0.5), except
    // one bright voxel of 300 (1.0) that a MIP shows where it projects.
    let a = Volume::from_fn([8, 8, 8], [1.0; 3], |_, _, _| 50.0);
    let b = Volume::from_fn([8, 8, 8], [1.0; 3], |z, y, x| {
        if (z, y, x) == (2, 5, 3) {
            300.0
        } else {
            200.0
        }
    });
    let styles = vec![
        ChannelStyle {
            channel: 0,
            color: [0.0, 1.0, 0.0],
            window: [0.0, 200.0],
            tf: None,
            levels: None,
        },
        ChannelStyle {
            channel: 1,
            color: [1.0, 0.0, 1.0],
            window: [100.0, 300.0],
            tf: None,
            levels: None,
        },
    ];
    let tf = constant_tf(1.0, [1.0; 3]);
    // Straight down through voxel centres, one pixel per voxel column.
    let cam = top_down([8.0, 8.0], 100.0);
    let mut p = RenderParams::new(8, 8, cam, tf.clone(), RenderMode::Mip);
    p.channels = styles.clone();
    let img = render_channels(&[a.clone(), b.clone()], &p);
    for j in 0..8 {
        for i in 0..8 {
            // Pixel (i, j) looks down the column of voxels (·, 7 − j, i).
            let expect = if (i, j) == (3, 2) {
                [1.0, 0.25, 1.0, 1.0]
            } else {
                [0.5, 0.25, 0.5, 1.0]
            };
            let px = img.get(i, j);
            for c in 0..4 {
                assert!((px[c] - expect[c]).abs() < 1e-6, "({i}, {j}): {px:?}");
            }
        }
    }
    // A slice through the voxel centres z = 5 (without the bright voxel),
    // and with colours that add up past 1 (clamped).
    let origin = [4.0, 4.0, 5.5];
    let cam = Camera::facing_plane(origin, [0.0, 0.0, 1.0], 8.0);
    let mut p = RenderParams::new(
        8,
        8,
        cam,
        tf,
        RenderMode::Slice {
            origin,
            normal: [0.0, 0.0, 1.0],
        },
    );
    p.channels = styles;
    p.channels[0].color = [4.0, 2.0, 0.0];
    let img = render_channels(&[a, b], &p);
    for j in 0..8 {
        for i in 0..8 {
            // 0.25·(4, 2, 0) + 0.5·(1, 0, 1) = (1.5, 0.5, 0.5) → (1, 0.5, 0.5).
            assert_eq!(img.get(i, j), [1.0, 0.5, 0.5, 1.0], "({i}, {j})");
        }
    }
}
