//! The in-core reference renderer: one whole level of one channel in RAM,
//! plain clamp-to-edge trilinear sampling, the same camera and transfer
//! function as every other renderer. It is written to be obviously correct,
//! not fast: it is the oracle that out-of-core images are tested against
//! (`../shared/DESIGN.md`, invariant 8).
//!
//! # The rules another renderer must follow to match it
//!
//! - **World box.** The volume fills `[0, X] × [0, Y] × [0, Z]` (world
//!   `[x, y, z]`, [`Volume::extent`]); a world point `w` is sampled at the
//!   normalized position `p = world_to_normalized(w, extent)` (`[z, y, x]`).
//! - **Sampling** ([`Volume::sample`]): voxel coordinate `p·span − 0.5`
//!   clamped to `[0, dims − 1]` per axis, then `brickyard_core::trilinear` (lerps along
//!   x, y, z), exactly as `brickyard_cache::vm::VirtualMemory::sample`
//!   (bit-identical for the same level).
//! - **Steps** (DVR, MIP): along each ray, `(t0, t1)` is the part inside the
//!   box ([`intersect_box`], `t ≥ 0`); samples are taken at
//!   `t_k = t0 + (k + 0.5)·Δ` for `k = 0, 1, …` while `t_k < t1`
//!   ([`step_t`]). `Δ = voxel / samples_per_voxel`, where `voxel` is the
//!   smallest spacing of the level ([`Volume::voxel_size`]).
//! - **DVR**: emission–absorption, front to back, premultiplied colour:
//!   for each sample, `[r, g, b, α] = tf.lookup(v)`, opacity corrected for
//!   the step as `α' = 1 − (1 − α)^(Δ/Δ_ref)` (`Δ_ref` = one voxel of
//!   the level unless
//!   [`RenderParams::reference_step`] says otherwise), then
//!   `C += (1 − A)·α'·rgb`, `A += (1 − A)·α'`; the ray stops once
//!   `A ≥ 0.99` ([`EARLY_TERMINATION`]). Here the arithmetic is `f64`
//!   (the renderers use `f32`; they agree within the tests' tolerance).
//! - **Shading** (DVR, when `tf.shading` is set; [`brickyard_core::Shading`]):
//!   at a sample of opacity > 0 at world point `w`, the gradient
//!   `g_a = (S(w + h_a·e_a) − S(w − h_a·e_a)) / (2·h_a)` per world axis `a`,
//!   `h_a` one voxel of the level along `a`, `S` the sampling rule above;
//!   `x = |g·d| / (|g|·|d|)` with `d` the ray direction; the colour becomes
//!   `rgb·(ambient + diffuse·x) + specular·x^shininess` (unchanged where
//!   `g = 0`), opacity as it was.
//! - **MIP**: the largest sampled value along the ray (NaN ignored) is
//!   mapped through the transfer function's *colour*; alpha is 1 for every
//!   ray that took at least one sample, 0 otherwise (the TF's opacity is not
//!   used).
//! - **Slice**: see [`RenderMode::Slice`]; of a label image
//!   ([`RenderParams::labels`]): the nearest voxel's label colour, and in
//!   DVR mode the label surfaces (`label_rgb`, `label_surface_ray`: the
//!   rules written out here, not the renderers' `optics` and `labels`).
//! - **Several views** ([`RenderParams::views`], `brickyard_core::views`):
//!   DVR and MIP rays from each view's camera; slices become super-slices
//!   (`render_super_slices` says how they are composited).
//! - **Several channels** (MIP, slice; [`RenderParams::channels`]): each
//!   channel's value (a MIP: its own largest along the ray) windowed to
//!   `[0, 1]` (NaN: 0), times its colour, added up, each component
//!   clamped to 1, opaque.
//! - **Several channels, DVR**: at each step every channel's value through
//!   its own transfer function ([`ChannelStyle::dvr_tf`]); the samples are
//!   coincident media: opacity `1 − Π(1 − α_i)`, colour `Σ α_i·c_i / Σ α_i`
//!   (nothing where every `α_i` is 0); that sample is corrected and
//!   composited as above.
//!
//! # Standing alone
//!
//! The oracle shares no code with the product renderers (`cpu`, `gpu`
//! and the modules they are made of): its step positions, opacity
//! correction, compositing, MIP colour, channel mix and plane intersection
//! are written here from the rules above, plainly and in `f64` (the
//! product works in `f32` where it can), so that a mistake in the
//! product's versions shows as a difference instead of being repeated in
//! both. What both take from `brickyard_core` is what defines the view
//! rather than how it is drawn, each tested there: the camera's rays, the
//! box intersection, the trilinear formula (bit for bit that of the
//! virtual memory) and the transfer function's `lookup`. A test in
//! `lib.rs` checks that this file names no product module.

