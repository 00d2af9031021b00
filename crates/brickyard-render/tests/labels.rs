//! Slices of a label image (`RenderParams::labels`): the nuclei stack's
//! instance labels, converted with label pyramids (the mode of each 2×2×2
//! block), drawn through a pool half the volume on the CPU and the device.
//! Every pixel must show the colour of a label that exists at the level
//! drawn (an interpolated label would be a colour of no label, or of the
//! wrong one), and the image must equal the in-core reference's nearest
//! samples.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_gpu::context::Gpu;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::image::Image;
use brickyard_render::labels::AMBIENT;
use brickyard_render::optics::label_color;
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

fn shared_data(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    assert!(
        path.exists(),
        "{} is missing: this test needs the shared data folder",
        path.display()
    );
    path
}

fn session(store: &Path, dtype: DType, pool_bytes: u64) -> Session {
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes,
        pt_cache_blocks: 256,
        request_cap: 256,
        upload_bytes_per_frame: 256 * 18 * 18 * 18 * dtype.size() as u64,
    };
    Session::open(store, cfg, 64 << 20, 2).unwrap()
}

/// The colours of the labels `level` holds, as RGBA bits.
fn label_colours(level: &Volume) -> HashSet<[u32; 4]> {
    let ids: HashSet<u32> = level.data.iter().map(|&v| v as u32).collect();
    ids.into_iter()
        .map(|id| label_color(Some(id as f32)).map(f32::to_bits))
        .collect()
}

/// Every pixel is transparent or the colour of one of `colours`; returns
/// how many distinct label colours the image shows.
fn only_label_colours(img: &Image, colours: &HashSet<[u32; 4]>, what: &str, tol: f32) -> usize {
    let mut shown = HashSet::new();
    for (i, px) in img.rgba.iter().enumerate() {
        if px[3] == 0.0 {
            assert_eq!(*px, [0.0; 4], "{what}: pixel {i}");
            continue;
        }
        let found = colours.iter().find(|c| {
            c.iter()
                .zip(px)
                .all(|(&c, &p)| (f32::from_bits(c) - p).abs() <= tol)
        });
        let Some(c) = found else {
            panic!("{what}: pixel {i} {px:?} is the colour of no label of the level");
        };
        shown.insert(*c);
    }
    shown.len()
}

/// Pixels whose colours differ by more than `tol` in any channel.
fn differing(a: &Image, b: &Image, tol: f32) -> usize {
    a.rgba
        .iter()
        .zip(&b.rgba)
        .filter(|(p, q)| p.iter().zip(q.iter()).any(|(x, y)| (x - y).abs() > tol))
        .count()
}

/// CPU frames until the view at `level` is complete: the image and the
/// bricks crossed in the last frame.
/// The view on the CPU, complete; with the background bricks and cells
/// crossed in its last frame.
fn converge_cpu(
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    level: usize,
) -> (Image, (u64, u64)) {
    let start = Instant::now();
    loop {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, Lod::Fixed(level));
        s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            return (img, (st.skipped_bricks, st.skipped_cells));
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "level {level}: CPU view incomplete at {} ({} resident)",
            st.completeness(),
            s.vm().resident_bricks()
        );
    }
}

