//! Connected components of a mask, out of core.
//!
//! **Pass 1** ([`label_pass1`]) walks the volume one layer of blocks (along
//! z) at a time; the blocks of a layer are labelled in parallel, each on its
//! own (local labels in raster order of their first voxel). Every local
//! label gets a global provisional id (block offsets in block scan order).
//! A block keeps only its six faces; the face voxels of touching blocks
//! (across faces, and for 26-connectivity across edges and corners too) are
//! compared and their provisional ids joined in a union–find. Only the
//! upper z faces of the previous layer are kept between layers. Per
//! provisional id the pass records voxel count, box, coordinate sums, the
//! sum of an intensity volume and the raster index of the first voxel.
//!
//! The final label of a component is its rank in raster order (z, y, x) of
//! its first voxel: 1, 2, … — the same numbering as an in-core flood fill
//! that scans the volume in C order, so the result does not depend on the
//! block size.
//!
//! **Pass 2** ([`LabelSource`]) is a volume source: reading a region labels
//! the blocks it touches again (the same local labels, since the same mask
//! is read) and maps them to final labels.
//!
//! Memory: per block in flight its mask and labels; per layer the faces of
//! its blocks; for the whole volume the offsets of the blocks and 8 bytes of
//! union–find plus one record of statistics per provisional id (a piece of
//! a component inside one block), never the voxels.

use crate::filter::{place, read_f64, tile};
use crate::kernels::{label_block, neighbour_offsets};
use brickyard_core::{as_bytes_mut, dispatch_dtype, DType, Dims3};
use brickyard_store::source::check_region;
use brickyard_store::{Progress, Result, SourceMeta, StoreError, VolumeSource};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Statistics of one final label. Coordinates are voxel indices `[z, y, x]`
/// of the labelled level; `max` is inclusive.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelStats {
    pub label: u32,
    pub voxels: u64,
    pub min: [u64; 3],
    pub max: [u64; 3],
    pub centroid: [f64; 3],
    /// Mean of the intensity volume over the label's voxels, if one was given.
    pub mean: Option<f64>,
}

impl LabelStats {
    /// The row of the statistics table.
    pub fn row(&self) -> brickyard_core::label_table::LabelRow {
        brickyard_core::label_table::LabelRow {
            voxels: self.voxels,
            min: self.min,
            max: self.max,
            centroid: self.centroid,
            mean: self.mean,
        }
    }
}

#[derive(Debug, Clone)]
struct Frag {
    count: u64,
    min: [u64; 3],
    max: [u64; 3],
    sum: [f64; 3],
    sum_i: f64,
    first: u64,
}

impl Frag {
    fn new() -> Frag {
        Frag {
            count: 0,
            min: [u64::MAX; 3],
            max: [0; 3],
            sum: [0.0; 3],
            sum_i: 0.0,
            first: u64::MAX,
        }
    }
    fn merge(&mut self, o: &Frag) {
        self.count += o.count;
        for a in 0..3 {
            self.min[a] = self.min[a].min(o.min[a]);
            self.max[a] = self.max[a].max(o.max[a]);
            self.sum[a] += o.sum[a];
        }
        self.sum_i += o.sum_i;
        self.first = self.first.min(o.first);
    }
}

/// The result of pass 1: what pass 2 needs to write final labels.
#[derive(Debug, Clone)]
pub struct Labeling {
    pub dims: Dims3,
    pub block: Dims3,
    pub conn: u8,
    nblocks: Dims3,
    /// Provisional id of local label 1 of each block (block scan order).
    offsets: Vec<u64>,
    /// Provisional id → final label.
    map: Vec<u32>,
    /// Statistics of labels `1..=count`, in label order.
    pub stats: Vec<LabelStats>,
}

impl Labeling {
    /// Number of labels (components).
    pub fn count(&self) -> u32 {
        self.stats.len() as u32
    }

    /// Number of provisional ids (pieces of components inside one block).
    pub fn provisional(&self) -> usize {
        self.map.len()
    }

    /// Bytes it holds (the labels' statistics, the map of pieces, the
    /// blocks' offsets): what pass 2 keeps beside the writer.
    pub fn bytes(&self) -> u64 {
        (self.stats.len() * std::mem::size_of::<LabelStats>()
            + self.map.len() * 4
            + self.offsets.len() * 8) as u64
    }

