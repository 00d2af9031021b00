//! Super-slices on the CPU: the N views of a stack of N parallel slices
//! for multi-view displays (`brickyard_core::views` says where each slice
//! lies and how far it shifts in each view). Device twin: `superslice.wgsl`.
//!
//! Each slice is classified by the transfer function (straight alpha, no
//! step correction) and the slices are composited in the order the thesis
//! gives: back to front from slice 0 to the reference slice `c = N/2`,
//! then front to back over the slices after it. With one accumulator that
//! is front-to-back compositing in the order `c, c−1, …, 0, c+1, …, N−1`,
//! which is what is done here.
//!
//! **Shared work.** A slice seen at a shift of `s` pixels in view `v` is
//! the same row of samples, read `s` columns further on, as in every other
//! view whose shift has the same fractional part. So each image row is
//! drawn as a few *layers* (one per slice and fractional shift, as wide as
//! a view plus the spread of the shifts) and every view reads its pixels
//! from them: N views cost about the samples of one, not N times as many.
//! Rows are independent (shifts are along x only), so a row's layers live
//! only while that row is drawn.

use crate::cpu::{FrameStats, Scene, Tiles};
use crate::image::Image;
use crate::optics::composite;
use crate::slice::slice_point;
use crate::walk::{Frame, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{add, dot, normalize, scale, Vec3};
use brickyard_core::views::{ViewRays, Views};
use brickyard_core::Sample;
use rayon::prelude::*;

/// One row of samples of slice `k`, at the fractional shift `frac`.
struct Layer {
    /// Plane origin of the slice.
    origin: Vec3,
    frac: f64,
    /// Whole-pixel shift of the layer's first column.
    lo: i64,
    width: usize,
    /// Where the layer starts in a row's scratch buffer.
    at: usize,
}

/// What view `v` reads of slice `k`: the layer and its column offset.
#[derive(Clone, Copy)]
struct Read {
    layer: usize,
    skip: usize,
}

/// Draw the super-slices of `views` through the plane `(origin, normal)`
/// into `img` (the whole frame: its tiles settle together), returning the
/// statistics and request collectors.
pub(crate) fn draw<T: Sample>(
    frame: &Frame<'_>,
    scene: &Scene,
    (origin, normal): (Vec3, Vec3),
    views: &Views,
    img: &mut Image,
    tiles: &mut Tiles,
) -> (FrameStats, Vec<Requests>) {
    let params = frame.params;
    let n = views.count;
    let rays = ViewRays::new(&params.camera, Some(views), params.width, params.height);
    let vw = rays.view_width() as usize;
    // Slices step towards the camera.
    // The plane's unit normal, for every pixel's `slice_point`.
    let unit = normalize(normal);
    let mut towards = unit;
    if dot(towards, params.camera.basis().forward) > 0.0 {
        towards = scale(towards, -1.0);
    }
    // Per slice, a layer per fractional part of the views' shifts,
    // spanning their whole-pixel parts (lo ..= hi).
    let mut layers: Vec<Layer> = vec![];
    let mut hi: Vec<i64> = vec![];
    let mut reads = vec![Read { layer: 0, skip: 0 }; (n * n) as usize];
    for k in 0..n {
        let first = layers.len();
        let slice_origin = add(origin, scale(towards, views.slice_depth(k)));
        for v in views.drawn() {
            let s = views.slice_shift(v, k);
            let (whole, frac) = (s.floor() as i64, s - s.floor());
            let i = match layers[first..].iter().position(|l| l.frac == frac) {
                Some(i) => first + i,
                None => {
                    layers.push(Layer {
                        origin: slice_origin,
                        frac,
                        lo: whole,
                        width: 0,
                        at: 0,
                    });
                    hi.push(whole);
                    layers.len() - 1
                }
            };
            layers[i].lo = layers[i].lo.min(whole);
            hi[i] = hi[i].max(whole);
            // For now the whole shift; made an offset below.
            reads[(v * n + k) as usize] = Read { layer: i, skip: 0 };
        }
    }
    let mut at = 0;
    for (l, h) in layers.iter_mut().zip(&hi) {
        l.width = vw + (h - l.lo) as usize;
        l.at = at;
        at += l.width;
    }
    let scratch_len = at;
    for v in views.drawn() {
        for k in 0..n {
            let r = &mut reads[(v * n + k) as usize];
            let l = &layers[r.layer];
            let whole = views.slice_shift(v, k).floor() as i64;
            r.skip = l.at + (whole - l.lo) as usize;
        }
    }
    let c = views.reference_slice();
    let order: Vec<u32> = (0..=c).rev().chain(c + 1..n).collect();
    let w = params.width as usize;
    let parts: Vec<(FrameStats, Requests)> = img
        .rgba
        .par_chunks_mut(w)
        .enumerate()
        .fold(
            || {
                (
                    Walker::<T>::new(frame, scene.channel),
                    frame.vm.requests(),
                    FrameStats::default(),
                    vec![[0f32; 4]; scratch_len],
                )
            },
            |(mut walker, mut req, mut st, mut scratch), (j, row)| {
                let py = j as f64 + 0.5;
                for l in &layers {
                    for (col, out) in scratch[l.at..l.at + l.width].iter_mut().enumerate() {
                        let px = (col as i64 + l.lo) as f64 + l.frac + 0.5;
                        let ray = rays.ray(0, px, py);
                        *out = match slice_point(&ray, l.origin, unit, scene.extent) {
                            Some((p, t)) => match walker.slice_value(p, t, &mut req, &mut st) {
                                Some(value) if !value.is_nan() => params.tf.lookup(value),
                                _ => [0.0; 4],
                            },
                            None => [0.0; 4],
                        };
                    }
                }
                for (col, v) in views.drawn().enumerate() {
                    let v = v as usize;
                    for (x, px) in row[col * vw..(col + 1) * vw].iter_mut().enumerate() {
                        let mut acc = [0f32; 4];
                        for &k in &order {
                            let r = reads[v * n as usize + k as usize];
                            composite(&mut acc, scratch[r.skip + x], 1.0);
                        }
                        *px = acc;
                    }
                }
                (walker, req, st, scratch)
            },
        )
        .map(|(mut walker, mut req, st, _)| {
            walker.flush(&mut req);
            (st, req)
        })
        .collect();
    let mut stats = FrameStats::default();
    let mut reqs = Vec::with_capacity(parts.len());
    for (s, r) in parts {
        stats.add(&s);
        reqs.push(r);
    }
    let settled = stats.exact == stats.samples;
    tiles.redo.iter_mut().for_each(|r| *r = !settled);
    (stats, reqs)
}
