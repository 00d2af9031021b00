//! DVR through the residency octree on the CPU (one to 64 channels): per
//! step the octree is descended from the root to the depth the step size
//! allows; a node every visible channel's transfer function hides at the
//! step's level is crossed in one landing, a node where every channel is
//! hidden or of one known value is composited without lookups, a node
//! where no visible channel has anything mapped is requested and crossed;
//! otherwise the steps inside the node are sampled, each channel looked up
//! through the page tables and, on a miss, substituted from the levels the
//! node's residency mask names. Steps, levels and mixing are those of
//! `multi.rs` (and of `dvr.rs` for one channel), so a complete frame
//! equals the page-table traversal. The per-node tables are made for each
//! frame from the octree's ranges as they are then (tightened by the
//! voxels of the bricks mapped so far, `Octree::sync`).

use super::Octree;
use crate::cpu::{FrameStats, Lod, Scene};
use crate::multi::{resident_run, take_run};
use crate::optics::{composite_visible, Media};
use crate::params::{ChannelStyle, RenderParams};
use crate::walk::{jump_before, start_at_entry, step_t, Frame, Grid, Track, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{intersect_box_inv, Ray, Vec3};
use brickyard_core::Sample;
use brickyard_core::TransferFunction;
use std::sync::{Arc, Mutex};

/// A thousandth of a step: landings lie this much early, and a step this
/// close to a node's face is taken as outside it.
const MARGIN: f64 = 1e-3;

/// Per-frame constants of the octree traversal.
pub(crate) struct OctFrame<'o> {
    pub(crate) tree: &'o Octree,
    /// Octree channel of each visible channel.
    channels: Vec<usize>,
    /// All visible channels' bits.
    all: u64,
    /// Per level, the deepest depth the step size allows.
    dmax: Vec<u32>,
    /// `[node][level]`: bit `i` set when visible channel `i` is hidden at
    /// that level in the node (its range is known and transparent), and
    /// bit `i` set when it has one known value in the node at that level.
    tables: Arc<Tables>,
}

/// The hidden and one-value bits of an [`OctFrame`] (see its fields).
#[derive(Debug)]
pub(crate) struct Tables {
    clear: Vec<u64>,
    homog: Vec<u64>,
}

/// What an [`OctFrame`]'s tables are made of: the octree's state
/// ([`Octree::id`], [`Octree::generation`]), the transfer functions and
/// channels, the step, the levels a step may ask for. Frames of one key
/// share their tables (kept in the octree, [`TableCache`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct TableKey {
    octree: (u64, u64),
    tf: TransferFunction,
    channels: Vec<ChannelStyle>,
    channel: usize,
    samples_per_voxel: u64,
    pub(crate) used: Vec<bool>,
}

impl TableKey {
    pub(crate) fn new(tree: &Octree, scene: &Scene, params: &RenderParams, lod: Lod) -> TableKey {
        let nl = scene.levels.len();
        TableKey {
            octree: (tree.id(), tree.generation()),
            tf: params.tf.clone(),
            channels: params.channels.clone(),
            channel: scene.channel,
            samples_per_voxel: params.samples_per_voxel.to_bits(),
            used: (0..nl).map(|l| level_used(lod, l, nl)).collect(),
        }
    }
}

/// Whether a step may ask for level `l` of `n` at `lod`.
pub(crate) fn level_used(lod: Lod, l: usize, n: usize) -> bool {
    match lod {
        Lod::Fixed(f) => l == f.min(n - 1),
        Lod::Auto { .. } => true,
    }
}

/// The last tables made from an octree, with their key (a clone of the
/// octree starts empty).
#[derive(Debug, Default)]
pub(crate) struct TableCache(Mutex<Option<(TableKey, Arc<Tables>)>>);

impl Clone for TableCache {
    fn clone(&self) -> TableCache {
        TableCache::default()
    }
}

