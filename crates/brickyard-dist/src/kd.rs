//! The k-d split of a volume's bricks among ranks for sort-last rendering:
//! each rank gets one box of whole bricks (a convex region), the boxes
//! partition the brick grid, and for any eye position the tree gives the
//! regions' visibility order (front to back) and, for binary swap, which
//! of two sibling groups of ranks lies in front.
//!
//! Ranks `lo..hi` of a node are split into `lo..mid` and `mid..hi` with
//! `mid = lo + (hi − lo)/2`, so that for a power-of-two count the sibling
//! groups of size `2^s` are exactly the pairs binary swap combines at
//! stage `s`. A node is cut across its longest axis (in bricks) where the
//! weight on the low side comes closest to its share of the ranks.

/// A box of bricks `[lo, hi)` per axis, `[z, y, x]` (level-0 brick
/// indices). Empty when any `hi ≤ lo` (more ranks than bricks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Region {
    pub lo: [u64; 3],
    pub hi: [u64; 3],
}

impl Region {
    pub fn is_empty(&self) -> bool {
        (0..3).any(|a| self.hi[a] <= self.lo[a])
    }

    pub fn bricks(&self) -> u64 {
        (0..3)
            .map(|a| self.hi[a].saturating_sub(self.lo[a]))
            .product()
    }

    pub fn contains(&self, b: [u64; 3]) -> bool {
        (0..3).all(|a| self.lo[a] <= b[a] && b[a] < self.hi[a])
    }

    /// The region in level-0 voxels `[z, y, x]`, clipped to `dims`.
    pub fn voxels(&self, brick: [u64; 3], dims: [u64; 3]) -> ([u64; 3], [u64; 3]) {
        (
            [0, 1, 2].map(|a| (self.lo[a] * brick[a]).min(dims[a])),
            [0, 1, 2].map(|a| (self.hi[a] * brick[a]).min(dims[a])),
        )
    }
}

#[derive(Debug, Clone)]
enum Node {
    Leaf {
        rank: usize,
        region: Region,
    },
    Split {
        /// Axis `[z, y, x]` index and the brick index of the cut: the low
        /// child holds bricks `< at`.
        axis: usize,
        at: u64,
        ranks: std::ops::Range<usize>,
        low: Box<Node>,
        high: Box<Node>,
    },
}

/// The k-d tree of `n` regions over a brick grid.
#[derive(Debug, Clone)]
pub struct KdTree {
    root: Node,
    n: usize,
}

impl KdTree {
    /// Split the grid of `nb` bricks (`[z, y, x]`) among `n ≥ 1` ranks,
    /// balancing `weight` (per brick, ≥ 0; e.g. 1 for bricks holding data).
    pub fn build(nb: [u64; 3], n: usize, weight: &dyn Fn([u64; 3]) -> f64) -> KdTree {
        assert!(n >= 1);
        let all = Region { lo: [0; 3], hi: nb };
        KdTree {
            root: split(all, 0..n, weight),
            n,
        }
    }

    pub fn ranks(&self) -> usize {
        self.n
    }

    /// Region of each rank, in rank order.
    pub fn regions(&self) -> Vec<Region> {
        let mut out = vec![
            Region {
                lo: [0; 3],
                hi: [0; 3]
            };
            self.n
        ];
        fn walk(n: &Node, out: &mut [Region]) {
            match n {
                Node::Leaf { rank, region } => out[*rank] = *region,
                Node::Split { low, high, .. } => {
                    walk(low, out);
                    walk(high, out);
                }
            }
        }
        walk(&self.root, &mut out);
        out
    }

    /// Visibility order, front to back, for an eye given by which side of
    /// each cut it lies on: `low_in_front(axis, at)` says whether the low
    /// side of the cut at brick index `at` on `axis` faces the eye.
    pub fn order(&self, low_in_front: &dyn Fn(usize, u64) -> bool) -> Vec<usize> {
        let mut out = vec![];
        fn walk(n: &Node, f: &dyn Fn(usize, u64) -> bool, out: &mut Vec<usize>) {
            match n {
                Node::Leaf { rank, .. } => out.push(*rank),
                Node::Split {
                    axis,
                    at,
                    low,
                    high,
                    ..
                } => {
                    if f(*axis, *at) {
                        walk(low, f, out);
                        walk(high, f, out);
                    } else {
                        walk(high, f, out);
                        walk(low, f, out);
                    }
                }
            }
        }
        walk(&self.root, low_in_front, &mut out);
        out
    }