use crate::image::Image;
use brickyard_core::camera::{intersect_box, world_extent, world_to_normalized, Ray, Vec3};
use brickyard_core::views::{ViewRays, Views};
#[cfg(feature = "loader")]
use brickyard_core::{dispatch_dtype, Sample};
use brickyard_core::{trilinear_of, Shading, TransferFunction};
#[cfg(feature = "loader")]
use brickyard_store::import::zarr;
#[cfg(feature = "loader")]
use brickyard_store::{StoreError, VolumeSource};
use rayon::prelude::*;
#[cfg(feature = "loader")]
use std::path::Path;

// What to render is the same for every renderer; named here too, as
// callers have always named it.
pub use crate::params::{ChannelStyle, LabelSelect, RenderMode, RenderParams, MAX_CHANNELS};

/// DVR stops a ray once its accumulated opacity reaches this.
pub const EARLY_TERMINATION: f32 = 0.99;

/// One channel of one level, whole, as `f32`.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume {
    /// Size in voxels, `[z, y, x]`.
    pub dims: [u64; 3],
    /// Voxel spacing (world units per voxel), `[z, y, x]`.
    pub spacing: [f64; 3],
    /// Voxels, `[z, y, x]`, x fastest; `len = dims` product.
    pub data: Vec<f32>,
    /// Voxels across the world box on each axis, `[z, y, x]`: `dims`, but
    /// for a coarser level of a store, whose last voxel may reach past the
    /// box ([`from_store`](Self::from_store)).
    pub span: [f64; 3],
    /// The world box `[X, Y, Z]`: `dims · spacing`, but for a coarser
    /// level of a store, level 0's.
    pub world: Vec3,
}

impl Volume {
    /// A volume from its voxels. Panics if `data` does not match `dims` or a
    /// dimension or spacing is not positive.
    pub fn new(dims: [u64; 3], spacing: [f64; 3], data: Vec<f32>) -> Volume {
        assert!(dims.iter().all(|&d| d > 0), "empty volume {dims:?}");
        assert!(
            spacing.iter().all(|&s| s > 0.0 && s.is_finite()),
            "spacing must be positive, got {spacing:?}"
        );
        assert_eq!(
            data.len() as u64,
            dims[0] * dims[1] * dims[2],
            "data length does not match dims {dims:?}"
        );
        Volume {
            dims,
            spacing,
            data,
            span: dims.map(|d| d as f64),
            world: world_extent(dims, spacing),
        }
    }

    /// A volume whose voxel `(z, y, x)` is `f(z, y, x)`.
    pub fn from_fn(dims: [u64; 3], spacing: [f64; 3], f: impl Fn(u64, u64, u64) -> f32) -> Volume {
        let mut data = Vec::with_capacity((dims[0] * dims[1] * dims[2]) as usize);
        for z in 0..dims[0] {
            for y in 0..dims[1] {
                for x in 0..dims[2] {
                    data.push(f(z, y, x));
                }
            }
        }
        Volume::new(dims, spacing, data)
    }

    /// Channel `channel` of a source, whole. Spacing from the source
    /// (1 on every axis when it has none). Values are converted as the
    /// virtual memory converts them (`to_f64() as f32`).
    #[cfg(feature = "loader")]
    pub fn from_source(src: &dyn VolumeSource, channel: usize) -> Result<Volume, StoreError> {
        let m = src.meta();
        if channel >= m.channels {
            return Err(StoreError::invalid(
                &m.path,
                "channel",
                format!(
                    "channel {channel} asked for but the volume has {}",
                    m.channels
                ),
            ));
        }
        let d = m.dims;
        let es = m.dtype.size();
        let slice = (d[1] * d[2]) as usize;
        let mut data = Vec::with_capacity(d[0] as usize * slice);
        // A few slices at a time, so that the raw bytes never double the
        // memory of the whole volume.
        let zs = ((16 << 20) / (slice * es)).max(1) as u64;
        let mut buf = Vec::new();
        for z0 in (0..d[0]).step_by(zs as usize) {
            let z1 = (z0 + zs).min(d[0]);
            buf.resize((z1 - z0) as usize * slice * es, 0u8);
            src.read_region(channel, z0..z1, 0..d[1], 0..d[2], &mut buf)?;
            dispatch_dtype!(m.dtype, T => {
                data.extend(buf.chunks_exact(es).map(|b| <T as Sample>::from_le(b).to_f64() as f32));
            });
        }
        let spacing = m.spacing.unwrap_or([1.0; 3]);
        if !spacing.iter().all(|&s| s > 0.0 && s.is_finite()) {
            return Err(StoreError::invalid(
                &m.path,
                "spacing",
                format!("spacing must be positive, got {spacing:?}"),
            ));
        }
        Ok(Volume::new(d, spacing, data))
    }