impl<'o> OctFrame<'o> {
    /// The frame's tables ([`new_with`](Self::new_with)), reusing those
    /// of the last frame of the same `key` (kept in `tree`) when there is
    /// one.
    pub(crate) fn cached(
        tree: &'o Octree,
        frames: &[&Frame],
        levels: &[bool],
        key: TableKey,
    ) -> OctFrame<'o> {
        let kept = {
            let c = tree.tables.0.lock().unwrap_or_else(|e| e.into_inner());
            c.as_ref()
                .filter(|(k, _)| *k == key)
                .map(|(_, t)| t.clone())
        };
        let of = OctFrame::new_with(tree, frames, levels, kept);
        let mut c = tree.tables.0.lock().unwrap_or_else(|e| e.into_inner());
        *c = Some((key, of.tables.clone()));
        of
    }

    /// The tables for the visible channels whose walkers' frames are
    /// `frames` (their transfer functions) over `tree`; `levels`: the
    /// levels samples may ask for (others get no table entries set);
    /// `kept`: the hidden and one-value bits already made for them.
    fn new_with(
        tree: &'o Octree,
        frames: &[&Frame],
        levels: &[bool],
        kept: Option<Arc<Tables>>,
    ) -> OctFrame<'o> {
        assert!(frames.len() <= 64, "at most 64 channels");
        let f0 = frames[0];
        let nl = tree.levels();
        let nodes = super::node_count(tree.depth);
        let channels: Vec<usize> = frames.iter().map(|f| f.scene.channel).collect();
        let all = if frames.len() == 64 {
            u64::MAX
        } else {
            (1u64 << frames.len()) - 1
        };
        let ext = f0.scene.extent;
        let edge = ext.iter().copied().fold(f64::INFINITY, f64::min);
        let dmax = (0..nl)
            .map(|l| {
                let dt = f0.step[l.min(f0.levels() - 1)].0;
                (0..=tree.depth)
                    .rev()
                    .find(|&d| edge / (1u64 << d) as f64 >= dt)
                    .unwrap_or(0)
            })
            .collect();
        if let Some(tables) = kept {
            return OctFrame {
                tree,
                channels,
                all,
                dmax,
                tables,
            };
        }
        let mut clear = vec![0u64; nodes * nl];
        let mut homog = vec![0u64; nodes * nl];
        for node in 0..nodes {
            for (l, _) in levels.iter().enumerate().filter(|(_, u)| **u) {
                let (mut cb, mut hb) = (0u64, 0u64);
                for (i, (f, &c)) in frames.iter().zip(&channels).enumerate() {
                    if c >= tree.channels {
                        continue;
                    }
                    let [lo, hi] = tree.range_of(node, c, f.channel_level(l));
                    if lo.is_nan() || hi.is_nan() {
                        continue;
                    }
                    if !f.tf_eval.range_visible(lo, hi) {
                        cb |= 1 << i;
                    } else if lo == hi {
                        hb |= 1 << i;
                    }
                }
                clear[node * nl + l] = cb;
                homog[node * nl + l] = hb;
            }
        }
        OctFrame {
            tree,
            channels,
            all,
            dmax,
            tables: Arc::new(Tables { clear, homog }),
        }
    }
}

/// The node being sampled: its steps up to `until` are inside it.
#[derive(Clone, Copy)]
struct Inside {
    node: usize,
    level: usize,
    until: f64,
    clear: u64,
}

/// The ray parameter where `ray` leaves node `c` of depth `d` (world box).
#[inline]
fn node_exit(ray: &Ray, inv_dir: Vec3, ext: Vec3, d: u32, c: [u64; 3]) -> f64 {
    let s = (1u64 << d) as f64;
    let mut t = f64::INFINITY;
    for j in 0..3 {
        // World axis j is octree axis 2 − j.
        let i = c[2 - j] as f64;
        let (lo, hi) = (i / s * ext[j], (i + 1.0) / s * ext[j]);
        let dj = ray.dir[j];
        let tj = if dj > 0.0 {
            (hi - ray.origin[j]) * inv_dir[j]
        } else if dj < 0.0 {
            (lo - ray.origin[j]) * inv_dir[j]
        } else {
            continue;
        };
        if tj < t {
            t = tj;
        }
    }
    t
}

/// The first step index whose parameter is at least `t` less a margin.
#[inline]
fn first_step_from(t: f64, base_t: f64, inv_dt: f64) -> u64 {
    let x = (t - base_t) * inv_dt - 0.5 - MARGIN;
    if x <= 0.0 {
        return 0;
    }
    let i = x as u64;
    if (i as f64) < x {
        i + 1
    } else {
        i
    }
}