    /// Whether the group of ranks `a` lies in front of its sibling group
    /// `b` (two children of one node); `None` when they are not siblings.
    pub fn front(
        &self,
        a: std::ops::Range<usize>,
        b: std::ops::Range<usize>,
        low_in_front: &dyn Fn(usize, u64) -> bool,
    ) -> Option<bool> {
        let want = a.start.min(b.start)..a.end.max(b.end);
        let mut n = &self.root;
        loop {
            match n {
                Node::Leaf { .. } => return None,
                Node::Split {
                    axis,
                    at,
                    ranks,
                    low,
                    high,
                } => {
                    if *ranks == want {
                        let a_low = a.start == ranks.start;
                        return Some(a_low == low_in_front(*axis, *at));
                    }
                    let mid = ranks.start + (ranks.end - ranks.start) / 2;
                    n = if want.end <= mid { low } else { high };
                    if want.start < mid && want.end > mid {
                        return None;
                    }
                }
            }
        }
    }
}

fn split(r: Region, ranks: std::ops::Range<usize>, weight: &dyn Fn([u64; 3]) -> f64) -> Node {
    let n = ranks.end - ranks.start;
    if n == 1 {
        return Node::Leaf {
            rank: ranks.start,
            region: r,
        };
    }
    let mid = ranks.start + n / 2;
    let share = (mid - ranks.start) as f64 / n as f64;
    // The longest axis that can be cut (ties: x, then y, then z).
    let ext = [0, 1, 2].map(|a| r.hi[a].saturating_sub(r.lo[a]));
    let axis = [2, 1, 0].into_iter().max_by_key(|&a| (ext[a], a)).unwrap();
    let at = if ext[axis] < 2 {
        // Nothing to cut: the low side keeps it all, the high side none.
        r.hi[axis]
    } else {
        // Weight of each slice across the axis.
        let slices: Vec<f64> = (r.lo[axis]..r.hi[axis])
            .map(|i| {
                let mut s = 0.0;
                let (o1, o2) = match axis {
                    0 => (1, 2),
                    1 => (0, 2),
                    _ => (0, 1),
                };
                for u in r.lo[o1]..r.hi[o1] {
                    for v in r.lo[o2]..r.hi[o2] {
                        let mut b = [0u64; 3];
                        b[axis] = i;
                        b[o1] = u;
                        b[o2] = v;
                        s += weight(b).max(0.0);
                    }
                }
                s
            })
            .collect();
        let total: f64 = slices.iter().sum();
        let mut best = (f64::INFINITY, r.lo[axis] + ext[axis] / 2);
        let mut acc = 0.0;
        // Cuts strictly inside, so that both sides hold bricks.
        for (k, s) in slices.iter().enumerate().take(slices.len() - 1) {
            acc += s;
            let frac = if total > 0.0 {
                acc / total
            } else {
                (k + 1) as f64 / slices.len() as f64
            };
            let d = (frac - share).abs();
            if d < best.0 {
                best = (d, r.lo[axis] + k as u64 + 1);
            }
        }
        best.1
    };
    let mut lo = r;
    let mut hi = r;
    lo.hi[axis] = at;
    hi.lo[axis] = at;
    Node::Split {
        axis,
        at,
        ranks: ranks.clone(),
        low: Box::new(split(lo, ranks.start..mid, weight)),
        high: Box::new(split(hi, mid..ranks.end, weight)),
    }
}

