//! A render shared by the MPI ranks ([`brickyard_run::share::Share`]):
//! bands of tiles on demand from rank 0 (image-parallel), the k-d regions
//! and the sort-last compositing of their partial images by binary swap
//! (a power-of-two count of ranks) or direct send (any other count), then
//! gathered on rank 0.

pub use crate::bands::{bands, Sections};
use crate::cluster::Cluster;
use crate::composite::{binary_swap, split_even, Operator};
use crate::kd::{eye_side, KdTree};
use anyhow::Result;
use brickyard_render::Image;
use brickyard_run::share::{Agreed, BrickBox, Share, Split};
use brickyard_store::builder::Team;
use mpi::datatype::{Partition, PartitionMut};
use mpi::point_to_point::send_receive_into;
use mpi::traits::*;
use mpi::Count;

const TAG_ASK: i32 = 11;
const TAG_BAND: i32 = 12;
const NONE: u32 = u32::MAX;

/// Bands of tile rows per rank on the CPU: more than one, so that a rank
/// that finishes early takes work a slower one would otherwise do.
pub const BANDS_PER_RANK: u32 = 4;

/// Bands per rank on a device: one, since every band costs a whole
/// device frame's fixed part (dispatch, counters, request table, read-back).
pub const DEVICE_BANDS_PER_RANK: u32 = 1;

/// The ranks of `mpirun` drawing one render.
pub struct RenderShare<'c> {
    c: &'c Cluster,
    split: Split,
    /// Rank 0: the view being handed out, its bands, the next one, and how
    /// many other ranks were told there are none left.
    view: Option<u32>,
    queue: Sections,
    told: usize,
    /// Image-parallel: bands per rank.
    per_rank: u32,
    /// Data-parallel: the tree of regions and how cuts map to the world.
    tree: Option<(KdTree, u64, [f64; 3])>,
    /// Other ranks: a request for the next band is out (asked before
    /// drawing the current one, so that rank 0's answer, which comes
    /// between its own frames, arrives while this rank draws).
    asked: bool,
}

impl<'c> RenderShare<'c> {
    pub fn new(c: &'c Cluster, split: Split) -> RenderShare<'c> {
        RenderShare {
            c,
            split,
            view: None,
            queue: Sections::default(),
            told: 0,
            per_rank: BANDS_PER_RANK,
            tree: None,
            asked: false,
        }
    }

    /// Image-parallel: `n` bands per rank (default [`BANDS_PER_RANK`]; the
    /// same on every rank, though rank 0 alone cuts the bands).
    pub fn bands_per_rank(mut self, n: u32) -> Self {
        self.per_rank = n.max(1);
        self
    }

    /// Rank 0: start handing out view `v` (once).
    fn open_view(&mut self, v: u32, rows: u32) {
        if self.view != Some(v) {
            self.view = Some(v);
            self.queue = Sections::new(bands(rows, self.c.size(), self.per_rank), self.c.size());
            self.told = 0;
        }
    }

    /// Rank 0: answer one request.
    fn answer(&mut self, from: i32, req: [u32; 2]) {
        let p = self.c.world().process_at_rank(from);
        if req[1] == 1 {
            // That rank stopped asking.
            self.told += 1;
            return;
        }
        let band = match self.queue.take(from as usize) {
            Some(b) => b,
            None => {
                self.told += 1;
                (NONE, NONE)
            }
        };
        p.send_with_tag(&[band.0, band.1][..], TAG_BAND);
    }

    /// Rank 0: answer every request waiting now.
    fn answer_waiting(&mut self) {
        let world = self.c.world();
        while let Some((msg, _)) = world
            .any_process()
            .immediate_matched_probe_with_tag(TAG_ASK)
        {
            let mut req = [0u32; 2];
            let st = msg.matched_receive_into(&mut req[..]);
            self.answer(st.source_rank(), req);
        }
    }

    /// Rank 0: answer until every other rank was told no band is left.
    fn answer_until_all_told(&mut self) {
        let world = self.c.world();
        while self.told < self.c.size() - 1 {
            let mut req = [0u32; 2];
            let st = world
                .any_process()
                .receive_into_with_tag(&mut req[..], TAG_ASK);
            self.answer(st.source_rank(), req);
        }
    }

    /// The pieces of this rank's final span, gathered on rank 0 into one
    /// image of `len` pixels: `spans[r]` is rank r's span.
    fn gather(
        &self,
        mine: &[[f32; 4]],
        spans: &[std::ops::Range<usize>],
        len: usize,
        w: u32,
        h: u32,
    ) -> Option<Image> {
        let root = self.c.world().process_at_rank(0);
        let flat: &[f32] = mine.as_flattened();
        if self.c.rank() == 0 {
            let counts: Vec<Count> = spans.iter().map(|s| (s.len() * 4) as Count).collect();
            let displs: Vec<Count> = spans.iter().map(|s| (s.start * 4) as Count).collect();
            let mut out = vec![[0f32; 4]; len];
            {
                let mut part = PartitionMut::new(out.as_flattened_mut(), &counts[..], &displs[..]);
                root.gather_varcount_into_root(flat, &mut part);
            }
            Some(Image {
                width: w,
                height: h,
                rgba: out,
            })
        } else {
            root.gather_varcount_into(flat);
            None
        }
    }
}

impl Share for RenderShare<'_> {
    fn rank(&self) -> usize {
        self.c.rank()
    }