    /// Level `level`, channel `channel` of a store (OME-Zarr image or bare
    /// Zarr array), read whole through `brickyard_store::import::zarr`.
    ///
    /// A coarser level is placed as the store's own `scale` says: it
    /// spans `dims₀ / R` of its voxels across level 0's world box, `R =
    /// spacing_l / spacing₀` (voxel `i` centred at `R·(i + ½)` level-0
    /// voxels; the last voxel of an axis that is not a multiple of `R`
    /// reaches past the box), and its spacing is the box over that span.
    /// The renderers take the span from the levels' sizes
    /// ([`level_span`](brickyard_core::level_span)); this takes `R` from
    /// the metadata, independently (rounded where it is within 1e-9 of a
    /// whole number, as a store's ratios are).
    #[cfg(feature = "loader")]
    pub fn from_store(path: &Path, level: usize, channel: usize) -> Result<Volume, StoreError> {
        let src = zarr::open(path, level)?;
        let mut v = Volume::from_source(&src, channel)?;
        if level > 0 {
            let base = zarr::open(path, 0)?;
            let m0 = base.meta();
            let s0 = m0.spacing.unwrap_or([1.0; 3]);
            let ext = world_extent(m0.dims, s0);
            let ratio = [0, 1, 2].map(|a| {
                let r = v.spacing[a] / s0[a];
                if (r - r.round()).abs() < 1e-9 * r {
                    r.round()
                } else {
                    r
                }
            });
            v.span = [0, 1, 2].map(|a| m0.dims[a] as f64 / ratio[a]);
            // world_extent is [x, y, z]; spacing is [z, y, x].
            v.spacing = [0, 1, 2].map(|a| ext[2 - a] / v.span[a]);
            v.world = ext;
        }
        Ok(v)
    }

    /// World extent `[X, Y, Z]` (note: `[x, y, z]`, the camera's order).
    pub fn extent(&self) -> Vec3 {
        self.world
    }

    /// One voxel of this level for stepping and opacity correction: the
    /// smallest spacing.
    pub fn voxel_size(&self) -> f64 {
        self.spacing.iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// The voxel at integer `[z, y, x]`.
    #[inline]
    pub fn voxel(&self, z: u64, y: u64, x: u64) -> f32 {
        let d = self.dims;
        self.data[((z * d[1] + y) * d[2] + x) as usize]
    }

    /// Smallest and largest value (NaN ignored; `(NaN, NaN)` if all are).
    pub fn min_max(&self) -> (f32, f32) {
        self.data
            .iter()
            .filter(|v| !v.is_nan())
            .fold((f32::NAN, f32::NAN), |(a, b), &v| (a.min(v), b.max(v)))
    }

    /// Clamp-to-edge trilinear sample at the normalized position
    /// `p = [z, y, x]` (the rule of `VirtualMemory::sample`: voxel
    /// coordinate `p·span − 0.5` clamped to `[0, dims − 1]` (`span`: the
    /// voxels across the box, `dims` but for a store's coarser level), `f32`
    /// fractions, then [`brickyard_core::trilinear`]: lerps along x, y, z,
    /// a zero fraction taking the first value as it is).
    #[inline]
    pub fn sample(&self, p: [f64; 3]) -> f32 {
        let d = self.dims;
        let s = self.span;
        let q = [0, 1, 2].map(|a| (p[a] * s[a] - 0.5).clamp(0.0, (d[a] - 1) as f64));
        // q ≥ 0 after the clamp: truncation is floor (and avoids a libm call).
        let b = q.map(|x| (x as u64) as f64);
        let base = [0, 1, 2].map(|a| b[a] as u64);
        let frac = [0, 1, 2].map(|a| (q[a] - b[a]) as f32);
        trilinear_of(
            |dz, dy, dx| {
                self.voxel(
                    (base[0] + dz as u64).min(d[0] - 1),
                    (base[1] + dy as u64).min(d[1] - 1),
                    (base[2] + dx as u64).min(d[2] - 1),
                )
            },
            frac,
            true,
        )
    }

    /// Sample at the world point `world` (`[x, y, z]`).
    #[inline]
    pub fn sample_world(&self, world: Vec3, extent: Vec3) -> f32 {
        self.sample(world_to_normalized(world, extent))
    }

    /// The index `[z, y, x]` of [`nearest`](Self::nearest)'s voxel.
    pub fn nearest_index(&self, p: [f64; 3]) -> [u64; 3] {
        let (d, s) = (self.dims, self.span);
        [0, 1, 2].map(|a| {
            let q = (p[a] * s[a] - 0.5).clamp(0.0, (d[a] - 1) as f64);
            (q + 0.5).floor() as u64
        })
    }

    /// The voxel nearest to the normalized position `p = [z, y, x]`: the
    /// voxel coordinate `p·span − 0.5` clamped to `[0, dims − 1]` as for
    /// [`sample`](Self::sample), rounded by `⌊q + ½⌋` (how label images are
    /// sampled).
    pub fn nearest(&self, p: [f64; 3]) -> f32 {
        let q = self.nearest_index(p);
        self.voxel(q[0], q[1], q[2])
    }
}

// ---- the rules, from their definitions ---------------------------------

/// The parameter of step `k` on a ray entering the volume at `t0`:
/// `t0 + (k + ½)·Δ`.
pub fn step_t(t0: f64, k: u64, dt: f64) -> f64 {
    t0 + (k as f64 + 0.5) * dt
}

/// A ray's colour so far: premultiplied, front to back, in `f64`.
#[derive(Default)]
struct Ray64 {
    rgb: [f64; 3],
    alpha: f64,
}

impl Ray64 {
    /// Composite a sample of straight-alpha colour `c` behind what the ray
    /// holds, its opacity corrected for a step of `exponent` reference
    /// steps (`α' = 1 − (1 − α)^exponent`): `C += (1 − A)·α'·rgb`,
    /// `A += (1 − A)·α'`. True once `A ≥ EARLY_TERMINATION`.
    fn add(&mut self, c: [f32; 4], exponent: f64) -> bool {
        let a = 1.0 - (1.0 - c[3] as f64).powf(exponent);
        let weight = (1.0 - self.alpha) * a;
        for (acc, x) in self.rgb.iter_mut().zip(c) {
            *acc += weight * x as f64;
        }
        self.alpha += weight;
        self.alpha >= EARLY_TERMINATION as f64
    }

