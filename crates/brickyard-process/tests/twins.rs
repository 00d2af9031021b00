//! Each device filter kernel against its CPU twin (the kernel of the same
//! name in `brickyard_process::kernels`, in f32) on random blocks, then
//! whole filters and filter chains on the device against the CPU's f64
//! filters, within the tolerance `brickyard_process::gpu` states. A missing
//! adapter fails these tests unless `BRICKYARD_SKIP_GPU=1` opts out
//! explicitly (see `brickyard_gpu::context::test_gpu`).

use brickyard_core::{as_bytes, as_bytes_mut, Dims3, Sample};
use brickyard_gpu::context::test_gpu;
use brickyard_process::kernels::{
    correlate_valid, gaussian_weights, square_root, sum_squares, threshold, window, SOBEL_D,
    SOBEL_S,
};
use brickyard_process::{
    build, build_on, DeviceFilter, Filter, FilterKernels, FilterSource, Pipeline,
};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::{Result, SourceMeta, VolumeSource};
use std::ops::Range;
use std::sync::Arc;

/// u = 2⁻²⁴, the unit roundoff of f32.
const U: f64 = 1.0 / 16_777_216.0;

fn kernels(block_voxels: u64) -> Option<Arc<FilterKernels>> {
    test_gpu().map(|g| FilterKernels::with_block_voxels(Arc::new(g), block_voxels))
}

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next() as f64 / (1u64 << 31) as f64
    }
    fn block(&mut self, n: usize, scale: f64) -> Vec<f32> {
        (0..n).map(|_| self.uniform(-scale, scale) as f32).collect()
    }
}

fn abs64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|x| x.abs() as f64).collect()
}

#[test]
fn correlate_valid_equals_cpu_twin() {
    let Some(k) = kernels(1 << 23) else { return };
    let mut rng = Lcg(1);
    // Counts that are not multiples of the workgroup (256), rows longer
    // than it, single rows, thin and cubic blocks.
    let shapes: [[usize; 3]; 6] = [
        [17, 19, 23],
        [5, 7, 300],
        [40, 3, 9],
        [1, 1, 513],
        [33, 65, 17],
        [70, 70, 70],
    ];
    let gauss = |s: f64, o: u32| -> Vec<f32> {
        gaussian_weights(s, o, 4.0)
            .iter()
            .map(|&v| v as f32)
            .collect()
    };
    let weights: Vec<Vec<f32>> = vec![
        gauss(0.6, 0),
        gauss(1.5, 0),
        gauss(2.0, 1),
        gauss(3.1, 0),
        SOBEL_D.map(|v| v as f32).to_vec(),
        SOBEL_S.map(|v| v as f32).to_vec(),
        (0..5).map(|_| rng.uniform(-2.0, 2.0) as f32).collect(),
    ];
    let (mut checked, mut exact) = (0, 0);
    for dims in shapes {
        let n: usize = dims.iter().product();
        let data = rng.block(n, 1000.0);
        for w in &weights {
            for axis in 0..3 {
                if dims[axis] < w.len() {
                    continue;
                }
                let (got, gd) = k.correlate_valid(&data, dims, axis, w).unwrap();
                let (want, wd) = correlate_valid(&data, dims, axis, w);
                assert_eq!(gd, wd);
                // Bound: the device may fuse each `acc + w·x` (Vulkan allows
                // it): at most one ulp of the running sum per tap.
                let wabs: Vec<f64> = w.iter().map(|v| v.abs() as f64).collect();
                let (s, _) = correlate_valid(&abs64(&data), dims, axis, &wabs);
                let taps = w.len() as f64;
                for i in 0..want.len() {
                    let tol = 2.0 * taps * U * s[i];
                    assert!(
                        (got[i] as f64 - want[i] as f64).abs() <= tol,
                        "{dims:?} axis {axis}, {} taps, voxel {i}: device {} vs twin {} (tolerance {tol})",
                        w.len(),
                        got[i],
                        want[i]
                    );
                }
                assert!(want.iter().any(|&v| v.abs() > 1.0), "a non-trivial result");
                checked += 1;
                exact += (got == want) as usize;
            }
        }
    }
    assert!(checked > 80, "{checked} cases");
    eprintln!("{checked} cases, {exact} of them bit for bit equal to the twin");
}

