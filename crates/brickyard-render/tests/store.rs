//! Volumes read from sources and stores, PNG output, and the real MR scan
//! of `../shared/data/` rendered through a converted store.

use brickyard_core::camera::Projection;
use brickyard_core::{Camera, DType, TransferFunction};
use brickyard_render::{render, Image, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::import::nrrd;
use brickyard_store::source::{SourceMeta, VolumeSource};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

/// A u16 volume in memory, two channels.
struct MemSource {
    meta: SourceMeta,
    data: Vec<u16>,
}

impl MemSource {
    fn new(dims: [u64; 3], spacing: [f64; 3]) -> MemSource {
        let mut meta = SourceMeta::new("mem", dims, 2, DType::U16);
        meta.spacing = Some(spacing);
        let n = (dims[0] * dims[1] * dims[2]) as usize;
        let data = (0..2 * n)
            .map(|i| ((i * 7919) % 4001) as u16 + if i >= n { 10000 } else { 0 })
            .collect();
        MemSource { meta, data }
    }
}

impl VolumeSource for MemSource {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }
    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> brickyard_store::Result<()> {
        let [dz, dy, dx] = self.meta.dims;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                for xx in x.clone() {
                    let i = (c as u64 * dz * dy * dx + (zz * dy + yy) * dx + xx) as usize;
                    out[o..o + 2].copy_from_slice(&self.data[i].to_le_bytes());
                    o += 2;
                }
            }
        }
        Ok(())
    }
}

fn convert_to(src: &dyn VolumeSource, out: &Path, brick: u64) {
    let opts = ConvertOptions {
        brick: [brick; 3],
        shard: [brick * 4; 3],
        ..Default::default()
    };
    convert(src, out, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
}

#[test]
fn store_levels_read_whole() {
    let tmp = tempfile::tempdir().unwrap();
    let dims = [20, 17, 9];
    let spacing = [2.0, 0.5, 1.25];
    let src = MemSource::new(dims, spacing);
    let store = tmp.path().join("v.ome.zarr");
    convert_to(&src, &store, 8);
    for c in 0..2 {
        let a = Volume::from_source(&src, c).unwrap();
        let b = Volume::from_store(&store, 0, c).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.dims, dims);
        assert_eq!(a.spacing, spacing);
        let n = (dims[0] * dims[1] * dims[2]) as usize;
        let expect: Vec<f32> = src.data[c * n..(c + 1) * n]
            .iter()
            .map(|&v| v as f32)
            .collect();
        assert_eq!(a.data, expect);
    }
    // Coarser levels cover the same world box.
    let l0 = Volume::from_store(&store, 0, 1).unwrap();
    let l1 = Volume::from_store(&store, 1, 1).unwrap();
    // Per-axis ratios follow the spacing: some axes may stay at level 1.
    assert!(l1.dims.iter().zip(&l0.dims).all(|(a, b)| a <= b) && l1.dims != l0.dims);
    for a in 0..3 {
        assert!((l1.extent()[a] - l0.extent()[a]).abs() < 1e-9);
    }
    // Errors say what is wrong.
    let e = Volume::from_store(&store, 0, 2).unwrap_err().to_string();
    assert!(e.contains("channel 2"), "{e}");
    let e = Volume::from_store(&store, 99, 0).unwrap_err().to_string();
    assert!(e.contains("level 99"), "{e}");
    assert!(Volume::from_store(&tmp.path().join("nope"), 0, 0).is_err());
}