    fn pixel(&self) -> [f32; 4] {
        let [r, g, b] = self.rgb;
        [r as f32, g as f32, b as f32, self.alpha as f32]
    }
}

/// A MIP pixel: the colour the transfer function gives the largest value,
/// opaque, where the ray took at least one sample (`hit`); black when
/// every sample was NaN; transparent where it took none.
fn mip_pixel(tf: &TransferFunction, hit: bool, largest: f32) -> [f32; 4] {
    match (hit, largest.is_nan()) {
        (false, _) => [0.0; 4],
        (true, true) => [0.0, 0.0, 0.0, 1.0],
        (true, false) => {
            let [r, g, b, _] = tf.lookup(largest);
            [r, g, b, 1.0]
        }
    }
}

/// Several channels added up: each value windowed to `[0, 1]` by its
/// style (NaN: 0) times the style's colour, summed, each component
/// clamped to 1, opaque.
fn channel_mix(styles: &[ChannelStyle], values: &[f32]) -> [f32; 4] {
    let mut rgb = [0.0f64; 3];
    for (s, &v) in styles.iter().zip(values) {
        let (lo, hi) = (s.window[0] as f64, s.window[1] as f64);
        let x = (v as f64 - lo) / (hi - lo);
        let intensity = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
        for (acc, c) in rgb.iter_mut().zip(s.color) {
            *acc += c as f64 * intensity;
        }
    }
    let [r, g, b] = rgb.map(|x| x.min(1.0) as f32);
    [r, g, b, 1.0]
}

/// Where `ray` meets the plane through `origin` perpendicular to `normal`:
/// the world point `o + t·d` with `(o + t·d − origin)·n = 0`, if `t ≥ 0`
/// and the point lies in the closed box `[0, extent]`; with its `t`.
fn plane_hit(ray: &Ray, origin: Vec3, normal: Vec3, extent: Vec3) -> Option<(Vec3, f64)> {
    let len = (normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]).sqrt();
    let n = normal.map(|x| x / len);
    let (o, d) = (ray.origin, ray.dir);
    let along = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
    if along == 0.0 {
        return None;
    }
    let t =
        ((origin[0] - o[0]) * n[0] + (origin[1] - o[1]) * n[1] + (origin[2] - o[2]) * n[2]) / along;
    if t.is_nan() || t < 0.0 {
        return None;
    }
    let w = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    (0..3)
        .all(|a| w[a] >= 0.0 && w[a] <= extent[a])
        .then_some((w, t))
}

// ---- the renderers -----------------------------------------------------

/// An image of `params`' size whose pixel `(i, j)` is `pixel(ray)` for the
/// camera's ray through it (rows in parallel). Panics if `params.validate()`
/// fails.
fn per_pixel(params: &RenderParams, pixel: impl Fn(&Ray) -> [f32; 4] + Sync) -> Image {
    if let Err(e) = params.validate() {
        panic!("invalid render parameters: {e}");
    }
    let (w, h) = (params.width, params.height);
    let rays = ViewRays::new(&params.camera, params.views.as_ref(), w, h);
    per_index(params, |i, j| pixel(&rays.pixel_ray(i, j)))
}