#[test]
fn sum_squares_and_square_root_equal_cpu_twins() {
    let Some(k) = kernels(1 << 23) else { return };
    let mut rng = Lcg(2);
    for n in [1usize, 255, 256, 257, 100_003] {
        let v = rng.block(n, 300.0);
        let acc: Vec<f32> = rng.block(n, 5e4).iter().map(|x| x.abs()).collect();
        for first in [true, false] {
            let got = k.sum_squares((!first).then_some(&acc[..]), &v).unwrap();
            let mut want = acc.clone();
            sum_squares(&mut want, &v, first);
            for i in 0..n {
                let bound =
                    2.0 * U * (if first { 0.0 } else { acc[i] as f64 } + (v[i] as f64).powi(2));
                assert!(
                    (got[i] as f64 - want[i] as f64).abs() <= bound,
                    "n {n}, first {first}, {i}: {} vs {}",
                    got[i],
                    want[i]
                );
            }
        }
        let got = k.square_root(&acc).unwrap();
        let mut want = acc.clone();
        square_root(&mut want);
        // Vulkan's sqrt is accurate to a few ulp, not correctly rounded.
        for i in 0..n {
            assert!(
                (got[i] as f64 - want[i] as f64).abs() <= 16.0 * U * want[i] as f64,
                "sqrt {}: {} vs {}",
                acc[i],
                got[i],
                want[i]
            );
        }
        assert!(want.iter().any(|&x| x > 10.0));
    }
}

#[test]
fn threshold_and_window_equal_cpu_twins_exactly() {
    let Some(k) = kernels(1 << 23) else { return };
    let mut rng = Lcg(3);
    // Bounds that are not f32 values, with the f32 values on each side of
    // them, exact f32 bounds, integers.
    let cases: [(f64, f64); 5] = [
        (0.1, 0.7),
        (-0.3, 2.7),
        (1000.0, 1000.0),
        (999.999_999_9, 1_000.000_000_1),
        (-1e-40, 1e-40),
    ];
    for (lo, hi) in cases {
        let mut v: Vec<f32> = rng.block(1001, 3.0);
        v.extend(rng.block(300, 2000.0).iter().map(|x| x.round()));
        for b in [lo, hi] {
            let f = b as f32;
            v.extend([f, f.next_up(), f.next_down(), f.next_up().next_up()]);
            v.extend([f.next_down().next_down(), 0.0, -0.0, f32::MIN_POSITIVE]);
        }
        let got = k.threshold(&v, lo).unwrap();
        let want = threshold(&v, lo);
        assert_eq!(got, want, "threshold({lo})");
        assert!(want.contains(&0.0) && want.contains(&1.0));
        let got = k.window(&v, lo, hi).unwrap();
        let want = window(&v, lo, hi);
        assert_eq!(got, want, "window({lo}, {hi})");
        assert!(want.contains(&0.0) && want.contains(&1.0));
    }
}

/// More voxels than 65535 workgroups of 256 hold: the workgroups spread
/// over two dimensions.
#[test]
fn a_dispatch_wider_than_65535_workgroups() {
    let Some(k) = kernels(1 << 25) else { return };
    let n = 65535 * 256 + 1000;
    let v: Vec<f32> = (0..n).map(|i| (i % 1013) as f32).collect();
    let got = k.threshold(&v, 506.5).unwrap();
    assert!(got == threshold(&v, 506.5), "threshold of {n} values");
    assert_eq!(got[n - 1], ((n - 1) % 1013 > 506) as u32 as f32);
}

/// Random padded blocks: each whole filter on the device (one
/// `DeviceFilter` reused over growing and shrinking blocks) against its
/// twin `Filter::apply::<f32>` and against the CPU's f64 filter.
#[test]
fn device_filters_equal_the_cpu_filters_on_random_blocks() {
    let Some(k) = kernels(1 << 23) else { return };
    let mut rng = Lcg(4);
    let filters = [
        Filter::Gauss([1.5, 0.7, 2.3]),
        Filter::Gauss([2.0; 3]),
        Filter::Gauss([0.2, 1.0, 0.2]),
        // Radius 0 on z and x: those passes are skipped on both sides; on
        // every axis: the input comes back.
        Filter::Gauss([0.1, 1.0, 0.1]),
        Filter::Gauss([0.1; 3]),
        Filter::GradMag([1.0, 2.0, 0.8]),
        Filter::Sobel,
        Filter::Threshold(0.25),
        Filter::Window(-10.0, 40.5),
    ];
    let shapes: [[usize; 3]; 5] = [
        [9, 13, 31],
        [1, 1, 1],
        [20, 7, 300],
        [3, 40, 5],
        [16, 16, 16],
    ];
    for f in filters {
        let mut dev = DeviceFilter::new(k.clone(), f.clone());
        let h = f.halo();
        for out in shapes {
            let pd: [usize; 3] = [0, 1, 2].map(|a| out[a] + 2 * h[a]);
            let n: usize = pd.iter().product();
            let data = rng.block(n, 100.0);
            let (got, gd) = dev.apply(&data, pd).unwrap();
            assert_eq!(gd, out);
            let twin = f.apply::<f32>(data.clone(), pd);
            let cpu = f.apply::<f64>(data.iter().map(|&v| v as f64).collect(), pd);
            assert_eq!(got.len(), cpu.len());
            let tol = f.device_tolerance(100.0);
            let what = format!("{f:?} on {out:?}");
            for i in 0..got.len() {
                let (g, t, c) = (got[i] as f64, twin[i] as f64, cpu[i]);
                assert!((g - t).abs() <= tol, "{what}, {i}: device {g} vs twin {t}");
                assert!(
                    (g - c as f32 as f64).abs() <= tol,
                    "{what}, {i}: device {g} vs CPU {c}"
                );
            }
            let big = cpu.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if f.components().is_some() && got.len() > 8 {
                assert!(
                    big > 1000.0 * tol,
                    "{what}: result {big} vs tolerance {tol}"
                );
            }
            if f.components().is_none() && got.len() > 8 {
                assert!(
                    cpu.contains(&0.0) && cpu.contains(&1.0),
                    "{what}: a trivial mask"
                );
            }
        }
    }
}