    fn block_index(&self, b: [u64; 3]) -> usize {
        ((b[0] * self.nblocks[1] + b[1]) * self.nblocks[2] + b[2]) as usize
    }

    fn block_box(&self, b: [u64; 3]) -> [Range<u64>; 3] {
        [0, 1, 2].map(|a| b[a] * self.block[a]..((b[a] + 1) * self.block[a]).min(self.dims[a]))
    }
}

struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    fn find(&mut self, mut i: usize) -> usize {
        while self.parent[i] != i {
            self.parent[i] = self.parent[self.parent[i]];
            i = self.parent[i];
        }
        i
    }
    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            // The smaller id becomes the root: deterministic.
            let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
            self.parent[hi] = lo;
        }
    }
}

/// One labelled block: local label count, statistics per local label, and
/// its faces: `faces[axis][0 | 1]` the labels on its low / high face along
/// `axis`, a 2D array over the two other axes (in z, y, x order).
struct BlockOut {
    n: u32,
    frags: Vec<Frag>,
    faces: [[Vec<u32>; 2]; 3],
    bdims: [usize; 3],
}

/// The two axes other than `a`, in order.
fn others(a: usize) -> (usize, usize) {
    match a {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

fn face_at(face: &[u32], a: usize, bd: [usize; 3], l: [usize; 3]) -> u32 {
    let (p, q) = others(a);
    face[l[p] * bd[q] + l[q]]
}

/// Read a block of `src` as a mask (non-zero, NaN included, is foreground).
fn read_mask(src: &dyn VolumeSource, c: usize, r: &[Range<u64>; 3]) -> Result<Vec<bool>> {
    let n = r.iter().map(|x| (x.end - x.start) as usize).product();
    dispatch_dtype!(src.meta().dtype, T => {
        let mut buf = vec![T::default(); n];
        src.read_region(c, r[0].clone(), r[1].clone(), r[2].clone(), as_bytes_mut(&mut buf))?;
        let zero = T::default();
        Ok(buf.into_iter().map(|v| v != zero).collect())
    })
}

fn label_one(
    mask: &dyn VolumeSource,
    channel: usize,
    conn: u8,
    r: &[Range<u64>; 3],
    intensity: Option<(&dyn VolumeSource, usize)>,
    dims: Dims3,
) -> Result<BlockOut> {
    let m = read_mask(mask, channel, r)?;
    let bd: [usize; 3] = [0, 1, 2].map(|a| (r[a].end - r[a].start) as usize);
    let (labels, n) = label_block(&m, bd, conn);
    drop(m);
    let inten = match intensity {
        Some((src, c)) => Some(dispatch_dtype!(src.meta().dtype, T => {
            read_f64::<T>(src, c, r.clone(), bd)?
        })),
        None => None,
    };
    let mut frags = vec![Frag::new(); n as usize];
    let mut i = 0;
    for z in 0..bd[0] {
        let gz = r[0].start + z as u64;
        for y in 0..bd[1] {
            let gy = r[1].start + y as u64;
            for x in 0..bd[2] {
                let l = labels[i];
                if l != 0 {
                    let gx = r[2].start + x as u64;
                    let f = &mut frags[l as usize - 1];
                    if f.count == 0 {
                        f.first = (gz * dims[1] + gy) * dims[2] + gx;
                    }
                    f.count += 1;
                    for (a, g) in [gz, gy, gx].into_iter().enumerate() {
                        f.min[a] = f.min[a].min(g);
                        f.max[a] = f.max[a].max(g);
                        f.sum[a] += g as f64;
                    }
                    if let Some(v) = &inten {
                        f.sum_i += v[i];
                    }
                }
                i += 1;
            }
        }
    }
    let faces = [0, 1, 2].map(|a| {
        let (p, q) = others(a);
        [0, bd[a] - 1].map(|fa| {
            let mut f = Vec::with_capacity(bd[p] * bd[q]);
            let mut l = [0usize; 3];
            l[a] = fa;
            for ip in 0..bd[p] {
                l[p] = ip;
                for iq in 0..bd[q] {
                    l[q] = iq;
                    f.push(labels[(l[0] * bd[1] + l[1]) * bd[2] + l[2]]);
                }
            }
            f
        })
    });
    Ok(BlockOut {
        n,
        frags,
        faces,
        bdims: bd,
    })
}

/// Pass 1 over channel `channel` of `mask` (any voxel type; non-zero is
/// foreground) with blocks of `block` voxels. `intensity`: a volume (and
/// channel) on the same grid whose mean per label goes into the statistics.
/// Progress counts mask voxels.
pub fn label_pass1(
    mask: &dyn VolumeSource,
    channel: usize,
    conn: u8,
    block: Dims3,
    intensity: Option<(&dyn VolumeSource, usize)>,
    progress: &dyn Progress,
    cancel: &AtomicBool,
) -> Result<Labeling> {
    label_pass1_within(
        mask,
        channel,
        conn,
        block,
        intensity,
        progress,
        cancel,
        u64::MAX,
    )
}

/// Bytes of bookkeeping a piece of a component (a component's part in one
/// block) takes until the labels are numbered, beyond the growing lists of
/// pieces and parents (counted at their capacity): its statistics merged
/// per component, its root, its entry in the map, and at most one label's
/// statistics.
pub const BYTES_PER_PIECE: u64 =
    (std::mem::size_of::<Option<Frag>>() + 8 + 4 + std::mem::size_of::<LabelStats>()) as u64;

/// [`label_pass1`] keeping its bookkeeping within `max_bytes`
/// ([`BYTES_PER_PIECE`] a piece): beyond it the pass stops with an error
/// that says how much the volume's pieces so far need (a noisy mask has
/// millions of components).
#[allow(clippy::too_many_arguments)]
pub fn label_pass1_within(
    mask: &dyn VolumeSource,
    channel: usize,
    conn: u8,
    block: Dims3,
    intensity: Option<(&dyn VolumeSource, usize)>,
    progress: &dyn Progress,
    cancel: &AtomicBool,
    max_bytes: u64,
) -> Result<Labeling> {
    let meta = mask.meta();
    if conn != 6 && conn != 26 {
        return Err(StoreError::invalid(
            &meta.path,
            "connectivity",
            format!("expected 6 or 26, found {conn}"),
        ));
    }
    if let Some((src, _)) = intensity {
        if src.meta().dims != meta.dims {
            return Err(StoreError::invalid(
                &src.meta().path,
                "dims",
                format!(
                    "the intensity volume is {:?}, the mask {:?}: they must be on one grid",
                    src.meta().dims,
                    meta.dims
                ),
            ));
        }
    }
    let dims = meta.dims;
    let block = block.map(|b| b.max(1));
    let nb: Dims3 = [0, 1, 2].map(|a| dims[a].div_ceil(block[a]));
    progress.start(dims.iter().product());
    let mut lab = Labeling {
        dims,
        block,
        conn,
        nblocks: nb,
        offsets: vec![0; nb.iter().product::<u64>() as usize],
        map: vec![],
        stats: vec![],
    };
    let mut uf = UnionFind { parent: vec![] };
    let mut frags: Vec<Frag> = vec![];
    let offs = neighbour_offsets(conn);
    // Upper z faces of the previous layer, per (by, bx).
    let mut prev: Vec<(Vec<u32>, [usize; 3])> = vec![];
    for bz in 0..nb[0] {
        if cancel.load(Ordering::Relaxed) {
            return Err(StoreError::Interrupted);
        }
        let list: Vec<[u64; 3]> = (0..nb[1])
            .flat_map(|by| (0..nb[2]).map(move |bx| [bz, by, bx]))
            .collect();
        let outs: Vec<Result<BlockOut>> = list
            .par_iter()
            .map(|&b| {
                if cancel.load(Ordering::Relaxed) {
                    return Err(StoreError::Interrupted);
                }
                let r = lab.block_box(b);
                let o = label_one(mask, channel, conn, &r, intensity, dims)?;
                progress.inc(o.bdims.iter().product::<usize>() as u64);
                Ok(o)
            })
            .collect();
        let outs: Vec<BlockOut> = outs.into_iter().collect::<Result<_>>()?;
        for (b, o) in list.iter().zip(&outs) {
            let bi = lab.block_index(*b);
            lab.offsets[bi] = frags.len() as u64;
            let start = uf.parent.len();
            uf.parent.extend(start..start + o.n as usize);
            frags.extend(o.frags.iter().cloned());
        }
        // Join across the faces of touching blocks: each block with the
        // touching blocks before it in scan order.
        for (b, o) in list.iter().zip(&outs) {
            let ob = lab.offsets[lab.block_index(*b)] as usize;
            let bb = lab.block_box(*b);
            for bo in &offs {
                let before = bo[0] < 0 || (bo[0] == 0 && (bo[1] < 0 || (bo[1] == 0 && bo[2] < 0)));
                if !before {
                    continue;
                }
                let n: [i64; 3] = [0, 1, 2].map(|a| b[a] as i64 + bo[a]);
                if (0..3).any(|a| n[a] < 0 || n[a] >= nb[a] as i64) {
                    continue;
                }
                let n = n.map(|v| v as u64);
                let a0 = (0..3).find(|&a| bo[a] != 0).unwrap();
                let (nface, nbd): (&[u32], [usize; 3]) = if bo[0] < 0 {
                    let p = &prev[(n[1] * nb[2] + n[2]) as usize];
                    (&p.0, p.1)
                } else {
                    let k = (n[1] * nb[2] + n[2]) as usize;
                    let no = &outs[k];
                    (&no.faces[a0][1], no.bdims)
                };
                let bface: &[u32] = &o.faces[a0][if bo[a0] < 0 { 0 } else { 1 }];
                let on = lab.offsets[lab.block_index(n)] as usize;
                let nbox = lab.block_box(n);
                join_pair(
                    &mut uf,
                    (bface, o.bdims, &bb, ob),
                    (nface, nbd, &nbox, on),
                    *bo,
                    a0,
                    &offs,
                );
            }
        }
        prev = outs
            .into_iter()
            .map(|mut o| (std::mem::take(&mut o.faces[0][1]), o.bdims))
            .collect();
        let need = (frags.capacity() * std::mem::size_of::<Frag>() + uf.parent.capacity() * 8)
            as u64
            + frags.len() as u64 * BYTES_PER_PIECE;
        if need > max_bytes {
            let done = (bz + 1) as f64 / nb[0] as f64;
            return Err(StoreError::invalid(
                &meta.path,
                "memory",
                format!(
                    "labelling: {} pieces of components in the first {:.0} % of the volume \
                     already need {} MiB of bookkeeping (about {} bytes each), more \
                     than the {} MiB the memory budget leaves it; about {} MiB for the whole \
                     volume (a noisy mask has a component per few voxels: smooth or threshold \
                     it first, or give more memory)",
                    frags.len(),
                    100.0 * done,
                    need >> 20,
                    need / frags.len().max(1) as u64,
                    max_bytes >> 20,
                    ((need as f64 / done) as u64) >> 20
                ),
            ));
        }
    }
    if cancel.load(Ordering::Relaxed) {
        return Err(StoreError::Interrupted);
    }
    // Final numbering: components in raster order of their first voxel.
    let np = frags.len();
    let mut roots = vec![0usize; np];
    let mut comp: Vec<Option<Frag>> = vec![None; np];
    for (i, f) in frags.iter().enumerate() {
        // (Millions of pieces take seconds: a Ctrl-C is seen meanwhile.)
        if i % (1 << 18) == 0 && cancel.load(Ordering::Relaxed) {
            return Err(StoreError::Interrupted);
        }
        let r = uf.find(i);
        roots[i] = r;
        match &mut comp[r] {
            Some(c) => c.merge(f),
            slot => *slot = Some(f.clone()),
        }
    }
    let mut order: Vec<(u64, usize)> = comp
        .iter()
        .enumerate()
        .filter_map(|(r, c)| c.as_ref().map(|c| (c.first, r)))
        .collect();
    order.sort_unstable();
    if order.len() > u32::MAX as usize {
        return Err(StoreError::invalid(
            &meta.path,
            "labels",
            format!("{} components do not fit in u32 labels", order.len()),
        ));
    }
    let mut final_of = vec![0u32; np];
    for (k, &(_, r)) in order.iter().enumerate() {
        final_of[r] = k as u32 + 1;
        let c = comp[r].as_ref().unwrap();
        let cnt = c.count as f64;
        lab.stats.push(LabelStats {
            label: k as u32 + 1,
            voxels: c.count,
            min: c.min,
            max: c.max,
            centroid: c.sum.map(|s| s / cnt),
            mean: intensity.map(|_| c.sum_i / cnt),
        });
    }
    lab.map = roots.iter().map(|&r| final_of[r]).collect();
    Ok(lab)
}

/// Join the provisional ids of adjacent voxels of block `b` and block `n`,
/// `n = b + bo` (block offset), through their faces along axis `a0` (the
/// first axis where `bo` is non-zero).
fn join_pair(
    uf: &mut UnionFind,
    b: (&[u32], [usize; 3], &[Range<u64>; 3], usize),
    n: (&[u32], [usize; 3], &[Range<u64>; 3], usize),
    bo: [i64; 3],
    a0: usize,
    offs: &[[i64; 3]],
) {
    let (bface, bbd, bbox, boff) = b;
    let (nface, nbd, nbox, noff) = n;
    // Local coordinate ranges in b of the voxels next to n.
    let vr: [Range<usize>; 3] = [0, 1, 2].map(|a| match bo[a] {
        -1 => 0..1,
        1 => bbd[a] - 1..bbd[a],
        _ => 0..bbd[a],
    });
    let ds: Vec<[i64; 3]> = offs
        .iter()
        .copied()
        .filter(|d| (0..3).all(|a| bo[a] == 0 || d[a] == bo[a]))
        .collect();
    for vz in vr[0].clone() {
        for vy in vr[1].clone() {
            for vx in vr[2].clone() {
                let v = [vz, vy, vx];
                let lb = face_at(bface, a0, bbd, v);
                if lb == 0 {
                    continue;
                }
                for d in &ds {
                    // Global coordinate of the neighbour, then local in n.
                    let mut l = [0usize; 3];
                    let mut inside = true;
                    for a in 0..3 {
                        let g = bbox[a].start as i64 + v[a] as i64 + d[a];
                        if g < nbox[a].start as i64 || g >= nbox[a].end as i64 {
                            inside = false;
                            break;
                        }
                        l[a] = (g - nbox[a].start as i64) as usize;
                    }
                    if !inside {
                        continue;
                    }
                    let ln = face_at(nface, a0, nbd, l);
                    if ln != 0 {
                        uf.union(boff + lb as usize - 1, noff + ln as usize - 1);
                    }
                }
            }
        }
    }
}

/// A box and the final labels in it.
type Part = ([Range<u64>; 3], Vec<u32>);

/// Pass 2: the final labels (u32) as a volume source.
pub struct LabelSource {
    mask: Arc<dyn VolumeSource>,
    channel: usize,
    lab: Arc<Labeling>,
    meta: SourceMeta,
}

impl LabelSource {
    pub fn new(mask: Arc<dyn VolumeSource>, channel: usize, lab: Arc<Labeling>) -> LabelSource {
        assert_eq!(mask.meta().dims, lab.dims, "labelling of another volume");
        let meta = LabelSource::meta_of(mask.meta(), lab.conn);
        LabelSource {
            mask,
            channel,
            lab,
            meta,
        }
    }

    /// What the labels (u32) of a mask of `im` with connectivity `conn`
    /// look like as a volume: its grid, one channel, marked as labels.
    pub fn meta_of(im: &SourceMeta, conn: u8) -> SourceMeta {
        let mut meta = SourceMeta::new(
            im.path.join(format!("label({conn})")),
            im.dims,
            1,
            DType::U32,
        );
        meta.spacing = im.spacing;
        meta.origin = im.origin;
        meta.unit = im.unit.clone();
        meta.labels = true;
        meta
    }

    pub fn labeling(&self) -> &Labeling {
        &self.lab
    }
}

impl VolumeSource for LabelSource {
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
    ) -> Result<()> {
        check_region(&self.meta, c, &z, &y, &x, out);
        let r = [z, y, x];
        let lab = &self.lab;
        // The label blocks the region touches.
        let br: [Range<u64>; 3] = [0, 1, 2].map(|a| {
            r[a].start / lab.block[a]
                ..r[a]
                    .end
                    .div_ceil(lab.block[a])
                    .max(r[a].start / lab.block[a])
        });
        let blocks = tile(&br, [1, 1, 1]);
        let parts: Vec<Result<Part>> = blocks
            .par_iter()
            .map(|bb| {
                let b = [bb[0].start, bb[1].start, bb[2].start];
                let bx = lab.block_box(b);
                let m = read_mask(self.mask.as_ref(), self.channel, &bx)?;
                let bd: [usize; 3] = [0, 1, 2].map(|a| (bx[a].end - bx[a].start) as usize);
                let (l, _) = label_block(&m, bd, lab.conn);
                let off = lab.offsets[lab.block_index(b)] as usize;
                // The part of the block inside the region.
                let ib: [Range<u64>; 3] =
                    [0, 1, 2].map(|a| bx[a].start.max(r[a].start)..bx[a].end.min(r[a].end));
                let mut v =
                    Vec::with_capacity(ib.iter().map(|s| (s.end - s.start) as usize).product());
                for z in ib[0].clone() {
                    for y in ib[1].clone() {
                        let row = (((z - bx[0].start) * bd[1] as u64 + y - bx[1].start)
                            * bd[2] as u64) as usize;
                        for x in ib[2].clone() {
                            let k = l[row + (x - bx[2].start) as usize];
                            v.push(if k == 0 {
                                0
                            } else {
                                lab.map[off + k as usize - 1]
                            });
                        }
                    }
                }
                Ok((ib, v))
            })
            .collect();
        let o = brickyard_core::cast_slice_mut::<u32>(out);
        for p in parts {
            let (ib, v) = p?;
            place(o, &r, &ib, &v);
        }
        Ok(())
    }

    fn preferred_read(&self) -> Dims3 {
        self.lab.block
    }
}

/// The statistics as CSV: one row per label; coordinates in voxels of the
/// labelled level, `[z, y, x]` columns, box bounds inclusive.
pub fn stats_csv(stats: &[LabelStats]) -> String {
    let mut v = vec![];
    write_stats_csv(&mut v, stats).expect("writing to memory");
    String::from_utf8(v).expect("UTF-8")
}

/// [`stats_csv`] written to `w` row by row (millions of labels make a
/// table of hundreds of MB: not held in memory whole).
pub fn write_stats_csv(w: &mut dyn std::io::Write, stats: &[LabelStats]) -> std::io::Result<()> {
    writeln!(w, "{}", brickyard_core::label_table::HEADER)?;
    for l in stats {
        brickyard_core::label_table::write_row(w, l.label as u64, &l.row())?;
    }
    Ok(())
}

/// The statistics as JSON: `{"count": N, "connectivity": C, "labels": [{...}]}`.
pub fn stats_json(lab: &Labeling, extra: &[(&str, String)]) -> String {
    let mut v = vec![];
    write_stats_json(&mut v, lab, extra).expect("writing to memory");
    String::from_utf8(v).expect("UTF-8")
}

/// [`stats_json`] written to `w` label by label.
pub fn write_stats_json(
    w: &mut dyn std::io::Write,
    lab: &Labeling,
    extra: &[(&str, String)],
) -> std::io::Result<()> {
    write!(
        w,
        "{{\n  \"count\": {},\n  \"connectivity\": {},\n  \"dims_zyx\": [{}, {}, {}],\n",
        lab.count(),
        lab.conn,
        lab.dims[0],
        lab.dims[1],
        lab.dims[2]
    )?;
    for (k, v) in extra {
        writeln!(w, "  \"{k}\": {v},")?;
    }
    write!(w, "  \"labels\": [")?;
    for (i, l) in lab.stats.iter().enumerate() {
        w.write_all(if i == 0 { b"\n" } else { b",\n" })?;
        brickyard_core::label_table::write_json_row(w, l.label as u64, &l.row())?;
    }
    w.write_all(b"\n  ]\n}\n")
}

/// A JSON string literal.
pub fn json_string(s: &str) -> String {
    let mut o = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => o += "\\\"",
            '\\' => o += "\\\\",
            c if (c as u32) < 0x20 => o += &format!("\\u{:04x}", c as u32),
            c => o.push(c),
        }
    }
    o.push('"');
    o
}