/// An image of `params`' size whose pixel `(i, j)` is `pixel(i, j)`.
fn per_index(params: &RenderParams, pixel: impl Fn(u32, u32) -> [f32; 4] + Sync) -> Image {
    let (w, h) = (params.width, params.height);
    let mut img = Image::new(w, h);
    img.rgba
        .par_chunks_mut(w as usize)
        .enumerate()
        .for_each(|(j, row)| {
            for (i, px) in row.iter_mut().enumerate() {
                *px = pixel(i as u32, j as u32);
            }
        });
    img
}

/// The super-slices of `params.views` through the plane `(origin,
/// normal)`, as the thesis composites them: for pixel `x` of view `v`,
/// slice `k` (at `(k − c)·spacing` towards the camera, `c = count/2`) is
/// sampled where the view's ray through `x + shift(v, k)` meets it and
/// classified by the transfer function (straight alpha, no step
/// correction; outside the box or NaN: nothing); slices `0 … c` are laid
/// back to front (`C = α·rgb + (1 − α)·C` each), then slices `c+1 …
/// count−1` are added front to back (`C += (1 − A)·α·rgb`).
fn render_super_slices(
    volume: &Volume,
    params: &RenderParams,
    views: &Views,
    (origin, normal): (Vec3, Vec3),
) -> Image {
    if let Err(e) = params.validate() {
        panic!("invalid render parameters: {e}");
    }
    let extent = volume.extent();
    let rays = ViewRays::new(&params.camera, Some(views), params.width, params.height);
    let forward = params.camera.basis().forward;
    let len = (normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]).sqrt();
    let mut n = [normal[0] / len, normal[1] / len, normal[2] / len];
    if n[0] * forward[0] + n[1] * forward[1] + n[2] * forward[2] > 0.0 {
        n = [-n[0], -n[1], -n[2]];
    }
    let c = views.count / 2;
    per_index(params, |i, j| {
        let (v, x) = rays.view_of(i);
        let layer = |k: u32| -> Option<[f64; 4]> {
            let ray = rays.ray(v, x as f64 + 0.5 + views.slice_shift(v, k), j as f64 + 0.5);
            let d = views.slice_depth(k);
            let o = [
                origin[0] + d * n[0],
                origin[1] + d * n[1],
                origin[2] + d * n[2],
            ];
            let (w, _) = plane_hit(&ray, o, normal, extent)?;
            let value = volume.sample_world(w, extent);
            if value.is_nan() {
                return None;
            }
            Some(params.tf.lookup(value).map(f64::from))
        };
        let mut acc = [0.0f64; 4];
        for k in 0..=c {
            if let Some([r, g, b, a]) = layer(k) {
                acc = [
                    a * r + (1.0 - a) * acc[0],
                    a * g + (1.0 - a) * acc[1],
                    a * b + (1.0 - a) * acc[2],
                    a + (1.0 - a) * acc[3],
                ];
            }
        }
        for k in c + 1..views.count {
            if let Some([r, g, b, a]) = layer(k) {
                let wgt = (1.0 - acc[3]) * a;
                acc = [
                    acc[0] + wgt * r,
                    acc[1] + wgt * g,
                    acc[2] + wgt * b,
                    acc[3] + wgt,
                ];
            }
        }
        acc.map(|x| x as f32)
    })
}

/// Render `volume` with `params` (rows in parallel). Panics if
/// `params.validate()` fails.
pub fn render(volume: &Volume, params: &RenderParams) -> Image {
    let extent = volume.extent();
    let voxel = volume.voxel_size();
    let dt = voxel / params.samples_per_voxel;
    let exponent = dt / params.reference_step.unwrap_or(voxel);
    if let (RenderMode::Slice { origin, normal }, Some(views)) = (&params.mode, &params.views) {
        return render_super_slices(volume, params, views, (*origin, *normal));
    }
    let sel = params.label_select.as_ref();
    per_pixel(params, |ray| match &params.mode {
        RenderMode::Dvr if params.labels => label_surface_ray(volume, ray, extent, dt, sel),
        RenderMode::Dvr => dvr_ray(volume, &params.tf, ray, extent, dt, exponent),
        RenderMode::Mip => mip_ray(volume, &params.tf, ray, extent, dt),
        RenderMode::Slice { origin, normal } if params.labels => {
            match plane_hit(ray, *origin, *normal, extent) {
                Some((w, _)) => {
                    match label_rgb(volume.nearest(world_to_normalized(w, extent)), sel) {
                        Some(c) => [c[0] as f32, c[1] as f32, c[2] as f32, 1.0],
                        None => [0.0; 4],
                    }
                }
                None => [0.0; 4],
            }
        }
        RenderMode::Slice { origin, normal } => {
            slice_ray(volume, &params.tf, ray, extent, *origin, *normal)
        }
    })
}