/// A volume held in memory.
struct Mem {
    meta: SourceMeta,
    data: Vec<u8>,
}

impl VolumeSource for Mem {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }
    fn read_region(
        &self,
        _c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        let s = self.meta.dtype.size();
        let d = self.meta.dims;
        let nx = (x.end - x.start) as usize * s;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                let i = ((zz * d[1] + yy) * d[2] + x.start) as usize * s;
                out[o..o + nx].copy_from_slice(&self.data[i..i + nx]);
                o += nx;
            }
        }
        Ok(())
    }
}

/// A generated u16 volume (Marschner–Lobb) with noise added, in memory.
fn generated(dims: Dims3) -> (Arc<dyn VolumeSource>, Vec<f64>) {
    let p = Procedural::new(Kind::MarschnerLobb, dims, brickyard_core::DType::U16);
    let n = dims.iter().product::<u64>() as usize;
    let mut v = vec![0u16; n];
    p.read_region(0, 0..dims[0], 0..dims[1], 0..dims[2], as_bytes_mut(&mut v))
        .unwrap();
    let mut rng = Lcg(5);
    for x in &mut v {
        *x = (*x as f64 * 0.9 + rng.uniform(0.0, 6000.0)) as u16;
    }
    let vals = v.iter().map(|x| x.to_f64()).collect();
    let meta = SourceMeta::new("/nonexistent/generated", dims, 1, u16::DTYPE);
    (
        Arc::new(Mem {
            meta,
            data: as_bytes(&v).to_vec(),
        }),
        vals,
    )
}

/// The whole volume of `src`, read in slabs of `slab` z-planes (as the
/// pyramid writer reads), as f64.
fn read_all(src: &dyn VolumeSource, slab: u64) -> Vec<f64> {
    let d = src.meta().dims;
    let plane = (d[1] * d[2]) as usize;
    let mut out = vec![];
    let mut z = 0;
    while z < d[0] {
        let h = slab.min(d[0] - z);
        match src.meta().dtype {
            brickyard_core::DType::F32 => {
                let mut b = vec![0f32; plane * h as usize];
                src.read_region(0, z..z + h, 0..d[1], 0..d[2], as_bytes_mut(&mut b))
                    .unwrap();
                out.extend(b.iter().map(|&v| v as f64));
            }
            brickyard_core::DType::U8 => {
                let mut b = vec![0u8; plane * h as usize];
                src.read_region(0, z..z + h, 0..d[1], 0..d[2], &mut b)
                    .unwrap();
                out.extend(b.iter().map(|&v| v as f64));
            }
            t => panic!("unexpected {t}"),
        }
        z += h;
    }
    out
}

fn stages(text: &str) -> Vec<Filter> {
    let p = Pipeline::parse(text).unwrap();
    p.ops
        .iter()
        .map(|op| match op {
            brickyard_process::Op::Gauss(brickyard_process::Sigma::Voxels(s)) => Filter::Gauss(*s),
            brickyard_process::Op::GradMag(brickyard_process::Sigma::Voxels(s)) => {
                Filter::GradMag(*s)
            }
            brickyard_process::Op::Sobel => Filter::Sobel,
            brickyard_process::Op::Threshold(t) => Filter::Threshold(*t),
            brickyard_process::Op::Window(a, b) => Filter::Window(*a, *b),
            o => panic!("{o:?}"),
        })
        .collect()
}