/// The pixel of `ray`: DVR of the channels of `walkers` (one per visible
/// channel, in the order of `of`'s tables) through the octree.
pub(crate) fn dvr_pixel<T: Sample>(
    walkers: &mut [Walker<'_, '_, T>],
    of: &OctFrame,
    (ray, entry): (&Ray, Option<(usize, f64)>),
    (req, st): (&mut Requests, &mut FrameStats),
) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    let f = walkers[0].f;
    let tree = of.tree;
    let nl = tree.levels();
    let ext = f.scene.extent;
    let d = ray.dir;
    let inv_dir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
    let Some((t0, t1)) = intersect_box_inv(ray, inv_dir, [0.0; 3], ext) else {
        return acc;
    };
    let mut level = f.level_at(t0);
    let mut next_t = f.next_level_t(level);
    // Nothing shows before the ray's entry depth at this level
    // ([`crate::entry`], as through the page tables): start there.
    let Some(c0) = start_at_entry(entry, level, t0, (t1, next_t)) else {
        return acc;
    };
    let (mut dt, mut inv_dt, mut exponent) = f.step[level];
    let mut base_t = t0;
    let mut k = 0u64;
    let mut inside: Option<Inside> = None;
    // The track of the current level, made at its first run.
    let mut track: Option<(usize, Track)> = None;
    'steps: loop {
        let t = step_t(base_t, k, dt);
        if t >= t1 {
            break;
        }
        k += 1;
        if t >= next_t {
            let l = f.level_at(t);
            if l != level {
                level = l;
                (dt, inv_dt, exponent) = f.step[level];
                base_t = t - 0.5 * dt;
                k = 1;
                inside = None;
            }
            next_t = f.next_level_t(level);
            if next_t <= t {
                next_t = t + dt;
            }
        }
        if t < c0 {
            k = jump_before(k, c0, next_t, base_t, inv_dt);
            continue;
        }
        st.steps += 1;
        let w = ray.at(t);
        let limit = t1.min(next_t);
        let cur = match inside {
            Some(n) if n.level == level && t < n.until => n,
            _ => {
                // Descend to the deepest node the step size allows.
                let p = [w[2] / ext[2], w[1] / ext[1], w[0] / ext[0]];
                let dmax = of.dmax[level];
                let mut found = None;
                for dd in 0..=dmax {
                    let s = 1u64 << dd;
                    let c = p.map(|x| ((x * s as f64) as u64).min(s - 1));
                    let node = tree.node(dd, c);
                    st.octree_nodes += 1;
                    let clear = of.tables.clear[node * nl + level];
                    let homog = of.tables.homog[node * nl + level];
                    let te = node_exit(ray, inv_dir, ext, dd, c);
                    if clear == of.all {
                        // Empty for every channel: land past it.
                        let kn = first_step_from(te.min(limit), base_t, inv_dt);
                        st.skipped_nodes += 1;
                        k = kn.max(k);
                        continue 'steps;
                    }
                    if (clear | homog) == of.all {
                        // One value per channel: composite it at every step
                        // inside, without lookups.
                        let c = mixed_constant(walkers, of, node, level);
                        let kn = first_step_from(te.min(limit), base_t, inv_dt).max(k);
                        st.skipped_nodes += 1;
                        if let Some(c) = c {
                            for _ in (k - 1)..kn {
                                if composite_visible(&mut acc, c, exponent) {
                                    break 'steps;
                                }
                            }
                        }
                        k = kn;
                        continue 'steps;
                    }
                    let open = of.all & !clear;
                    let mapped = (0..walkers.len())
                        .filter(|i| open >> i & 1 != 0)
                        .any(|i| tree.mask_of(node, of.channels[i]) != 0);
                    if !mapped {
                        // Nothing mapped for any channel shown: ask for the
                        // bricks here and cross the node.
                        let kn = first_step_from(te.min(limit), base_t, inv_dt).max(k);
                        let n = (kn - (k - 1)) as u32;
                        for (i, wk) in walkers.iter_mut().enumerate() {
                            if open >> i & 1 != 0 {
                                let lc = wk.f.channel_level(level);
                                let (vb, _) = f.coords(lc, w);
                                wk.enter(lc, vb, req, true);
                                wk.cache[lc].missed = wk.cache[lc].missed.saturating_add(n);
                            }
                        }
                        st.samples += n as u64;
                        st.unserved += n as u64;
                        k = kn;
                        continue 'steps;
                    }
                    if dd == dmax {
                        found = Some(Inside {
                            node,
                            level,
                            until: te - MARGIN * dt,
                            clear,
                        });
                        break;
                    }
                }
                let n = found.expect("the deepest node is kept");
                inside = Some(n);
                n
            }
        };
        let (vb, frac) = f.coords(level, w);
        // Every channel resident at the step's level here (or its brick
        // hidden): the steps through the brick in one run, as through the
        // page tables (the node's residency masks serve misses only; a
        // channel the node hides is sampled by its cells, and adds
        // nothing).
        let run = if f.scene.octree_runs {
            resident_run(walkers, level, vb, req)
        } else {
            None
        };
        if let Some(r) = run {
            let tr = match &track {
                Some((l, tr)) if *l == level => tr,
                _ => &track.insert((level, f.track(level, ray, inv_dir, t1))).1,
            };
            let g = Grid { base_t, dt, inv_dt };
            // To the brick's exit: its cells stand in for the nodes inside
            // (ending at each node's exit instead took 1.6–2× the time).
            let at = (tr, g, level);
            let (done, end) = take_run(f, &r, at, (w, k, limit), (exponent, true), &mut acc, st);
            if done {
                break;
            }
            k = end;
            inside = None;
            continue;
        }
        // Sample every channel the node does not hide.
        let mut mix = Media::NONE;
        for (i, wk) in walkers.iter_mut().enumerate() {
            if cur.clear >> i & 1 != 0 {
                continue;
            }
            // The channel's own level (its level range), usually the step's.
            let lc = wk.f.channel_level(level);
            let (cb, cf) = if lc == level {
                (vb, frac)
            } else {
                f.coords(lc, w)
            };
            if wk.enter(lc, cb, req, true).transparent {
                continue;
            }
            let mask = tree.mask_of(cur.node, of.channels[i]);
            let Some(v) = wk.value_masked(lc, w, cb, cf, mask, req, st) else {
                continue;
            };
            match wk.f.tf_eval.lookup_visible(v) {
                Some(c) => {
                    mix.add(c);
                }
                None => st.transparent += 1,
            }
        }
        if let Some(c) = mix.sample() {
            if composite_visible(&mut acc, c, exponent) {
                break;
            }
        }
    }
    acc
}

