//! The virtual memory against a naive model: random access sequences with
//! random budgets never return a wrong value, never exceed a budget,
//! eventually serve every request when the working set fits, and keep
//! making progress when it does not.

use brickyard_cache::brick::{BrickContent, BrickKey, LoadedBrick};
use brickyard_cache::vm::{VirtualMemory, VmConfig};
use brickyard_core::{plan_levels, DType, Dims3};
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
    fn unit(&mut self) -> f64 {
        (self.next() % 1_000_000) as f64 / 1_000_000.0
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// Whole levels in memory (u16), independent per level.
struct Model {
    levels: Vec<Dims3>,
    /// Per level, its voxels across the extent: level 0's over the plan's
    /// cumulative ratio (voxel `i` centred at `R·(i + ½)` level-0 voxels).
    spans: Vec<[f64; 3]>,
    data: Vec<Vec<u16>>,
}

impl Model {
    fn new(dims: Dims3, rng: &mut Lcg) -> Model {
        let plan = plan_levels(dims, [1.0; 3], [0.0; 3], [4; 3]);
        let levels: Vec<Dims3> = plan.levels.iter().map(|l| l.dims).collect();
        let spans = plan
            .levels
            .iter()
            .map(|l| [0, 1, 2].map(|a| dims[a] as f64 / l.cum_ratio[a] as f64))
            .collect();
        let data = levels
            .iter()
            .map(|d| {
                let n = (d[0] * d[1] * d[2]) as usize;
                // Smooth-ish data with a zero half, so empty bricks occur.
                (0..n)
                    .map(|i| {
                        let x = i as u64 % d[2];
                        if x < d[2] / 3 {
                            0
                        } else {
                            (rng.next() % 1000) as u16
                        }
                    })
                    .collect()
            })
            .collect();
        Model {
            levels,
            spans,
            data,
        }
    }
    fn at(&self, l: usize, v: [i64; 3]) -> f32 {
        let d = self.levels[l];
        let c = [0, 1, 2].map(|a| v[a].clamp(0, d[a] as i64 - 1) as u64);
        self.data[l][((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize] as f32
    }
    /// Reference sample: clamp-to-edge trilinear or nearest on the level.
    fn sample(&self, l: usize, p: [f64; 3], trilinear: bool) -> f32 {
        let d = self.levels[l];
        let pos = [0, 1, 2].map(|a| p[a] * self.spans[l][a]);
        if !trilinear {
            return self.at(
                l,
                [0, 1, 2].map(|a| (pos[a].floor() as i64).min(d[a] as i64 - 1)),
            );
        }
        let q = [0, 1, 2].map(|a| (pos[a] - 0.5).clamp(0.0, (d[a] - 1) as f64));
        let b = q.map(|x| x.floor());
        let f = [0, 1, 2].map(|a| q[a] - b[a]);
        let mut acc = 0.0;
        for dz in 0..2 {
            for dy in 0..2 {
                for dx in 0..2 {
                    let w = (if dz == 1 { f[0] } else { 1.0 - f[0] })
                        * (if dy == 1 { f[1] } else { 1.0 - f[1] })
                        * (if dx == 1 { f[2] } else { 1.0 - f[2] });
                    acc += w * self.at(l, [b[0] as i64 + dz, b[1] as i64 + dy, b[2] as i64 + dx])
                        as f64;
                }
            }
        }
        acc as f32
    }
    /// The brick with its apron, as the loader delivers it.
    fn brick(&self, key: BrickKey, brick: Dims3, apron: u64) -> Arc<LoadedBrick> {
        let l = key.level as usize;
        let a = apron as i64;
        let mut out = vec![];
        let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
        let mut uniform = true;
        let first = self.at(
            l,
            [0, 1, 2].map(|i| key.brick[i] as i64 * brick[i] as i64 - a),
        );
        for z in -a..brick[0] as i64 + a {
            for y in -a..brick[1] as i64 + a {
                for x in -a..brick[2] as i64 + a {
                    let v = [z, y, x];
                    let g = [0, 1, 2].map(|i| key.brick[i] as i64 * brick[i] as i64 + v[i]);
                    let val = self.at(l, g);
                    uniform &= val == first;
                    out.extend_from_slice(&(val as u16).to_le_bytes());
                    let inside = (0..3).all(|i| {
                        v[i] >= 0 && v[i] < brick[i] as i64 && g[i] < self.levels[l][i] as i64
                    });
                    if inside {
                        mn = mn.min(val as f64);
                        mx = mx.max(val as f64);
                    }
                }
            }
        }
        let content = if uniform && first == 0.0 {
            BrickContent::Empty
        } else if uniform {
            BrickContent::Constant(first as f64)
        } else {
            BrickContent::Data(out.into())
        };
        Arc::new(LoadedBrick {
            key,
            content,
            min: mn,
            max: mx,
            bytes_read: 0,
        })
    }
}

/// Counts of what a case exercised.
#[derive(Default)]
struct Seen {
    evicted_bricks: usize,
    evicted_pt_blocks: usize,
    orphans: usize,
    deep: usize,
    flagged: usize,
}

fn run_case(seed: u64, fits: bool, seen: &mut Seen) {
    let mut rng = Lcg(seed);
    let dims = [4 + rng.below(20), 4 + rng.below(30), 4 + rng.below(40)];
    let model = Model::new(dims, &mut rng);
    let brick = [4, 4, 4];
    let apron = 1;
    let padded_bytes = 6 * 6 * 6 * 2;
    let total_bricks: u64 = model
        .levels
        .iter()
        .map(|d| (0..3).map(|a| d[a].div_ceil(4)).product::<u64>())
        .sum();
    let slots = if fits {
        total_bricks + 2
    } else {
        2 + rng.below(total_bricks / 3 + 1)
    };
    let cfg = VmConfig {
        brick,
        apron,
        pt_block: [1 + rng.below(2), 2, 2],
        max_dir_entries: [4, 16, 64, 100_000][rng.below(4) as usize],
        pool_bytes: slots * padded_bytes,
        pt_cache_blocks: if fits { 4096 } else { 2 + rng.below(6) },
        request_cap: 1 + rng.below(12) as usize,
        upload_bytes_per_frame: padded_bytes * (1 + rng.below(8)),
    };
    let cap = cfg.request_cap;
    let pool_budget = cfg.pool_bytes;
    let mut vm = VirtualMemory::new(&model.levels, 1, DType::U16, cfg);
    if vm.layout().nmax() >= 3 {
        seen.deep += 1;
    }
    assert!(vm.pool_bytes() as u64 <= pool_budget, "pool over budget");
    // A fixed working set of positions, sampled every frame.
    let mut points: Vec<(usize, [f64; 3], bool)> = (0..60)
        .map(|_| {
            let l = rng.below(model.levels.len() as u64) as usize;
            (l, [rng.unit(), rng.unit(), rng.unit()], rng.below(2) == 0)
        })
        .collect();
    let mut complete_at = None;
    let mut inserted_total = 0;
    for frame in 0..400 {
        // A view that fits stays put until complete; otherwise it moves:
        // a few points change every frame.
        if !fits {
            for _ in 0..6 {
                let i = rng.below(points.len() as u64) as usize;
                let l = rng.below(model.levels.len() as u64) as usize;
                points[i] = (l, [rng.unit(), rng.unit(), rng.unit()], rng.below(2) == 0);
            }
        }
        vm.begin_frame();
        let mut req = vm.requests();
        let mut served_exact = 0;
        for &(l, p, tri) in &points {
            let r = vm.sample(l, 0, p, tri, &mut req);
            if let Some(lv) = r.level {
                let lv = lv as usize;
                assert!(lv >= l, "served finer than asked");
                let want = model.sample(lv, p, tri);
                assert!(
                    (r.value - want).abs() <= 1e-3 * want.abs().max(1.0),
                    "seed {seed} frame {frame}: level {lv} p {p:?} tri {tri}: got {} want {want}",
                    r.value
                );
                if lv == l {
                    served_exact += 1;
                }
            }
        }
        let rep = vm.end_frame([&req]);
        assert!(rep.requests.len() <= cap);
        if served_exact == points.len() && complete_at.is_none() {
            complete_at = Some(frame);
            if fits {
                break;
            }
        }
        let bricks: Vec<_> = rep
            .requests
            .iter()
            .map(|&k| model.brick(k, brick, apron))
            .collect();
        let ins = vm.insert(&bricks);
        inserted_total += ins.inserted + ins.flagged;
        seen.evicted_bricks += ins.evicted_bricks;
        seen.evicted_pt_blocks += ins.evicted_pt_blocks;
        seen.orphans += ins.orphans_reclaimed;
        seen.flagged += ins.flagged;
        vm.check_invariants()
            .unwrap_or_else(|e| panic!("seed {seed} frame {frame}: {e}"));
    }
    if fits {
        assert!(complete_at.is_some(), "seed {seed}: view never completed");
    } else {
        assert!(inserted_total > 0, "seed {seed}: no progress");
    }
}

#[test]
fn random_sequences_fitting_working_set_complete_with_exact_values() {
    let mut seen = Seen::default();
    for seed in 0..40 {
        run_case(seed, true, &mut seen);
    }
    assert!(
        seen.deep > 0 && seen.flagged > 0,
        "cases must cover deep hierarchies and flagged bricks"
    );
}

#[test]
fn random_sequences_with_tight_budgets_stay_correct_and_progress() {
    let mut seen = Seen::default();
    for seed in 100..160 {
        run_case(seed, false, &mut seen);
    }
    // The tight cases must really evict bricks and page-table blocks and
    // reclaim the orphans of evicted blocks.
    assert!(seen.evicted_bricks > 0, "no brick eviction");
    assert!(seen.evicted_pt_blocks > 0, "no page-table block eviction");
    assert!(seen.orphans > 0, "no orphan reclaimed");
    assert!(seen.deep > 0, "no deep hierarchy");
}

#[test]
fn the_pool_gets_every_slot_its_budget_pays_for() {
    let levels: Vec<Dims3> = vec![[256, 256, 256], [128, 128, 128]];
    // A slot: a padded 10³ u8 brick and the range of its one cell (8
    // bytes).
    let slot = 1000 + 8;
    for slots in [1u64, 7, 1024, 1025, 1509, 2047, 24147] {
        let cfg = VmConfig {
            brick: [8; 3],
            apron: 1,
            pool_bytes: slots * slot + slot - 1,
            ..Default::default()
        };
        let vm = VirtualMemory::new(&levels, 1, DType::U8, cfg);
        assert_eq!(vm.pool_slots() as u64, slots, "budget for {slots} slots");
        assert_eq!(vm.pool_bytes() as u64, slots * slot);
        vm.check_invariants().unwrap();
    }
}

#[test]
fn a_pool_has_no_more_slots_than_the_volume_has_bricks() {
    // 40×24×17 in 8³ bricks: 5·3·3 = 45 at level 0, 3·2·2 = 12 at level 1
    // (20×12×9), 2·1·1 = 2 at level 2 (10×6×5): 59 bricks per channel.
    let levels: Vec<Dims3> = vec![[17, 24, 40], [9, 12, 20], [5, 6, 10]];
    let slot = 1000 + 8;
    for (channels, budget, want) in [
        (1usize, 1u64 << 30, 59u64),
        (3, 1 << 30, 177),
        (1, 59 * slot, 59),
        (1, 58 * slot, 58),
        (2, 100 * slot + 7, 100),
    ] {
        let cfg = VmConfig {
            brick: [8; 3],
            apron: 1,
            pool_bytes: budget,
            ..Default::default()
        };
        let vm = VirtualMemory::new(&levels, channels, DType::U8, cfg);
        assert_eq!(
            vm.pool_slots() as u64,
            want,
            "{channels} channel(s), a budget of {budget} bytes"
        );
        assert_eq!(vm.pool_bytes() as u64, want * slot);
        vm.check_invariants().unwrap();
    }
}

#[test]
fn bricks_over_the_upload_budget_wait_and_the_rest_are_consumed() {
    let levels: Vec<Dims3> = vec![[64, 64, 64], [32, 32, 32]];
    let cfg = VmConfig {
        brick: [8; 3],
        apron: 1,
        pool_bytes: 100 * 1000,
        upload_bytes_per_frame: 3 * 1000,
        ..Default::default()
    };
    let mut vm = VirtualMemory::new(&levels, 1, DType::U8, cfg);
    let data = |x: u32| {
        Arc::new(LoadedBrick {
            key: BrickKey::new(0, 0, [0, 0, x]),
            content: BrickContent::Data(Arc::from(vec![x as u8 + 1; 1000])),
            min: 0.0,
            max: 255.0,
            bytes_read: 0,
        })
    };
    let batch: Vec<_> = (0..5).map(data).collect();
    vm.begin_frame();
    vm.end_frame(std::iter::empty());
    let r = vm.insert(&batch);
    // Three fit the budget; the other two are left for the next frame.
    assert_eq!((r.inserted, r.processed, r.bytes_uploaded), (3, 3, 3000));
    vm.begin_frame();
    vm.end_frame(std::iter::empty());
    let r = vm.insert(&batch[r.processed..]);
    assert_eq!((r.inserted, r.processed), (2, 2));
    // Offering a resident brick again consumes it without writing.
    let r = vm.insert(&batch[..1]);
    assert_eq!((r.inserted, r.processed), (0, 1));
    assert_eq!(vm.resident_bricks(), 5);
    vm.check_invariants().unwrap();
}

/// The page-table caches hold no more blocks than the volume's entries can
/// point to: a 1024³ volume of 32³ bricks under a cache of 4096 blocks per
/// level (the benchmarks' setting) takes the few blocks its 32³ bricks
/// need, not 4096 blocks of 16³ entries (128 MiB of tables, over a
/// software device's buffer limit).
#[test]
fn page_table_caches_hold_no_more_blocks_than_the_volume_needs() {
    let levels: Vec<_> = (0..6).map(|l| [1024u64 >> l; 3]).collect();
    for channels in [1usize, 3] {
        let vm = VirtualMemory::new(
            &levels,
            channels,
            DType::U8,
            VmConfig {
                brick: [32; 3],
                max_dir_entries: 8,
                pt_cache_blocks: 4096,
                ..Default::default()
            },
        );
        assert!(vm.layout().pt_levels() >= 1, "the layout has page tables");
        let lay = vm.layout();
        for n in 1..lay.nmax() {
            // Blocks of level n: one per entry of level n - 1, every level
            // and channel.
            let most: u64 = lay
                .real
                .iter()
                .map(|r| r[n - 1].iter().product::<u64>())
                .sum::<u64>()
                * channels as u64;
            let blocks = vm.tables()[n].len() / vm.pt_block_len(n);
            assert_eq!(
                blocks as u64,
                most.min(4096),
                "level {n}, {channels} channels"
            );
            assert!(
                most < 4096,
                "the volume needs fewer blocks than the cache holds"
            );
        }
        let entries: usize = vm.tables().iter().map(|t| t.len()).sum();
        assert!(entries * 8 < 4 << 20, "{entries} entries");
    }
}

/// Two views drawn in turn from one pool (the viewer's slices), whose
/// working sets fit it together, after a third view filled the pool with
/// bricks neither needs: both complete. A brick written after a frame's
/// LRU compaction sits where the slot it took was, at the tail; had the
/// next compaction left it there, each view's bricks would be the first
/// the other evicts, and neither would ever complete.
#[test]
fn views_drawn_in_turn_keep_each_others_bricks_when_together_they_fit() {
    let mut rng = Lcg(7);
    let model = Model::new([16, 16, 64], &mut rng);
    let brick = [4u64; 3];
    let padded_bytes = 6 * 6 * 6 * 2;
    let cfg = VmConfig {
        brick,
        apron: 1,
        pool_bytes: 40 * padded_bytes,
        request_cap: 1000,
        upload_bytes_per_frame: 1000 * padded_bytes,
        ..Default::default()
    };
    let mut vm = VirtualMemory::new(&model.levels, 1, DType::U16, cfg);
    // Points of level 0 (nearest voxel: one brick each) with x in `x0..x1`
    // and y, z anywhere.
    let mut view = |n: usize, x0: f64, x1: f64| -> Vec<[f64; 3]> {
        (0..n)
            .map(|_| [rng.unit(), rng.unit(), x0 + (x1 - x0) * rng.unit()])
            .collect()
    };
    let filler = view(200, 0.0, 1.0);
    let a = view(12, 0.0, 0.5);
    let b = view(12, 0.5, 1.0);
    // One frame of `points`: whether every point was served at level 0.
    let frame = |vm: &mut VirtualMemory, points: &[[f64; 3]]| -> bool {
        vm.begin_frame();
        let mut req = vm.requests();
        let mut exact = 0;
        for &p in points {
            let r = vm.sample(0, 0, p, false, &mut req);
            if let Some(lv) = r.level {
                let want = model.sample(lv as usize, p, false);
                assert_eq!(r.value, want, "level {lv} at {p:?}");
                exact += usize::from(lv == 0);
            }
        }
        let rep = vm.end_frame([&req]);
        let bricks: Vec<_> = rep
            .requests
            .iter()
            .map(|&k| model.brick(k, brick, 1))
            .collect();
        vm.insert(&bricks);
        vm.check_invariants().unwrap();
        exact == points.len()
    };
    for _ in 0..20 {
        frame(&mut vm, &filler);
    }
    let mut done = (false, false);
    for turn in 0..40 {
        done = (frame(&mut vm, &a), frame(&mut vm, &b));
        if done == (true, true) {
            assert!(turn <= 3, "complete only after {turn} turns");
            break;
        }
    }
    assert_eq!(done, (true, true), "the views never completed");
}