/// Whole chains through `FilterSource` on a generated volume: the device
/// (cut into pieces of at most 40 000 padded voxels, so that regions are
/// cut) against the CPU (blocks of 16³). Float results within the chain's
/// tolerance: each stage's own, plus the earlier stages' carried through
/// the later stages' gain. Masks equal, except where the float value before
/// the threshold lies within its tolerance of the bound.
#[test]
fn filter_chains_on_the_device_equal_the_cpu() {
    let Some(k) = kernels(40_000) else { return };
    let dims: Dims3 = [37, 45, 70];
    let (src, vals) = generated(dims);
    let m = vals.iter().fold(0.0f64, |a, &v| a.max(v.abs()));
    let block = [16; 3];
    for text in [
        "gauss(1.5)|sobel",
        "gradmag(1)",
        "gauss(2,1,0.6)",
        "gauss(2)|threshold(30000)",
        "gauss(1)|window(20000,34000.5)",
    ] {
        let p = Pipeline::parse(text).unwrap();
        let cpu = build(&p, src.clone(), 0, block).unwrap();
        let dev = build_on(&p, src.clone(), 0, block, Some(&k)).unwrap();
        let (want, got) = (
            read_all(cpu.source.as_ref(), 13),
            read_all(dev.source.as_ref(), 13),
        );
        let fs = stages(text);
        let last = fs.last().unwrap();
        if last.components().is_some() {
            // Tolerance of the chain (inputs of every stage are at most the
            // input's maximum times the gains before it).
            let (mut tol, mut scale) = (0.0, m);
            for f in &fs {
                tol = tol * f.gain() + f.device_tolerance(scale);
                scale *= f.gain();
            }
            let mut worst = 0.0f64;
            for i in 0..want.len() {
                let d = (got[i] - want[i]).abs();
                worst = worst.max(d);
                assert!(
                    d <= tol,
                    "{text}, voxel {i}: device {} vs CPU {} (tolerance {tol})",
                    got[i],
                    want[i]
                );
            }
            let big = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(big > 100.0 * tol, "{text}: result {big} vs tolerance {tol}");
            eprintln!("{text}: worst difference {worst:.3e}, tolerance {tol:.3e}, largest value {big:.3e}");
        } else {
            // The float stage before the mask, on the CPU.
            let before = Pipeline::parse(text.rsplit_once('|').unwrap().0).unwrap();
            let g = read_all(
                build(&before, src.clone(), 0, block)
                    .unwrap()
                    .source
                    .as_ref(),
                13,
            );
            let f0 = &fs[0];
            let tol = f0.device_tolerance(m);
            let (lo, hi) = match last {
                Filter::Threshold(t) => (*t, f64::NAN),
                Filter::Window(a, b) => (*a, *b),
                _ => unreachable!(),
            };
            let mut differ = 0;
            for i in 0..want.len() {
                if got[i] != want[i] {
                    differ += 1;
                    let near = (g[i] - lo).abs() <= tol || (g[i] - hi).abs() <= tol;
                    assert!(near, "{text}, voxel {i}: masks differ at {} (bounds {lo}, {hi}, tolerance {tol})", g[i]);
                }
            }
            let ones = want.iter().filter(|&&v| v == 1.0).count();
            assert!(
                ones > want.len() / 20 && ones < want.len() * 19 / 20,
                "{text}: {ones} of {} set",
                want.len()
            );
            assert!(
                differ <= want.len() / 1000,
                "{text}: {differ} voxels differ"
            );
            eprintln!("{text}: {ones} voxels set, {differ} differ");
        }
    }
}

/// A stage whose halo alone does not fit the device's block stays on the
/// CPU, and computes the same as without a device.
#[test]
fn a_stage_too_wide_for_the_device_block_stays_on_the_cpu() {
    let Some(k) = kernels(3000) else { return };
    let (src, _) = generated([12, 13, 14]);
    let wide =
        FilterSource::new(src.clone(), 0, Filter::Gauss([8.0; 3]), "g", [8; 3]).with_device(&k);
    assert!(!wide.on_device());
    let narrow =
        FilterSource::new(src.clone(), 0, Filter::Gauss([1.0; 3]), "g", [8; 3]).with_device(&k);
    assert!(narrow.on_device());
    let cpu = FilterSource::new(src, 0, Filter::Gauss([8.0; 3]), "g", [8; 3]);
    assert_eq!(read_all(&wide, 5), read_all(&cpu, 5));
}
