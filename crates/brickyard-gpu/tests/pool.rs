//! The device brick pool holds exactly the voxels written into it, for every
//! data type, in every slot of a pool spread over several slot rows.

use brickyard_core::DType;
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::pool::DevicePool;

fn random_brick(dtype: DType, n: usize, seed: u64) -> (Vec<u8>, Vec<f64>) {
    let mut s = seed;
    let mut bytes = vec![];
    let mut values = vec![];
    for _ in 0..n {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let r = s >> 11;
        let v: f64 = match dtype {
            DType::U8 => (r % 256) as f64,
            DType::I8 => (r % 256) as f64 - 128.0,
            DType::U16 => (r % 65536) as f64,
            DType::I16 => (r % 65536) as f64 - 32768.0,
            DType::U32 => (r % (1 << 32)) as f64,
            DType::I32 => (r % (1 << 32)) as f64 - 2147483648.0,
            DType::F32 => ((r % 2_000_001) as f64 - 1e6) / 7.0,
            DType::F64 => ((r % 2_000_001) as f64 - 1e6) / 7.0,
        };
        let (b, x): (Vec<u8>, f64) = match dtype {
            DType::U8 => (vec![v as u8], v),
            DType::I8 => ((v as i8).to_le_bytes().to_vec(), v),
            DType::U16 => ((v as u16).to_le_bytes().to_vec(), v),
            DType::I16 => ((v as i16).to_le_bytes().to_vec(), v),
            DType::U32 => ((v as u32).to_le_bytes().to_vec(), v),
            DType::I32 => ((v as i32).to_le_bytes().to_vec(), v),
            DType::F32 => ((v as f32).to_le_bytes().to_vec(), v as f32 as f64),
            DType::F64 => (v.to_le_bytes().to_vec(), v),
        };
        bytes.extend_from_slice(&b);
        values.push(x);
    }
    (bytes, values)
}

#[test]
fn pool_holds_what_was_written_for_every_dtype() {
    let Some(gpu) = test_gpu() else { return };
    let padded = [6u32, 5, 7];
    let n = padded.iter().product::<u32>() as usize;
    for dtype in DType::ALL {
        // 40 slots, at most 4 per axis: rows and layers of slots.
        let mut pool = DevicePool::with_slots_per_axis(&gpu, dtype, padded, 40, 4).unwrap();
        assert_eq!((pool.slots(), pool.grid()), (40, [3, 4, 4]));
        // Slot 17: x = 17 mod 4, y = 17 / 4 mod 4, z = 17 / 16, in bricks.
        let o = pool.origin(17);
        assert_eq!((o.x, o.y, o.z), (7, 0, 6));
        let o = pool.origin(39);
        assert_eq!((o.x, o.y, o.z), (21, 5, 12));
        let fmt = pool.format;
        let mut written = vec![];
        for (i, s) in [0u32, 39, 17, 5, 38].into_iter().enumerate() {
            let (bytes, values) = random_brick(dtype, n, 1 + i as u64 * 31 + dtype as u64);
            pool.write(&gpu, s, &bytes);
            written.push((s, values));
        }
        assert_eq!(
            pool.take_uploaded(),
            5 * n as u64 * fmt.texel_bytes as u64,
            "{dtype:?}"
        );
        // Written together: 23 bricks (several to a staging line, several
        // slabs), some over bricks written one by one above.
        let order: Vec<u32> = (0..23u32).map(|i| (i * 7 + 3) % 40).collect();
        let together: Vec<(u32, Vec<u8>, Vec<f64>)> = order
            .iter()
            .map(|&s| {
                let (bytes, values) = random_brick(dtype, n, 1000 + s as u64 + dtype as u64);
                (s, bytes, values)
            })
            .collect();
        let items: Vec<brickyard_gpu::pool::BrickWrite> = together
            .iter()
            .map(|(s, b, _)| (*s, &b[..], &[][..]))
            .collect();
        pool.write_many(&gpu, &items);
        assert_eq!(
            pool.take_uploaded(),
            23 * n as u64 * fmt.texel_bytes as u64,
            "{dtype:?}"
        );
        written.retain(|(s, _)| !order.contains(s));
        assert!(!written.is_empty(), "some bricks written one by one remain");
        written.extend(together.into_iter().map(|(s, _, v)| (s, v)));
        for (s, values) in &written {
            let got = pool.read_slot(&gpu, *s).unwrap();
            assert_eq!(
                got.len(),
                values.len(),
                "{dtype:?} slot {s}: voxels read back"
            );
            for (i, (&g, &v)) in got.iter().zip(values).enumerate() {
                let ok = if fmt.exact {
                    // Unorm texels come back as texel/255 × 255: within
                    // a rounding of the product.
                    (g as f64 - v).abs() <= v.abs() * 1e-6
                } else {
                    g == v as f32
                };
                assert!(ok, "{dtype:?} slot {s} voxel {i}: {g} != {v} ({fmt:?})");
            }
        }
    }
}

#[test]
fn a_pool_beyond_the_device_limits_is_refused() {
    let Some(gpu) = test_gpu() else { return };
    let max = gpu.limits.max_texture_dimension_3d;
    let per_axis = max / 34;
    let too_many = per_axis * per_axis * per_axis + 1;
    let err = DevicePool::new(&gpu, DType::U8, [34; 3], too_many)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("limit"), "{err}");
}