/// The mixed sample of a node where every visible channel is hidden or
/// of one value (`None`: nothing visible).
fn mixed_constant<T: Sample>(
    walkers: &[Walker<'_, '_, T>],
    of: &OctFrame,
    node: usize,
    level: usize,
) -> Option<[f32; 4]> {
    of.mixed(walkers.iter().map(|w| w.f), node, level)
}

impl OctFrame<'_> {
    /// The mixed colour (straight alpha) of node `node` at `level` where
    /// every visible channel (their frames `frames`, in table order) is
    /// hidden or of one value; `None`: nothing visible.
    fn mixed<'x, 'a: 'x>(
        &self,
        frames: impl Iterator<Item = &'x Frame<'a>>,
        node: usize,
        level: usize,
    ) -> Option<[f32; 4]> {
        let clear = self.tables.clear[node * self.tree.levels() + level];
        let mut mix = Media::NONE;
        for (i, f) in frames.enumerate() {
            if clear >> i & 1 != 0 {
                continue;
            }
            let v = self
                .tree
                .range_of(node, self.channels[i], f.channel_level(level))[0];
            if let Some(c) = f.tf_eval.lookup_visible(v) {
                mix.add(c);
            }
        }
        mix.sample()
    }

    /// This frame's tables for the device's traversal (`octree/dvr.wgsl`),
    /// the visible channels' frames `frames` in table order: per node and
    /// level 8 words (hidden channels' bits, low and high word; kind 0:
    /// descend or sample, 1: hidden for every channel, 2: one mixed colour;
    /// 0; the colour as f32 bits), then the residency masks as the octree
    /// keeps them (`[node][channel]`, every channel of the volume: what the
    /// device twin's masks buffer holds), then per level the deepest
    /// depth. Returns the words and where the masks and the depths start
    /// (relative).
    pub(crate) fn device_words(&self, frames: &[&Frame]) -> (Vec<u32>, u32, u32) {
        let nl = self.tree.levels();
        let nodes = super::node_count(self.tree.depth);
        let nv = self.channels.len();
        let mut words = Vec::with_capacity(nodes * (nl * 8 + nv) + nl);
        for node in 0..nodes {
            for l in 0..nl {
                let clear = self.tables.clear[node * nl + l];
                let homog = self.tables.homog[node * nl + l];
                let (kind, color) = if clear == self.all {
                    (1, [0.0; 4])
                } else if clear | homog == self.all {
                    (
                        2,
                        self.mixed(frames.iter().copied(), node, l)
                            .unwrap_or([0.0; 4]),
                    )
                } else {
                    (0, [0.0; 4])
                };
                words.extend([clear as u32, (clear >> 32) as u32, kind, 0]);
                words.extend(color.map(f32::to_bits));
            }
        }
        let masks = words.len() as u32;
        words.extend_from_slice(&self.tree.mask);
        let depths = words.len() as u32;
        words.extend(self.dmax.iter().copied());
        (words, masks, depths)
    }

    /// Where [`device_words`](Self::device_words)' masks and depths start
    /// and how many words it gives, for an octree of `depth` with `levels`
    /// levels and `channels` channels (the volume's).
    pub(crate) fn device_layout(depth: u32, levels: usize, channels: usize) -> [usize; 3] {
        let nodes = super::node_count(depth);
        let masks = nodes * levels * 8;
        let depths = masks + nodes * channels;
        [masks, depths, depths + levels]
    }
}