/// Render several channels (`params.channels`): added up (slice, MIP) or
/// composited per sample, each through its own transfer function (DVR):
/// `volumes[i]` is the level to show of channel `params.channels[i]` (all
/// of one size, but for DVR, where each may be another level of one
/// extent). Panics if the parameters are invalid, no channel is given
/// or the volumes do not match them.
pub fn render_channels(volumes: &[Volume], params: &RenderParams) -> Image {
    assert!(!params.channels.is_empty(), "no channels to render");
    assert_eq!(
        volumes.len(),
        params.channels.len(),
        "one volume per channel"
    );
    // DVR may read channels at other levels (their level ranges): each
    // volume is sampled at the same normalized positions; the first one
    // gives the extent and the step. Slices and MIPs take one grid.
    assert!(
        matches!(params.mode, RenderMode::Dvr) || volumes.iter().all(|v| v.dims == volumes[0].dims)
    );
    let v0 = &volumes[0];
    let extent = v0.extent();
    let dt = v0.voxel_size() / params.samples_per_voxel;
    let styles = &params.channels;
    let tfs: Vec<TransferFunction> = styles.iter().map(|s| s.dvr_tf()).collect();
    per_pixel(params, |ray| match &params.mode {
        RenderMode::Slice { origin, normal } => match plane_hit(ray, *origin, *normal, extent) {
            Some((p, _)) => {
                let values: Vec<f32> = volumes.iter().map(|v| v.sample_world(p, extent)).collect();
                channel_mix(styles, &values)
            }
            None => [0.0; 4],
        },
        RenderMode::Mip => match intersect_box(ray, [0.0; 3], extent) {
            Some((t0, t1)) if step_t(t0, 0, dt) < t1 => {
                let largest: Vec<f32> = volumes
                    .iter()
                    .map(|v| max_along(v, ray, (t0, t1), extent, dt))
                    .collect();
                channel_mix(styles, &largest)
            }
            _ => [0.0; 4],
        },
        RenderMode::Dvr => {
            let exponent = dt / params.reference_step.unwrap_or(v0.voxel_size());
            dvr_channels_ray(volumes, &tfs, ray, extent, dt, exponent)
        }
    })
}

