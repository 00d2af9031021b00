//! Slices on the CPU: the plane as the camera sees it. Each pixel's ray
//! meets the plane (`t ≥ 0`, inside the closed world box); the walker
//! samples every channel shown there at the level the footprint at `t`
//! asks for, and the pixel is the transfer function's colour (one
//! channel) or the channels' mix, opaque; a label image's slice takes the
//! nearest voxel and shows each label in its own colour. `slice.wgsl` is
//! the device twin.

use crate::cpu::FrameStats;
use crate::optics::{label_color_of, mix_channels, slice_color};
use crate::params::{RenderParams, MAX_CHANNELS};
use crate::walk::Walker;
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{dot, sub, Ray, Vec3};
use brickyard_core::Sample;

/// Where `ray` meets the plane through `origin` with the unit normal `n`
/// (normalized once per frame by the caller), if that is in front of the
/// ray and inside the box `[0, extent]`: the world point and the ray
/// parameter.
#[inline]
pub fn slice_point(ray: &Ray, origin: Vec3, n: Vec3, extent: Vec3) -> Option<(Vec3, f64)> {
    meet(ray, dot(sub(origin, ray.origin), n), n, extent)
}

/// [`slice_point`] given its numerator `num = (origin − ray.origin)·n`.
#[inline(always)]
fn meet(ray: &Ray, num: f64, n: Vec3, extent: Vec3) -> Option<(Vec3, f64)> {
    let denom = dot(ray.dir, n);
    if denom == 0.0 {
        return None;
    }
    let t = num / denom;
    if t.is_nan() || t < 0.0 {
        return None;
    }
    let w = ray.at(t);
    // (Three tests, not an iterator over the axes: that cost a call per
    // pixel.)
    let inside = |a: usize| w[a] >= 0.0 && w[a] <= extent[a];
    if !(inside(0) && inside(1) && inside(2)) {
        return None;
    }
    Some((w, t))
}

/// A frame's slice plane for one view and one channel: the plane through
/// `origin` with unit normal `n`, and, where every ray starts at the eye
/// (perspective), [`slice_point`]'s numerator, the same for all pixels.
pub(crate) struct Plane {
    pub(crate) origin: Vec3,
    pub(crate) n: Vec3,
    pub(crate) extent: Vec3,
    /// `(origin − eye)·n` for rays from `eye`.
    pub(crate) from_eye: Option<(Vec3, f64)>,
}

impl Plane {
    pub(crate) fn new(origin: Vec3, n: Vec3, extent: Vec3, eye: Option<Vec3>) -> Plane {
        Plane {
            origin,
            n,
            extent,
            from_eye: eye.map(|e| (e, dot(sub(origin, e), n))),
        }
    }

    /// [`pixel`] of one channel: the same colour, bit for bit (the
    /// numerator is the one [`slice_point`] computes for a ray from the
    /// eye).
    #[inline(always)]
    pub(crate) fn pixel_one<T: Sample>(
        &self,
        wk: &mut Walker<'_, '_, T>,
        ray: &Ray,
        (req, st): (&mut Requests, &mut FrameStats),
    ) -> [f32; 4] {
        let num = match self.from_eye {
            Some((e, num)) if e == ray.origin => num,
            _ => dot(sub(self.origin, ray.origin), self.n),
        };
        let Some((wp, t)) = meet(ray, num, self.n, self.extent) else {
            return [0.0; 4];
        };
        let v = wk.slice_value(wp, t, req, st);
        if wk.f.params.labels {
            return label_color_of(v, wk.f.params.label_select.as_ref());
        }
        slice_color(&wk.f.tf_eval, v)
    }
}

/// The pixel of `ray` in a slice through the plane `(origin, n)` (`n` of
/// unit length): one walker per channel shown (`params.channels`, or one
/// channel through the frame's transfer-function evaluator).
#[inline]
pub(crate) fn pixel<T: Sample>(
    walkers: &mut [Walker<'_, '_, T>],
    ray: &Ray,
    (origin, n): (Vec3, Vec3),
    params: &RenderParams,
    extent: Vec3,
    (req, st): (&mut Requests, &mut FrameStats),
) -> [f32; 4] {
    let Some((wp, t)) = slice_point(ray, origin, n, extent) else {
        return [0.0; 4];
    };
    if params.channels.is_empty() {
        let wk = &mut walkers[0];
        let v = wk.slice_value(wp, t, req, st);
        if params.labels {
            return label_color_of(v, params.label_select.as_ref());
        }
        return slice_color(&wk.f.tf_eval, v);
    }
    let mut v = [f32::NAN; MAX_CHANNELS];
    for (x, wk) in v.iter_mut().zip(walkers.iter_mut()) {
        *x = wk.slice_value(wp, t, req, st).unwrap_or(f32::NAN);
    }
    mix_channels(&params.channels, v.into_iter())
}

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    /// The value at the world point `w` of a slice, `t` along the ray.
    pub(crate) fn slice_value(
        &mut self,
        w: Vec3,
        t: f64,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let f = self.f;
        let level = f.level_at(t);
        let (vb, frac) = f.sample_coords(level, w);
        self.enter(level, vb, req, true);
        self.value(level, w, vb, frac, req, st)
    }
}