#[test]
fn png_round_trip() {
    let vol = Volume::from_fn([8, 8, 8], [1.0; 3], |z, y, x| (x + y + z) as f32);
    let tf = TransferFunction::preset("hot", [0.0, 21.0]).unwrap();
    let cam = Camera::fit(
        vol.extent(),
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 30.0 },
    );
    let img = render(&vol, &RenderParams::new(37, 23, cam, tf, RenderMode::Dvr));
    let tmp = tempfile::tempdir().unwrap();
    for bg in [[0.0; 4], [0.1, 0.2, 0.3, 1.0], [1.0, 1.0, 1.0, 0.5]] {
        let path = tmp.path().join("a.png");
        img.write_png(&path, bg).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0u8; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (37, 23));
        assert_eq!(info.color_type, png::ColorType::Rgba);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        assert_eq!(&buf[..info.buffer_size()], &img.to_rgba8(bg)[..]);
    }
    let e = img
        .write_png(&tmp.path().join("no/such/dir.png"), [0.0; 4])
        .unwrap_err()
        .to_string();
    assert!(e.contains("dir.png"), "{e}");
}

fn shared_data(name: &str) -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    assert!(
        p.exists(),
        "test data {} is missing: this test needs the project's shared data folder \
         (../shared/data/ next to the repository)",
        p.display()
    );
    p
}

#[test]
fn real_mr_brain_dvr_and_mip() {
    let input = shared_data("mr-brain-i16.nrrd");
    let src = nrrd::open(&input).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let store = tmp.path().join("brain.ome.zarr");
    convert_to(&src, &store, 32);
    let vol = Volume::from_store(&store, 0, 0).unwrap();
    assert_eq!(vol, Volume::from_source(&src, 0).unwrap());
    assert_eq!(vol.dims, [25, 256, 256]);
    let (lo, hi) = vol.min_max();
    assert!(hi > lo);
    let ext = vol.extent();
    let cam = Camera::fit(ext, 30.0, 20.0, Projection::Perspective { fov_y_deg: 30.0 });
    let tf = TransferFunction::default_for(DType::I16, lo as f64, hi as f64);
    let mut out = vec![];
    for (name, mode) in [("dvr", RenderMode::Dvr), ("mip", RenderMode::Mip)] {
        let img = render(&vol, &RenderParams::new(128, 128, cam, tf.clone(), mode));
        let path = tmp.path().join(format!("mr-brain-{name}.png"));
        img.write_png(&path, [0.0, 0.0, 0.0, 1.0]).unwrap();
        let opaque = img.coverage(0.9);
        let empty = img.rgba.iter().filter(|p| p[3] == 0.0).count() as f64 / (128.0 * 128.0);
        let bright = img.rgba.iter().map(|p| p[0]).fold(0.0f32, f32::max);
        println!(
            "{name}: {opaque:.3} opaque, {empty:.3} empty, brightest {bright:.3}, {}",
            path.display()
        );
        assert!(
            opaque > 0.05,
            "{name}: only {opaque} of the pixels are opaque"
        );
        assert!(empty > 0.05, "{name}: only {empty} of the pixels are empty");
        assert!(bright > 0.3, "{name}: brightest pixel {bright}");
        // Not a flat image: colours vary over the opaque pixels.
        let reds: Vec<f32> = img
            .rgba
            .iter()
            .filter(|p| p[3] > 0.9)
            .map(|p| p[0] / p[3])
            .collect();
        let mean = reds.iter().sum::<f32>() / reds.len() as f32;
        let var = reds.iter().map(|r| (r - mean) * (r - mean)).sum::<f32>() / reds.len() as f32;
        assert!(var.sqrt() > 0.02, "{name}: flat image (sd {})", var.sqrt());
        out.push(img);
    }
    // A coarser level renders the same object: close to level 0, not equal.
    let l1 = Volume::from_store(&store, 1, 0).unwrap();
    let mut p = RenderParams::new(128, 128, cam, tf, RenderMode::Mip);
    p.samples_per_voxel = 2.0;
    let coarse = render(&l1, &p);
    let psnr = coarse.psnr(&out[1]);
    println!("mip level 1 vs level 0: PSNR {psnr:.1} dB");
    assert!(psnr > 15.0 && psnr.is_finite(), "{psnr}");
    let _: &Image = &coarse;
}