/// The same on the device, through a device copy of `s`'s virtual memory.
fn converge_device(
    gpu: &Gpu,
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    level: usize,
) -> (Image, (u64, u64)) {
    let (mut dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
    let mut r = GpuRenderer::new(gpu);
    let start = Instant::now();
    loop {
        s.begin_frame();
        let f = r
            .render(gpu, &dvm, s.vm(), scene, p, Lod::Fixed(level))
            .unwrap();
        s.finish_frame([&f.requests]);
        dvm.sync(gpu, s.vm_mut());
        if f.stats.completeness() == 1.0 {
            return (f.image, (f.stats.skipped_bricks, f.stats.skipped_cells));
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "level {level}: device view incomplete"
        );
    }
}

#[test]
fn label_slices_show_whole_labels_on_the_cpu_and_the_device() {
    let dir = tempfile::tempdir().unwrap();
    let (store, levels) = nuclei_labels(dir.path());
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let vol_bytes = levels[0].dims.iter().product::<u64>() * 4;
    let gpu = brickyard_gpu::context::test_gpu();
    // An oblique plane through the nuclei, face on; the transfer function
    // is not used.
    let origin = [extent[0] * 0.5, extent[1] * 0.5, extent[2] * 0.45];
    let normal = [0.15, -0.1, 1.0];
    let cam = Camera::facing_plane(origin, normal, extent[0].max(extent[1]) * 1.05);
    let tf = TransferFunction::preset("linear", [0.0, 20.0]).unwrap();
    let mut p = RenderParams::new(96, 96, cam, tf, RenderMode::Slice { origin, normal });
    p.labels = true;
    p.validate().unwrap();
    for level in [0usize, 1] {
        let colours = label_colours(&levels[level]);
        assert!(
            colours.len() >= 15,
            "level {level}: {} labels",
            colours.len()
        );
        let want = render(&levels[level], &p);
        let shown = only_label_colours(&want, &colours, "reference", 1e-6);
        assert!(shown >= 8, "reference, level {level}: {shown} labels shown");
        assert!(want.coverage(0.01) > 0.1, "reference nearly empty");
        // The CPU through a pool half the volume.
        let mut s = session(&store, DType::U32, vol_bytes / 2);
        assert!((s.vm().pool_bytes() as u64) < vol_bytes);
        let (img, _) = converge_cpu(&mut s, &scene, &p, level);
        let shown_cpu = only_label_colours(&img, &colours, "CPU", 0.0);
        // (The reference's colours are its own f64 arithmetic's.)
        let d = differing(&img, &want, 1e-6);
        eprintln!(
            "level {level}: CPU shows {shown_cpu} labels, {d} pixels differ from the reference"
        );
        // The same rule in f64 on both sides: at most a pixel whose point
        // lies on a voxel boundary to rounding.
        assert!(
            d <= 2,
            "level {level}: {d} pixels differ from the reference"
        );
        s.vm().check_invariants().unwrap();
        let Some(gpu) = &gpu else { continue };
        let mut s = session(&store, DType::U32, vol_bytes / 2);
        let (dev, _) = converge_device(gpu, &mut s, &scene, &p, level);
        // The device's colours are its own arithmetic's (within 1e-6 of
        // the CPU's); its points are f32, so a few pixels on voxel
        // boundaries may take the neighbouring voxel.
        let shown_dev = only_label_colours(&dev, &colours, "device", 1e-6);
        let d = differing(&dev, &img, 1e-6);
        eprintln!(
            "level {level}: the device shows {shown_dev} labels, {d} pixels differ from the CPU"
        );
        assert!(
            d * 100 <= img.rgba.len(),
            "level {level}: {d} pixels of {} differ between the device and the CPU",
            img.rgba.len()
        );
        s.vm().check_invariants().unwrap();
    }
}

#[test]
fn label_colours_are_not_for_mips() {
    let cam = Camera::facing_plane([1.0; 3], [0.0, 0.0, 1.0], 2.0);
    let tf = TransferFunction::preset("linear", [0.0, 1.0]).unwrap();
    let mut p = RenderParams::new(8, 8, cam, tf.clone(), RenderMode::Mip);
    p.labels = true;
    let e = p.validate().unwrap_err().to_string();
    assert!(e.contains("labels") && e.contains("MIP"), "{e}");
}

/// The nuclei labels converted with label pyramids (z 4× coarser), and
/// every level whole.
fn nuclei_labels(dir: &Path) -> (PathBuf, Vec<Volume>) {
    let input = shared_data("nuclei-labels-u32.tif");
    let src = brickyard_store::import::open_input(&input, &Default::default()).unwrap();
    let store = dir.join("labels.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [64; 3],
        labels: true,
        spacing: Some([1.0, 0.25, 0.25]),
        ..Default::default()
    };
    convert(
        src.as_ref(),
        &store,
        &o,
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let n = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels = (0..n)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    (store, levels)
}

/// Every lit pixel is some label's colour times a shade in `[AMBIENT, 1]`
/// (within `tol`); returns how many labels show and the range of shades.
fn shaded_label_colours(img: &Image, ids: &HashSet<u32>, tol: f32) -> (usize, f32, f32) {
    let mut shown = HashSet::new();
    let (mut lo, mut hi) = (f32::INFINITY, 0f32);
    for (i, px) in img.rgba.iter().enumerate() {
        if px[3] == 0.0 {
            assert_eq!(*px, [0.0; 4], "pixel {i}");
            continue;
        }
        assert_eq!(px[3], 1.0, "pixel {i}");
        let found = ids.iter().filter(|&&id| id != 0).find_map(|&id| {
            let c = label_color(Some(id as f32));
            let k = c[..3].iter().cloned().fold(0.0, f32::max);
            let shade = px[..3].iter().cloned().fold(0.0, f32::max) / k;
            let fits = (AMBIENT - tol..=1.0 + tol).contains(&shade)
                && (0..3).all(|a| (c[a] * shade - px[a]).abs() <= tol);
            fits.then_some((id, shade))
        });
        let Some((id, shade)) = found else {
            panic!("pixel {i} {px:?} is no label's colour, shaded");
        };
        shown.insert(id);
        lo = lo.min(shade);
        hi = hi.max(shade);
    }
    (shown.len(), lo, hi)
}

#[test]
fn label_surfaces_in_3d_on_the_cpu_and_the_device() {
    let dir = tempfile::tempdir().unwrap();
    let (store, levels) = nuclei_labels(dir.path());
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let vol_bytes = levels[0].dims.iter().product::<u64>() * 4;
    let gpu = brickyard_gpu::context::test_gpu();
    let cam = Camera::fit(
        extent,
        35.0,
        40.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let tf = TransferFunction::preset("linear", [0.0, 1.0]).unwrap();
    let mut p = RenderParams::new(96, 80, cam, tf, RenderMode::Dvr);
    p.labels = true;
    p.reference_step = Some(scene.voxel(0));
    p.validate().unwrap();
    for level in [0usize, 1] {
        let ids: HashSet<u32> = levels[level].data.iter().map(|&v| v as u32).collect();
        let want = render(&levels[level], &p);
        let (shown, lo, hi) = shaded_label_colours(&want, &ids, 1e-5);
        eprintln!("level {level}: the reference shows {shown} labels, shades {lo}..{hi}");
        assert!(
            shown >= 8 && hi - lo > 0.3,
            "level {level}: {shown} labels, shades {lo}..{hi}"
        );
        assert!(want.coverage(0.01) > 0.1, "reference nearly empty");
        // The CPU, with the store's brick statistics (background bricks
        // crossed) and without. (Rays that meet no label cross the whole
        // volume: a fixed level-0 view needs every brick they pass, more
        // than half the volume's.)
        let pool = vol_bytes * 5 / 4;
        for stats in [true, false] {
            let mut s = session(&store, DType::U32, pool);
            scene.ranges = stats.then(|| std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
            let (img, (skipped, cells)) = converge_cpu(&mut s, &scene, &p, level);
            let d = differing(&img, &want, 1e-5);
            eprintln!("level {level}, statistics {stats}: {d} pixels differ from the reference, {skipped} bricks and {cells} cells crossed");
            assert!(
                d <= 3,
                "level {level}, statistics {stats}: {d} pixels differ from the reference"
            );
            // (Without statistics, bricks the pool holds as empty are
            // crossed too.)
            assert!(skipped > 0, "no background brick crossed");
            // (Bricks of 16³ hold 8 cells: the background ones of bricks
            // with labels are crossed too.)
            assert!(cells > 0, "no background cell crossed");
            s.vm().check_invariants().unwrap();
        }
        let Some(gpu) = &gpu else { continue };
        let mut s = session(&store, DType::U32, pool);
        // (With the statistics: background bricks and cells crossed.)
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
        let (dev, (bricks, cells)) = converge_device(gpu, &mut s, &scene, &p, level);
        eprintln!("level {level}: the device crossed {bricks} bricks and {cells} cells");
        assert!(
            bricks > 0 && cells > 0,
            "level {level}: {bricks} bricks, {cells} cells crossed on the device"
        );
        shaded_label_colours(&dev, &ids, 1e-5);
        // f32 steps on the device: a ray grazing a voxel may stop a step
        // earlier or later.
        let d = differing(&dev, &want, 1e-5);
        eprintln!("level {level}: {d} pixels on the device differ from the reference");
        assert!(
            d * 50 <= want.rgba.len(),
            "level {level}: {d} pixels of {} differ between the device and the reference",
            want.rgba.len()
        );
        s.vm().check_invariants().unwrap();
    }
}

#[test]
fn sheets_of_labels_behind_background_bricks_are_met_where_the_reference_meets_them() {
    // Background everywhere but sheets one voxel thick across x, at x = 20
    // and x = 32 (the first layer of the third brick of 16). Rays along +x
    // cross the first brick (background, its apron too) without sampling
    // and meet the first sheet at every phase of the step grid.
    let dir = tempfile::tempdir().unwrap();
    let (nx, ny, nz) = (48usize, 16usize, 16usize);
    let mut v = vec![0u8; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            v[(z * ny + y) * nx + 20] = 5;
            v[(z * ny + y) * nx + 32] = 9;
        }
    }
    let raw = dir.path().join("sheets.raw");
    std::fs::write(&raw, &v).unwrap();
    std::fs::write(
        dir.path().join("sheets.raw.json"),
        r#"{"dims": [48, 16, 16], "dtype": "u8"}"#,
    )
    .unwrap();
    let src = brickyard_store::import::open_input(&raw, &Default::default()).unwrap();
    let store = dir.path().join("sheets.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [64; 3],
        labels: true,
        ..Default::default()
    };
    convert(
        src.as_ref(),
        &store,
        &o,
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let level0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = world_extent(level0.dims, level0.spacing);
    let dims = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .map(|v| v.dims)
        .collect();
    let mut scene = Scene::new(extent, dims);
    let mut s = session(&store, DType::U8, 1 << 20);
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    // From x < 0 towards +x, slightly off axis: rays meet the sheet at
    // every phase of the step grid.
    let cam = Camera::look_at(
        [-20.0, 7.3, 8.1],
        [24.0, 8.0, 8.0],
        [0.0, 0.0, 1.0],
        Projection::Perspective { fov_y_deg: 20.0 },
    );
    let tf = TransferFunction::preset("linear", [0.0, 1.0]).unwrap();
    let mut p = RenderParams::new(64, 64, cam, tf, RenderMode::Dvr);
    p.labels = true;
    let want = render(&level0, &p);
    let sheet = label_color(Some(5.0));
    let on_sheet = want
        .rgba
        .iter()
        .filter(|px| px[3] == 1.0 && (0..3).all(|a| px[a] <= sheet[a] + 1e-6))
        .count();
    assert!(
        on_sheet > 64 * 64 / 4,
        "the reference shows the first sheet on {on_sheet} pixels"
    );
    // The walk alone (no entry depths, which start rays near the sheet).
    scene.entry_depths = false;
    let (img, (skipped, _)) = converge_cpu(&mut s, &scene, &p, 0);
    assert!(skipped > 0, "the background brick was sampled step by step");
    let d = differing(&img, &want, 1e-5);
    assert_eq!(d, 0, "{d} pixels differ from the reference");
    // With entry depths: the same pixels (a ray started a step too late
    // passes a sheet one voxel thick).
    scene.entry_depths = true;
    let (img, _) = converge_cpu(&mut s, &scene, &p, 0);
    let d = differing(&img, &want, 1e-5);
    assert_eq!(
        d, 0,
        "with entry depths, {d} pixels differ from the reference"
    );
    // The device crosses them too (f32 steps: a ray may meet a sheet a
    // step off).
    let Some(gpu) = brickyard_gpu::context::test_gpu() else {
        return;
    };
    let mut s = session(&store, DType::U8, 1 << 20);
    let (dev, (jumped, _)) = converge_device(&gpu, &mut s, &scene, &p, 0);
    let d = differing(&dev, &want, 1e-5);
    eprintln!("the device crossed {jumped} bricks; {d} pixels differ from the reference");
    assert!(
        jumped > 0,
        "the device sampled the background brick step by step"
    );
    assert!(
        d * 100 <= want.rgba.len(),
        "{d} pixels differ on the device"
    );
}

/// Pixels of each label's colour, shaded or not (`ids`: the labels to
/// look for): the label each lit pixel shows, by the hue of its colour.
fn labels_shown(img: &Image, ids: &HashSet<u32>) -> std::collections::HashMap<u32, usize> {
    let mut n = std::collections::HashMap::new();
    for px in img.rgba.iter().filter(|px| px[3] > 0.0) {
        let k = px[..3].iter().cloned().fold(0.0, f32::max);
        let id = ids.iter().copied().filter(|&id| id != 0).find(|&id| {
            let c = label_color(Some(id as f32));
            let m = c[..3].iter().cloned().fold(0.0, f32::max);
            (0..3).all(|a| (c[a] / m - px[a] / k).abs() <= 1e-4)
        });
        *n.entry(id.unwrap_or(0)).or_insert(0) += 1;
    }
    n
}

#[test]
fn label_selections_draw_only_or_all_but_the_labels_named_on_the_cpu_and_the_device() {
    use brickyard_render::params::LabelSelect;
    let dir = tempfile::tempdir().unwrap();
    let (store, levels) = nuclei_labels(dir.path());
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let vol_bytes = levels[0].dims.iter().product::<u64>() * 4;
    let gpu = brickyard_gpu::context::test_gpu();
    let ids: HashSet<u32> = levels[0].data.iter().map(|&v| v as u32).collect();
    let tf = TransferFunction::preset("linear", [0.0, 1.0]).unwrap();
    let origin = [extent[0] * 0.5, extent[1] * 0.5, extent[2] * 0.45];
    let normal = [0.15, -0.1, 1.0];
    let slice_cam = Camera::facing_plane(origin, normal, extent[0].max(extent[1]) * 1.05);
    let mut slice = RenderParams::new(
        96,
        96,
        slice_cam,
        tf.clone(),
        RenderMode::Slice { origin, normal },
    );
    let cam = Camera::fit(
        extent,
        35.0,
        40.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let mut dvr = RenderParams::new(96, 80, cam, tf, RenderMode::Dvr);
    dvr.reference_step = Some(scene.voxel(0));
    for (what, p) in [("slice", &mut slice), ("3D", &mut dvr)] {
        p.labels = true;
        // The three labels the view shows most of, by the reference.
        let all = render(&levels[0], p);
        let mut seen: Vec<(usize, u32)> = labels_shown(&all, &ids)
            .into_iter()
            .map(|(id, n)| (n, id))
            .collect();
        seen.sort_unstable_by(|a, b| b.cmp(a));
        assert!(
            seen.len() >= 8 && seen.iter().all(|s| s.1 != 0),
            "{what}: {seen:?}"
        );
        let named: Vec<i32> = seen[..3].iter().map(|s| s.1 as i32).collect();
        // Bricks and cells crossed without a selection.
        let crossed = {
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
            converge_cpu(&mut s, &scene, p, 0).1
        };
        for hide in [false, true] {
            p.label_select = Some(LabelSelect::new(named.clone(), hide));
            p.validate().unwrap();
            let want = render(&levels[0], p);
            let shown = labels_shown(&want, &ids);
            let named_px: usize = named
                .iter()
                .map(|id| shown.get(&(*id as u32)).copied().unwrap_or(0))
                .sum();
            let other_px: usize = shown
                .iter()
                .filter(|(id, _)| !named.contains(&(**id as i32)))
                .map(|(_, n)| n)
                .sum();
            eprintln!(
                "{what}, hide {hide}: {named_px} pixels of the labels named, {other_px} of others"
            );
            if hide {
                assert_eq!(named_px, 0, "{what}: hidden labels drawn");
                // The rest as before, and (in 3D) labels behind the hidden
                // ones come to light.
                let before: usize = seen[3..].iter().map(|s| s.0).sum();
                if what == "3D" {
                    assert!(
                        other_px > before + 50,
                        "{what}: {other_px} against {before}"
                    );
                } else {
                    assert_eq!(other_px, before, "{what}");
                }
            } else {
                assert_eq!(other_px, 0, "{what}: labels not named drawn");
                assert!(
                    named.iter().all(|id| shown.contains_key(&(*id as u32))),
                    "{what}: {shown:?}"
                );
            }
            // The CPU against the reference, the device against the CPU.
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
            let (img, (bricks, cells)) = converge_cpu(&mut s, &scene, p, 0);
            eprintln!(
                "{what}, hide {hide}: {bricks} bricks and {cells} cells crossed, {crossed:?} without a selection"
            );
            if what == "3D" && !hide {
                // Bricks and cells without the labels drawn are crossed
                // too (their ranges name none of them).
                assert!(
                    bricks > crossed.0 && cells > crossed.1,
                    "{bricks} bricks and {cells} cells crossed, {crossed:?} without a selection"
                );
            }
            let d = differing(&img, &want, 1e-5);
            assert!(
                d <= 3,
                "{what}, hide {hide}: {d} pixels differ from the reference"
            );
            let loaded = s.loader().bricks_loaded();
            let boxed = (!hide).then(|| {
                // Where the labels named lie (their bounding boxes, found in
                // the volume here): bricks none of them reaches are crossed,
                // and the images stay the same.
                let d0 = levels[0].dims;
                let boxes: Vec<[u64; 6]> = named
                    .iter()
                    .map(|&id| {
                        let mut b = [u64::MAX, u64::MAX, u64::MAX, 0, 0, 0];
                        for (i, &v) in levels[0].data.iter().enumerate() {
                            if v as i32 == id {
                                let i = i as u64;
                                let q = [i / (d0[1] * d0[2]), i / d0[2] % d0[1], i % d0[2]];
                                for a in 0..3 {
                                    b[a] = b[a].min(q[a]);
                                    b[3 + a] = b[3 + a].max(q[a]);
                                }
                            }
                        }
                        b
                    })
                    .collect();
                let mut pb = p.clone();
                pb.label_select.as_mut().unwrap().boxes =
                    Some(brickyard_render::params::LabelBoxes { dims: d0, boxes });
                let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
                scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
                let (img_b, _) = converge_cpu(&mut s, &scene, &pb, 0);
                let loaded_b = s.loader().bricks_loaded();
                eprintln!(
                    "{what}: {loaded_b} bricks loaded with the labels' boxes, {loaded} without"
                );
                assert_eq!(
                    differing(&img_b, &img, 0.0),
                    0,
                    "{what}: the boxes changed the image"
                );
                if what == "3D" {
                    assert!(
                        loaded_b * 5 < loaded * 4,
                        "{loaded_b} bricks loaded, {loaded} without boxes"
                    );
                }
                pb
            });
            let Some(gpu) = &gpu else { continue };
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            let (dev, (_, dev_cells)) = converge_device(gpu, &mut s, &scene, p, 0);
            if what == "3D" {
                eprintln!("{what}, hide {hide}: the device crossed {dev_cells} cells");
                assert!(
                    dev_cells > 0,
                    "{what}, hide {hide}: no cell crossed on the device"
                );
            }
            let d = differing(&dev, &img, 1e-5);
            eprintln!("{what}, hide {hide}: {d} pixels on the device differ from the CPU");
            assert!(
                d * 50 <= img.rgba.len(),
                "{what}, hide {hide}: {d} pixels differ on the device"
            );
            assert_eq!(
                labels_shown(&dev, &ids).contains_key(&(named[0] as u32)),
                !hide,
                "{what}"
            );
            let Some(pb) = &boxed else { continue };
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            let (dev_b, _) = converge_device(gpu, &mut s, &scene, pb, 0);
            let d = differing(&dev_b, &dev, 0.0);
            eprintln!("{what}: {d} pixels on the device differ with the labels' boxes");
            assert_eq!(d, 0, "{what}: the boxes changed the device's image");
            // Without the store's brick statistics (as the web client
            // draws), the boxes alone: the same images.
            let mut bare = scene.clone();
            bare.ranges = None;
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            let (cpu_bare, _) = converge_cpu(&mut s, &bare, pb, 0);
            assert_eq!(
                differing(&cpu_bare, &img, 0.0),
                0,
                "{what}: CPU, boxes alone"
            );
            let mut s = session(&store, DType::U32, vol_bytes * 5 / 4);
            let (dev_bare, _) = converge_device(gpu, &mut s, &bare, pb, 0);
            assert_eq!(
                differing(&dev_bare, &dev, 0.0),
                0,
                "{what}: device, boxes alone"
            );
        }
        p.label_select = None;
    }
}

#[test]
fn label_selections_are_refused_where_they_mean_nothing() {
    use brickyard_render::params::LabelSelect;
    let cam = Camera::facing_plane([1.0; 3], [0.0, 0.0, 1.0], 2.0);
    let tf = TransferFunction::preset("linear", [0.0, 1.0]).unwrap();
    let mode = RenderMode::Slice {
        origin: [1.0; 3],
        normal: [0.0, 0.0, 1.0],
    };
    let mut p = RenderParams::new(8, 8, cam, tf, mode);
    p.label_select = Some(LabelSelect::new(vec![3], false));
    let e = p.validate().unwrap_err().to_string();
    assert!(
        e.contains("label_select") && e.contains("label image"),
        "{e}"
    );
    p.labels = true;
    p.validate().unwrap();
    p.label_select = Some(LabelSelect {
        ids: vec![5, 3],
        hide: false,
        boxes: None,
    });
    assert!(p.validate().unwrap_err().to_string().contains("increasing"));
    p.label_select = Some(LabelSelect::new(vec![0, 3], true));
    assert!(p.validate().unwrap_err().to_string().contains("background"));
    assert_eq!(
        LabelSelect::parse_ids("3, 17,40-42").unwrap(),
        vec![3, 17, 40, 41, 42]
    );
    assert_eq!(LabelSelect::parse_ids("-2").unwrap(), vec![-2]);
    for bad in [
        "",
        "x",
        "5-3",
        "1-999999",
        "0",
        "3,0-2",
        "1,,2",
        "1,",
        "16777217",
        "-16777217",
        "4000000000",
    ] {
        assert!(LabelSelect::parse_ids(bad).is_err(), "{bad}");
    }
    // Labels up to 2^24 are told apart (f32 holds every integer there).
    assert_eq!(
        LabelSelect::parse_ids("16777215-16777216").unwrap(),
        vec![16777215, 16777216]
    );
    assert!(LabelSelect::parse_ids("16777217")
        .unwrap_err()
        .contains("2^24"));
}

#[test]
fn selections_tell_the_value_ranges_that_draw_nothing_as_a_label_by_label_search_does() {
    use brickyard_render::optics::label_clear;
    use brickyard_render::params::LabelSelect;
    for ids in [vec![3], vec![-2, 1, 2, 3, 9], vec![4, 5, 6, 7]] {
        for hide in [false, true] {
            let sel = LabelSelect::new(ids.clone(), hide);
            for lo in -4..12 {
                for hi in lo..12 {
                    // Values a little off the integers round to them.
                    let (flo, fhi) = (lo as f32 - 0.3, hi as f32 + 0.2);
                    let naive = (lo..=hi).any(|k| k != 0 && ids.contains(&k) != hide);
                    assert_eq!(
                        sel.draws_any(flo, fhi),
                        naive,
                        "{ids:?} hide {hide}: [{lo}, {hi}]"
                    );
                    assert_eq!(label_clear(flo, fhi, Some(&sel)), !naive);
                }
            }
            assert!(sel.draws_any(f32::NAN, 3.0));
        }
    }
    // Without a selection: background alone.
    assert!(label_clear(0.0, 0.0, None) && !label_clear(0.0, 1.0, None));
}
