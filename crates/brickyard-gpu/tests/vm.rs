//! The device's page tables, walk and sampler against the host's virtual
//! memory (`entry_of`, `sample_at`), frame after frame, while bricks come
//! and go in a pool and page-table caches far smaller than the volume:
//! entries and slots exactly, values within 1e-5 (relative).

use brickyard_cache::brick::{BrickContent, BrickKey, LoadedBrick};
use brickyard_cache::vm::{VirtualMemory, VmConfig};
use brickyard_core::vm::PageFlag;
use brickyard_core::{plan_levels, DType, Dims3};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::vm::{DeviceVm, Query};
use std::sync::Arc;

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// Whole levels in memory: a zero third (empty bricks), a constant quarter
/// (constant bricks; negative for signed types) and random values.
struct Model {
    dtype: DType,
    levels: Vec<Dims3>,
    data: Vec<Vec<f64>>,
}

impl Model {
    fn new(dims: Dims3, dtype: DType, rng: &mut Lcg) -> Model {
        let levels: Vec<Dims3> = plan_levels(dims, [1.0; 3], [0.0; 3], [4; 3])
            .levels
            .iter()
            .map(|l| l.dims)
            .collect();
        let constant = if dtype == DType::U8 { 77.0 } else { -77.0 };
        let data = levels
            .iter()
            .map(|d| {
                (0..d[0] * d[1] * d[2])
                    .map(|i| {
                        let (x, y) = (i % d[2], i / d[2] % d[1]);
                        if x < d[2] / 3 {
                            0.0
                        } else if y < d[1] / 4 {
                            constant
                        } else {
                            let r = rng.below(250) as f64;
                            match dtype {
                                DType::F32 => r / 8.0 - 10.0,
                                DType::I16 => r * 3.0 - 300.0,
                                _ => r,
                            }
                        }
                    })
                    .collect()
            })
            .collect();
        Model {
            dtype,
            levels,
            data,
        }
    }