/// DVR of several channels along one ray: at each step every channel's
/// value through its own transfer function, mixed as coincident media
/// (opacity `1 − Π(1 − α_i)`, colour `Σ α_i·c_i / Σ α_i`), the mixed
/// sample's opacity corrected for the step and composited front to back,
/// all in f64.
fn dvr_channels_ray(
    volumes: &[Volume],
    tfs: &[TransferFunction],
    ray: &Ray,
    extent: Vec3,
    dt: f64,
    exponent: f64,
) -> [f32; 4] {
    let (mut rgb, mut alpha) = ([0.0f64; 3], 0.0f64);
    if let Some((t0, t1)) = intersect_box(ray, [0.0; 3], extent) {
        let mut k = 0u64;
        loop {
            let t = step_t(t0, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            let w = ray.at(t);
            let (mut keep, mut sum, mut weight) = (1.0f64, [0.0f64; 3], 0.0f64);
            for (vol, tf) in volumes.iter().zip(tfs) {
                let [r, g, b, a] = tf.lookup(vol.sample_world(w, extent)).map(f64::from);
                keep *= 1.0 - a;
                sum[0] += a * r;
                sum[1] += a * g;
                sum[2] += a * b;
                weight += a;
            }
            if weight <= 0.0 {
                continue;
            }
            let a = 1.0 - keep.powf(exponent);
            let wgt = (1.0 - alpha) * a;
            for (acc, s) in rgb.iter_mut().zip(sum) {
                *acc += wgt * s / weight;
            }
            alpha += wgt;
            if alpha >= EARLY_TERMINATION as f64 {
                break;
            }
        }
    }
    [rgb[0] as f32, rgb[1] as f32, rgb[2] as f32, alpha as f32]
}

/// DVR with automatic level of detail, written plainly on whole levels in
/// memory (`levels[l]`: level `l`, all of one extent): each step `t = base
/// + (k + ½)·Δ_l` samples level `l`, the level whose voxel matches the pixel
/// footprint at `t` (`⌊max(log2(footprint / voxel₀), 0) + bias⌋`, clamped); where
/// that level changes, the new level's step grid takes that sample as its
/// step 0 (the next step lies `Δ_new` on: samples stay evenly spaced within
/// a level). The oracle of the
/// renderers' `Lod::Auto`. Panics if the parameters are invalid.
pub fn render_auto_lod(levels: &[Volume], params: &RenderParams, bias: f64) -> Image {
    let extent = levels[0].extent();
    let voxel = |l: usize| levels[l].voxel_size();
    let reference = params.reference_step.unwrap_or(voxel(0));
    let level_at = |t: f64| {
        let l = (params.camera.pixel_footprint(t, params.lod_height()) / voxel(0))
            .log2()
            .max(0.0)
            + bias;
        if l.is_finite() && l > 0.0 {
            (l.floor() as usize).min(levels.len() - 1)
        } else {
            0
        }
    };
    per_pixel(params, |ray| {
        let mut acc = Ray64::default();
        let Some((t0, t1)) = intersect_box(ray, [0.0; 3], extent) else {
            return acc.pixel();
        };
        let mut level = level_at(t0);
        let (mut base, mut k) = (t0, 0u64);
        loop {
            let t = step_t(base, k, voxel(level) / params.samples_per_voxel);
            if t >= t1 {
                break;
            }
            k += 1;
            let l = level_at(t);
            let dt = voxel(l) / params.samples_per_voxel;
            if l != level {
                (level, base, k) = (l, t - 0.5 * dt, 1);
            }
            let (vol, w) = (&levels[level], ray.at(t));
            let c = shaded(
                vol,
                &params.tf,
                params.tf.lookup(vol.sample_world(w, extent)),
                (w, ray.dir, extent),
            );
            if acc.add(c, dt / reference) {
                break;
            }
        }
        acc.pixel()
    })
}

fn dvr_ray(
    vol: &Volume,
    tf: &TransferFunction,
    ray: &Ray,
    extent: Vec3,
    dt: f64,
    exponent: f64,
) -> [f32; 4] {
    let mut acc = Ray64::default();
    let Some((t0, t1)) = intersect_box(ray, [0.0; 3], extent) else {
        return acc.pixel();
    };
    let mut k = 0u64;
    loop {
        let t = step_t(t0, k, dt);
        if t >= t1 {
            break;
        }
        k += 1;
        let w = ray.at(t);
        let c = shaded(
            vol,
            tf,
            tf.lookup(vol.sample_world(w, extent)),
            (w, ray.dir, extent),
        );
        if acc.add(c, exponent) {
            break;
        }
    }
    acc.pixel()
}

/// Colour `c` of a DVR sample at world point `w` on a ray of direction
/// `dir`, shaded by the rule above when the transfer function asks for it.
fn shaded(
    vol: &Volume,
    tf: &TransferFunction,
    c: [f32; 4],
    (w, dir, extent): (Vec3, Vec3, Vec3),
) -> [f32; 4] {
    match &tf.shading {
        Some(sh) if c[3] > 0.0 => shade_sample(vol, sh, c, (w, dir, extent)),
        _ => c,
    }
}

fn shade_sample(
    vol: &Volume,
    sh: &Shading,
    c: [f32; 4],
    (w, dir, extent): (Vec3, Vec3, Vec3),
) -> [f32; 4] {
    let mut g = [0.0f64; 3];
    for (a, ga) in g.iter_mut().enumerate() {
        // World axis a is volume axis 2 − a.
        let h = extent[a] / vol.span[2 - a];
        let (mut ahead, mut behind) = (w, w);
        ahead[a] += h;
        behind[a] -= h;
        let diff = vol.sample_world(ahead, extent) as f64 - vol.sample_world(behind, extent) as f64;
        *ga = diff / (2.0 * h);
    }
    let len_g = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    if len_g == 0.0 {
        return c;
    }
    let len_d = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    let cos = ((g[0] * dir[0] + g[1] * dir[1] + g[2] * dir[2]) / (len_g * len_d)).abs();
    let lit = |x: f32| {
        x as f64 * (sh.ambient as f64 + sh.diffuse as f64 * cos)
            + sh.specular as f64 * cos.powf(sh.shininess as f64)
    };
    [lit(c[0]) as f32, lit(c[1]) as f32, lit(c[2]) as f32, c[3]]
}

fn mip_ray(vol: &Volume, tf: &TransferFunction, ray: &Ray, extent: Vec3, dt: f64) -> [f32; 4] {
    match intersect_box(ray, [0.0; 3], extent) {
        Some((t0, t1)) => {
            let hit = step_t(t0, 0, dt) < t1;
            mip_pixel(tf, hit, max_along(vol, ray, (t0, t1), extent, dt))
        }
        None => [0.0; 4],
    }
}

/// The largest sample along `ray` inside `(t0, t1)` (NaN ignored; NaN when
/// there is none).
fn max_along(vol: &Volume, ray: &Ray, (t0, t1): (f64, f64), extent: Vec3, dt: f64) -> f32 {
    let mut best = f32::NAN;
    let mut k = 0u64;
    loop {
        let t = step_t(t0, k, dt);
        if t >= t1 {
            break;
        }
        k += 1;
        // f32::max ignores NaN.
        best = best.max(vol.sample_world(ray.at(t), extent));
    }
    best
}

// ---- label images (`RenderParams::labels`), from their definitions -----

/// The label a value stands for, `⌊v + ½⌋`; `None` for NaN.
fn label(v: f32) -> Option<i64> {
    (!v.is_nan()).then(|| (v as f64 + 0.5).floor() as i64)
}

/// A label's colour in linear RGB, `None` for label 0 (the background) and
/// NaN: the 32 bits of MurmurHash3's finalizer of the label give the hue
/// (low 16 bits, of the whole circle), the saturation (`0.6 + 0.4·b/255`,
/// bits 16–23) and the value (`0.75 + 0.25·b/255`, bits 24–31), turned
/// into RGB by the six sectors of the hue.
fn label_rgb(v: f32, sel: Option<&LabelSelect>) -> Option<[f64; 3]> {
    let id = label(v).filter(|&id| id != 0)?;
    // A selection: only the labels it names, or all but those (a plain
    // search of its list).
    if sel.is_some_and(|s| s.ids.iter().any(|&x| x as i64 == id) == s.hide) {
        return None;
    }
    let mut h = id as i32 as u32;
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^= h >> 16;
    let hue = (h & 0xffff) as f64 / 65536.0 * 6.0;
    let sat = 0.6 + 0.4 * ((h >> 16) & 0xff) as f64 / 255.0;
    let val = 0.75 + 0.25 * (h >> 24) as f64 / 255.0;
    let sector = hue.floor();
    let f = hue - sector;
    let (p, q, t) = (
        val * (1.0 - sat),
        val * (1.0 - sat * f),
        val * (1.0 - sat * (1.0 - f)),
    );
    Some(match sector as u32 {
        0 => [val, t, p],
        1 => [q, val, p],
        2 => [p, val, t],
        3 => [p, q, val],
        4 => [t, p, val],
        _ => [val, p, q],
    })
}

/// A label image in 3D (DVR mode): the first step `t0 + (k + ½)·Δ` whose
/// nearest voxel holds a label (not 0), in that label's colour times
/// `0.25 + 0.75·|cos|` of the angle between the ray and the label's
/// surface normal there: the gradient of the label's indicator (1 where a
/// voxel holds it, 0 elsewhere and outside the volume) by Sobel's 3×3×3
/// operator (central differences across each axis, weighted `1 2 1` along
/// the other two), per world unit; 1 where that gradient is 0.
fn label_surface_ray(
    vol: &Volume,
    ray: &Ray,
    extent: Vec3,
    dt: f64,
    sel: Option<&LabelSelect>,
) -> [f32; 4] {
    let Some((t0, t1)) = intersect_box(ray, [0.0; 3], extent) else {
        return [0.0; 4];
    };
    let d = vol.dims;
    for k in 0.. {
        let t = step_t(t0, k, dt);
        if t >= t1 {
            break;
        }
        let q = vol.nearest_index(world_to_normalized(ray.at(t), extent));
        let v = vol.voxel(q[0], q[1], q[2]);
        let Some(rgb) = label_rgb(v, sel) else {
            continue;
        };
        let id = label(v);
        // The indicator at offset `o` ([z, y, x], each −1, 0 or 1).
        let holds = |o: [i64; 3]| {
            let n = [0, 1, 2].map(|a| q[a] as i64 + o[a]);
            let inside = (0..3).all(|a| n[a] >= 0 && n[a] < d[a] as i64);
            let held = inside && label(vol.voxel(n[0] as u64, n[1] as u64, n[2] as u64)) == id;
            held as u8 as f64
        };
        let weight = |o: i64| if o == 0 { 2.0 } else { 1.0 };
        let mut g = [0.0f64; 3];
        for a in 0..3 {
            let (b, c) = ((a + 1) % 3, (a + 2) % 3);
            for ob in -1..=1 {
                for oc in -1..=1 {
                    let mut lo = [0i64; 3];
                    lo[a] = -1;
                    lo[b] = ob;
                    lo[c] = oc;
                    let mut hi = lo;
                    hi[a] = 1;
                    g[a] += weight(ob) * weight(oc) * (holds(lo) - holds(hi));
                }
            }
        }
        // Per world unit, in [x, y, z].
        let n = [
            g[2] / vol.spacing[2],
            g[1] / vol.spacing[1],
            g[0] / vol.spacing[0],
        ];
        let dir = ray.dir;
        let nn = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let dd = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        let shade = if nn == 0.0 {
            1.0
        } else {
            0.25 + 0.75
                * ((n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2]) / (nn * dd))
                    .abs()
                    .min(1.0)
        };
        return [
            (rgb[0] * shade) as f32,
            (rgb[1] * shade) as f32,
            (rgb[2] * shade) as f32,
            1.0,
        ];
    }
    [0.0; 4]
}

fn slice_ray(
    vol: &Volume,
    tf: &TransferFunction,
    ray: &Ray,
    extent: Vec3,
    origin: Vec3,
    normal: Vec3,
) -> [f32; 4] {
    let Some((w, _)) = plane_hit(ray, origin, normal, extent) else {
        return [0.0; 4];
    };
    let v = vol.sample_world(w, extent);
    if v.is_nan() {
        return [0.0; 4];
    }
    let c = tf.lookup(v);
    [c[0], c[1], c[2], 1.0]
}