/// The eye's side of cuts in world space: `low_in_front(axis, at)` for an
/// eye at world `[x, y, z]`, bricks of `brick` voxels of `spacing` world
/// units (`[z, y, x]`), for a perspective camera; for an orthographic one
/// pass the eye far back along the view direction.
pub fn eye_side(eye: [f64; 3], brick: [u64; 3], spacing: [f64; 3]) -> impl Fn(usize, u64) -> bool {
    move |axis: usize, at: u64| {
        // World coordinate of the cut: voxel `at·brick` starts there (voxel
        // centres at (i + ½)·spacing, voxel i spans [i, i+1)·spacing).
        let w = at as f64 * brick[axis] as f64 * spacing[axis];
        let e = eye[2 - axis];
        e < w
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regions_partition_the_bricks_and_balance() {
        for nb in [[1u64, 1, 1], [3, 5, 7], [8, 8, 8], [2, 16, 3]] {
            for n in 1..=9usize {
                let t = KdTree::build(nb, n, &|_| 1.0);
                let regs = t.regions();
                assert_eq!(regs.len(), n);
                let mut count = 0;
                for z in 0..nb[0] {
                    for y in 0..nb[1] {
                        for x in 0..nb[2] {
                            let owners = regs.iter().filter(|r| r.contains([z, y, x])).count();
                            assert_eq!(owners, 1, "nb {nb:?} n {n}: brick {:?}", [z, y, x]);
                            count += 1;
                        }
                    }
                }
                let total: u64 = regs.iter().map(|r| r.bricks()).sum();
                assert_eq!(total, count);
                if (n as u64) <= nb[0] * nb[1] * nb[2] && n.is_power_of_two() && nb == [8, 8, 8] {
                    // Uniform weights, power-of-two counts of a cube: equal.
                    assert!(
                        regs.iter().all(|r| r.bricks() == 512 / n as u64),
                        "{regs:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn weights_move_the_cuts() {
        // All weight in the first x slab: two ranks split inside it.
        let t = KdTree::build([1, 1, 8], 2, &|b| if b[2] < 2 { 1.0 } else { 0.0 });
        let r = t.regions();
        assert_eq!(r[0].hi[2], 1, "{r:?}");
    }

    /// The visibility order agrees with distance along every cut: a region
    /// listed before another is never entirely behind a cut that separates
    /// them, as seen from the eye.
    #[test]
    fn order_puts_the_eye_side_first() {
        let nb = [4, 6, 5];
        for n in [2usize, 3, 4, 7, 8] {
            let t = KdTree::build(nb, n, &|_| 1.0);
            let regs = t.regions();
            for eye in [
                [-1.0, 2.0, 3.0],
                [9.0, -4.0, 0.5],
                [2.5, 3.5, 10.0],
                [2.0, 2.0, 2.0],
            ] {
                let side = eye_side(eye, [1, 1, 1], [1.0; 3]);
                let order = t.order(&side);
                let mut sorted = order.clone();
                sorted.sort();
                assert_eq!(sorted, (0..n).collect::<Vec<_>>());
                // Rays from the eye in many directions: the regions each
                // ray enters, sorted by where it enters them, come in the
                // visibility order.
                let pos = |r: usize| order.iter().position(|&q| q == r).unwrap();
                let mut g = 1u64;
                let mut rnd = || {
                    g = g
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    ((g >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
                };
                for _ in 0..2000 {
                    let d = [rnd(), rnd(), rnd()];
                    let mut hits: Vec<(f64, usize)> = vec![];
                    for (r, reg) in regs.iter().enumerate() {
                        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                        for ax in 0..3 {
                            // World axis k = 2 - ax (x, y, z).
                            let (e, dd) = (eye[2 - ax], d[2 - ax]);
                            let (lo, hi) = (reg.lo[ax] as f64, reg.hi[ax] as f64);
                            if dd.abs() < 1e-12 {
                                if e < lo || e > hi {
                                    t0 = f64::INFINITY;
                                }
                                continue;
                            }
                            let (a, b) = ((lo - e) / dd, (hi - e) / dd);
                            t0 = t0.max(a.min(b));
                            t1 = t1.min(a.max(b));
                        }
                        if t0 < t1 - 1e-9 {
                            hits.push((t0, r));
                        }
                    }
                    hits.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
                    for w in hits.windows(2) {
                        assert!(
                            pos(w[0].1) < pos(w[1].1),
                            "n {n} eye {eye:?} dir {d:?}: {hits:?} against order {order:?}"
                        );
                    }
                }
                if n.is_power_of_two() {
                    // Sibling groups: front() agrees with the order.
                    let mut s = 1;
                    while s < n {
                        for g in (0..n).step_by(2 * s) {
                            let (a, b) = (g..g + s, g + s..g + 2 * s);
                            let f = t.front(a.clone(), b.clone(), &side).unwrap();
                            assert_eq!(f, pos(a.start) < pos(b.start), "n {n} groups {a:?} {b:?}");
                        }
                        s *= 2;
                    }
                }
            }
        }
    }
}