    fn size(&self) -> usize {
        self.c.size()
    }

    fn split(&self) -> Split {
        self.split
    }

    fn ranks_on_node(&self) -> usize {
        self.c.ranks_on_node()
    }

    fn next_band(&mut self, view: u32, rows: u32) -> Result<Option<(u32, u32)>> {
        if self.c.rank() == 0 {
            self.open_view(view, rows);
            self.answer_waiting();
            if let Some(b) = self.queue.take(0) {
                return Ok(Some(b));
            }
            self.answer_until_all_told();
            return Ok(None);
        }
        let root = self.c.world().process_at_rank(0);
        if !self.asked {
            root.send_with_tag(&[view, 0][..], TAG_ASK);
        }
        let mut band = [0u32; 2];
        root.receive_into_with_tag(&mut band[..], TAG_BAND);
        self.asked = false;
        if band[0] == NONE {
            return Ok(None);
        }
        // Ask for the next one now: it is answered while this one is drawn.
        root.send_with_tag(&[view, 0][..], TAG_ASK);
        self.asked = true;
        Ok(Some((band[0], band[1])))
    }

    fn serve(&mut self) {
        if self.c.rank() == 0 && self.view.is_some() {
            self.answer_waiting();
        }
    }

    fn stop_asking(&mut self, view: u32) {
        if self.c.rank() == 0 {
            // The others take the bands left.
            if self.view == Some(view) {
                self.answer_until_all_told();
            }
        } else {
            let root = self.c.world().process_at_rank(0);
            if self.asked {
                // The band asked for ahead goes back undrawn (the run fails
                // anyway): take the answer, then say this rank stops (rank 0
                // counts either a "none" answer or the stop, never both).
                let mut band = [0u32; 2];
                root.receive_into_with_tag(&mut band[..], TAG_BAND);
                self.asked = false;
                if band[0] == NONE {
                    return;
                }
            }
            root.send_with_tag(&[view, 1][..], TAG_ASK);
        }
    }

    fn agree(&mut self, mine: Result<()>) -> Result<()> {
        self.c
            .agree(mine.map_err(|e| format!("{e:#}")))
            .map_err(|e| Agreed(e).into())
    }

    fn gather_times(&mut self, mine: f64) -> Vec<f64> {
        let root = self.c.world().process_at_rank(0);
        if self.c.rank() == 0 {
            let mut all = vec![0.0f64; self.c.size()];
            root.gather_into_root(&mine, &mut all[..]);
            all
        } else {
            root.gather_into(&mine);
            vec![]
        }
    }