    fn at(&self, l: usize, v: [i64; 3]) -> f64 {
        let d = self.levels[l];
        let c = [0, 1, 2].map(|a| v[a].clamp(0, d[a] as i64 - 1) as u64);
        self.data[l][((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize]
    }

    fn bytes(&self, v: f64) -> Vec<u8> {
        match self.dtype {
            DType::U8 => vec![v as u8],
            DType::I16 => (v as i16).to_le_bytes().to_vec(),
            DType::F32 => (v as f32).to_le_bytes().to_vec(),
            d => unreachable!("{d:?}"),
        }
    }

    /// The brick with its apron, as the loader delivers it.
    fn brick(&self, key: BrickKey, brick: Dims3, apron: u64) -> Arc<LoadedBrick> {
        let l = key.level as usize;
        let a = apron as i64;
        let o = [0, 1, 2].map(|i| key.brick[i] as i64 * brick[i] as i64 - a);
        let first = self.at(l, o);
        let (mut out, mut uniform) = (vec![], true);
        for z in 0..brick[0] as i64 + 2 * a {
            for y in 0..brick[1] as i64 + 2 * a {
                for x in 0..brick[2] as i64 + 2 * a {
                    let v = self.at(l, [o[0] + z, o[1] + y, o[2] + x]);
                    uniform &= v == first;
                    out.extend_from_slice(&self.bytes(v));
                }
            }
        }
        let content = match (uniform, first == 0.0) {
            (true, true) => BrickContent::Empty,
            (true, false) => BrickContent::Constant(first),
            _ => BrickContent::Data(out.into()),
        };
        Arc::new(LoadedBrick {
            key,
            content,
            min: 0.0,
            max: 0.0,
            bytes_read: 0,
        })
    }
}

fn run_case(dtype: DType, seed: u64) {
    let Some(gpu) = test_gpu() else { return };
    let mut rng = Lcg(seed);
    let model = Model::new([40, 36, 44], dtype, &mut rng);
    let brick = [8u64; 3];
    let cfg = VmConfig {
        brick,
        apron: 1,
        pt_block: [2; 3],
        // A small directory forces intermediate page-table levels.
        max_dir_entries: 16,
        pool_bytes: 24 * (10 * 10 * 10 * dtype.size() as u64 + 512),
        pt_cache_blocks: 6,
        request_cap: 64,
        upload_bytes_per_frame: 1 << 30,
    };
    let mut vm = VirtualMemory::new(&model.levels, 1, dtype, cfg);
    assert!(vm.layout().nmax() >= 3, "two intermediate levels at least");
    let (mut dvm, first) = DeviceVm::new(&gpu, &mut vm).unwrap();
    assert_eq!(first.bricks, 0, "a fresh virtual memory holds no bricks");
    let grids: Vec<Dims3> = model
        .levels
        .iter()
        .map(|d| [0, 1, 2].map(|a| d[a].div_ceil(brick[a])))
        .collect();
    let (mut mapped, mut resident, mut evicted_seen) = (0, 0, 0);
    for frame in 0..12 {
        vm.begin_frame();
        let batch: Vec<Arc<LoadedBrick>> = (0..10)
            .map(|_| {
                let l = rng.below(model.levels.len() as u64) as usize;
                let g = grids[l];
                let b = [0, 1, 2].map(|a| rng.below(g[a]) as u32);
                model.brick(BrickKey::new(l as u8, 0, b), brick, 1)
            })
            .collect();
        let rep = vm.insert(&batch);
        evicted_seen += rep.evicted_bricks + rep.evicted_pt_blocks;
        vm.end_frame(std::iter::empty());
        let sync = dvm.sync(&gpu, &mut vm);
        let texel = dvm.pool.format.texel_bytes as u64;
        let padded_voxels: u64 = vm.padded().iter().product::<usize>() as u64;
        assert_eq!(
            sync.bytes,
            sync.entries as u64 * 16
                + sync.bricks as u64 * (padded_voxels * texel + vm.cell_grid().len() as u64 * 8),
            "only changes cross (entries; bricks with their cell ranges)"
        );
        // Queries: voxels of the bricks just inserted and random ones.
        let mut queries = vec![];
        for lb in &batch {
            let l = lb.key.level as usize;
            let v = [0, 1, 2].map(|a| {
                (lb.key.brick[a] as u64 * brick[a] + rng.below(brick[a]))
                    .min(model.levels[l][a] - 1)
            });
            queries.push((l, v));
        }
        for _ in 0..300 {
            let l = rng.below(model.levels.len() as u64) as usize;
            let v = [0, 1, 2].map(|a| rng.below(model.levels[l][a]));
            queries.push((l, v));
        }
        let qs: Vec<Query> = queries
            .iter()
            .map(|&(l, v)| {
                let f = [0, 1, 2].map(|_| rng.below(1000) as f32 / 1000.0);
                Query::new(l, 0, v, f)
            })
            .collect();
        let walked = dvm.lookup(&gpu, &qs).unwrap();
        let sampled = dvm.sample(&gpu, &qs).unwrap();
        for (i, q) in qs.iter().enumerate() {
            let (l, v) = queries[i];
            let want = vm.entry_of(l, 0, v);
            let (got, slot) = walked[i];
            assert_eq!(
                got,
                [want.word, want.value],
                "frame {frame}, level {l}, voxel {v:?}"
            );
            if want.flag() == PageFlag::Mapped {
                let g = vm.slot_grid(None);
                let c = want.slot().unwrap();
                assert_eq!(slot, Some((c[0] * g[1] + c[1]) * g[2] + c[2]));
                resident += 1;
            }
            if want.flag() != PageFlag::Unmapped {
                mapped += 1;
            }
            let f = [q.frac[0], q.frac[1], q.frac[2]];
            let want = vm.sample_at(l, 0, v, f);
            match (sampled[i], want) {
                (Some(g), Some(w)) => assert!(
                    (g - w).abs() <= 1e-5 * w.abs().max(1.0),
                    "{dtype:?} frame {frame}, level {l}, voxel {v:?} + {f:?}: device {g}, host {w}"
                ),
                (g, w) => assert_eq!(g.is_some(), w.is_some(), "level {l}, voxel {v:?}"),
            }
        }
    }
    // A mirror made of a virtual memory already in use holds the same.
    let (late, rep) = DeviceVm::new(&gpu, &mut vm).unwrap();
    assert_eq!(rep.bricks, vm.resident_slots().len());
    assert!(rep.bricks > 0);
    let qs: Vec<Query> = (0..400)
        .map(|_| {
            let l = rng.below(model.levels.len() as u64) as usize;
            let v = [0, 1, 2].map(|a| rng.below(model.levels[l][a]));
            Query::new(l, 0, v, [0.25, 0.5, 0.75])
        })
        .collect();
    let got = late.sample(&gpu, &qs).unwrap();
    assert_eq!(got.len(), qs.len(), "one sample per query");
    for (q, g) in qs.iter().zip(got) {
        let v = [0, 1, 2].map(|a| q.voxel[a] as u64);
        let w = vm.sample_at(q.level as usize, 0, v, [0.25, 0.5, 0.75]);
        assert_eq!(g.is_some(), w.is_some());
        if let (Some(g), Some(w)) = (g, w) {
            assert!(
                (g - w).abs() <= 1e-5 * w.abs().max(1.0),
                "late mirror: {g} vs {w}"
            );
        }
    }
    // The case exercised residency, flags and evictions.
    assert!(
        resident > 100 && mapped > resident && evicted_seen > 0,
        "{resident} {mapped} {evicted_seen}"
    );
}

#[test]
fn device_walk_and_sampler_equal_the_host_u8() {
    run_case(DType::U8, 1);
}

#[test]
fn device_walk_and_sampler_equal_the_host_i16() {
    run_case(DType::I16, 2);
}

#[test]
fn device_walk_and_sampler_equal_the_host_f32() {
    run_case(DType::F32, 3);
}