    fn gather_text(&mut self, mine: String) -> Vec<String> {
        self.c
            .gather_bytes(mine.as_bytes())
            .into_iter()
            .map(|b| String::from_utf8_lossy(&b).into_owned())
            .collect()
    }

    fn sum(&mut self, mut img: Image) -> Result<Option<Image>> {
        self.c.sum_f32_to_root(img.rgba.as_flattened_mut());
        Ok((self.c.rank() == 0).then_some(img))
    }

    fn regions(
        &mut self,
        bricks: [u64; 3],
        brick: u64,
        spacing: [f64; 3],
        weight: &dyn Fn([u64; 3]) -> f64,
    ) -> Vec<BrickBox> {
        let tree = KdTree::build(bricks, self.c.size(), weight);
        let out = tree
            .regions()
            .iter()
            .map(|r| BrickBox { lo: r.lo, hi: r.hi })
            .collect();
        self.tree = Some((tree, brick, spacing));
        out
    }

    fn composite(&mut self, img: Image, mip: bool, eye: [f64; 3]) -> Result<(Option<Image>, f64)> {
        let t0 = std::time::Instant::now();
        let (tree, brick, spacing) = self
            .tree
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("composite: no regions (call region first)"))?;
        let side = eye_side(eye, [*brick; 3], *spacing);
        let op = if mip { Operator::Max } else { Operator::Over };
        let (n, rank) = (self.c.size(), self.c.rank());
        let len = img.rgba.len();
        let (w, h) = (img.width, img.height);
        let world = self.c.world();
        let out = if n.is_power_of_two() {
            let front = |a: std::ops::Range<usize>, b: std::ops::Range<usize>| {
                tree.front(a, b, &side).unwrap_or(false)
            };
            let mut buf = img.rgba;
            let stages = binary_swap(rank, n, len, &front);
            for st in &stages {
                let p = world.process_at_rank(st.partner as i32);
                let mut got = vec![[0f32; 4]; st.keep.len()];
                send_receive_into(
                    buf[st.send.clone()].as_flattened(),
                    &p,
                    got.as_flattened_mut(),
                    &p,
                );
                let mine = &mut buf[st.keep.clone()];
                if st.in_front {
                    op.apply(mine, &got);
                } else {
                    op.apply_under(mine, &got);
                }
            }
            let spans: Vec<std::ops::Range<usize>> = (0..n)
                .map(|r| {
                    binary_swap(r, n, len, &front)
                        .last()
                        .map_or(0..len, |s| s.keep.clone())
                })
                .collect();
            let keep = spans[rank].clone();
            self.gather(&buf[keep], &spans, len, w, h)
        } else {
            // Direct send: span r of every partial image goes to rank r,
            // which composites the n pieces in visibility order.
            let spans = split_even(len, n);
            let counts: Vec<Count> = spans.iter().map(|s| (s.len() * 4) as Count).collect();
            let displs: Vec<Count> = spans.iter().map(|s| (s.start * 4) as Count).collect();
            let mine = spans[rank].len();
            let rcounts: Vec<Count> = vec![(mine * 4) as Count; n];
            let rdispls: Vec<Count> = (0..n).map(|i| (i * mine * 4) as Count).collect();
            let mut pieces = vec![[0f32; 4]; mine * n];
            {
                let send = Partition::new(img.rgba.as_flattened(), &counts[..], &displs[..]);
                let mut recv =
                    PartitionMut::new(pieces.as_flattened_mut(), &rcounts[..], &rdispls[..]);
                world.all_to_all_varcount_into(&send, &mut recv);
            }
            let order = tree.order(&side);
            let piece = |r: usize| &pieces[r * mine..(r + 1) * mine];
            let mut acc = piece(order[0]).to_vec();
            for &r in &order[1..] {
                op.apply(&mut acc, piece(r));
            }
            self.gather(&acc, &spans, len, w, h)
        };
        Ok((out, t0.elapsed().as_secs_f64() * 1e3))
    }
}
