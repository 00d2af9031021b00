//! Ray-guided rendering on the CPU through the virtual memory: DVR, MIP and
//! slices. Every sample is a lookup `(level, channel, p)`; a miss records a
//! request and is answered by the finest resident coarser level, so a frame
//! never waits for I/O. Each frame reports its completeness: the fraction of
//! samples served at the level they asked for.
//!
//! Sampling follows the reference renderer's rules (step positions
//! `t0 + (k + ½)·Δ`, opacity correction, early termination at 0.99), so a
//! complete frame at a fixed level equals the in-core reference image.

use crate::image::Image;
use crate::reference::{composite, mip_color, slice_point, step_t, RenderMode, RenderParams};
use brickyard_cache::vm::{Requests, VirtualMemory};
use brickyard_core::camera::{intersect_box, world_to_normalized, Ray, Vec3};
use brickyard_core::Dims3;
use rayon::prelude::*;

/// What the renderer needs to know about the volume besides the pages.
#[derive(Debug, Clone)]
pub struct Scene {
    /// World size `[x, y, z]` of the volume.
    pub extent: Vec3,
    /// Voxels per level, `[z, y, x]`.
    pub levels: Vec<Dims3>,
    pub channel: usize,
}

impl Scene {
    /// A scene of channel 0 of a volume with world size `extent` (`[x, y, z]`)
    /// and `levels` (voxels per level, `[z, y, x]`).
    pub fn new(extent: Vec3, levels: Vec<Dims3>) -> Scene {
        Scene {
            extent,
            levels,
            channel: 0,
        }
    }

    /// Smallest voxel edge of level `l` in world units.
    pub fn voxel(&self, l: usize) -> f64 {
        let d = self.levels[l];
        let ext_zyx = [self.extent[2], self.extent[1], self.extent[0]];
        (0..3)
            .map(|a| ext_zyx[a] / d[a] as f64)
            .fold(f64::INFINITY, f64::min)
    }
}

/// Level of detail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Lod {
    /// Always this level.
    Fixed(usize),
    /// Per sample, the level whose voxel matches the pixel footprint at the
    /// sample's distance, shifted by `bias` levels (negative: finer).
    Auto { bias: f64 },
}

/// Figures of one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameStats {
    pub samples: u64,
    /// Samples served at the level they asked for.
    pub exact: u64,
    /// Samples with nothing resident at all.
    pub unserved: u64,
}

impl FrameStats {
    /// Fraction of samples served at the level they asked for.
    pub fn completeness(&self) -> f64 {
        if self.samples == 0 {
            1.0
        } else {
            self.exact as f64 / self.samples as f64
        }
    }
}

/// Render one frame. Returns the image, its statistics and the request
/// collectors (hand them to `Session::finish_frame`).
pub fn render_frame(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
) -> (Image, FrameStats, Vec<Requests>) {
    let (w, h) = (params.width, params.height);
    let rg = params.camera.ray_gen(w, h);
    let mut img = Image::new(w, h);
    let rows_per_task = 8usize;
    let parts: Vec<(FrameStats, Requests)> = img
        .rgba
        .par_chunks_mut(w as usize * rows_per_task)
        .enumerate()
        .map(|(chunk, rows)| {
            let mut req = vm.requests();
            let mut st = FrameStats::default();
            let ctx = Ctx {
                vm,
                scene,
                params,
                lod,
            };
            for (r, row) in rows.chunks_mut(w as usize).enumerate() {
                let j = (chunk * rows_per_task + r) as u32;
                for (i, px) in row.iter_mut().enumerate() {
                    let ray = rg.pixel_ray(i as u32, j);
                    *px = match &params.mode {
                        RenderMode::Dvr => ctx.dvr(&ray, &mut req, &mut st),
                        RenderMode::Mip => ctx.mip(&ray, &mut req, &mut st),
                        RenderMode::Slice { origin, normal } => {
                            ctx.slice(&ray, *origin, *normal, &mut req, &mut st)
                        }
                    };
                }
            }
            (st, req)
        })
        .collect();
    let mut stats = FrameStats::default();
    let mut reqs = Vec::with_capacity(parts.len());
    for (s, r) in parts {
        stats.samples += s.samples;
        stats.exact += s.exact;
        stats.unserved += s.unserved;
        reqs.push(r);
    }
    (img, stats, reqs)
}

struct Ctx<'a> {
    vm: &'a VirtualMemory,
    scene: &'a Scene,
    params: &'a RenderParams,
    lod: Lod,
}

impl Ctx<'_> {
    fn level_at(&self, t: f64) -> usize {
        let n = self.scene.levels.len();
        match self.lod {
            Lod::Fixed(l) => l.min(n - 1),
            Lod::Auto { bias } => {
                let fp = self.params.camera.pixel_footprint(t, self.params.height);
                let l = (fp / self.scene.voxel(0)).log2() + bias;
                if l.is_finite() && l > 0.0 {
                    (l.floor() as usize).min(n - 1)
                } else {
                    0
                }
            }
        }
    }

    #[inline]
    fn sample(&self, l: usize, w: Vec3, req: &mut Requests, st: &mut FrameStats) -> Option<f32> {
        let p = world_to_normalized(w, self.scene.extent);
        let r = self.vm.sample(l, self.scene.channel, p, true, req);
        st.samples += 1;
        match r.level {
            Some(lv) => {
                st.exact += (lv as usize == l) as u64;
                Some(r.value)
            }
            None => {
                st.unserved += 1;
                None
            }
        }
    }

    fn dvr(&self, ray: &Ray, req: &mut Requests, st: &mut FrameStats) -> [f32; 4] {
        let mut acc = [0.0f32; 4];
        let Some((t0, t1)) = intersect_box(ray, [0.0; 3], self.scene.extent) else {
            return acc;
        };
        let spv = self.params.samples_per_voxel;
        let reference = self.params.reference_step.unwrap_or(self.scene.voxel(0));
        // Steps keep the reference renderer's positions while the level
        // stays the same; a level change restarts the grid at the current t.
        let mut level = self.level_at(t0);
        let mut dt = self.scene.voxel(level) / spv;
        let mut exponent = (dt / reference) as f32;
        let mut base = t0;
        let mut k = 0u64;
        loop {
            let t = step_t(base, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            let l = self.level_at(t);
            if l != level {
                level = l;
                base = t;
                k = 0;
                dt = self.scene.voxel(level) / spv;
                exponent = (dt / reference) as f32;
            }
            let Some(v) = self.sample(level, ray.at(t), req, st) else {
                continue;
            };
            if composite(&mut acc, self.params.tf.lookup(v), exponent) {
                break;
            }
        }
        acc
    }

    fn mip(&self, ray: &Ray, req: &mut Requests, st: &mut FrameStats) -> [f32; 4] {
        let Some((t0, t1)) = intersect_box(ray, [0.0; 3], self.scene.extent) else {
            return [0.0; 4];
        };
        let level = self.level_at(t0);
        let dt = self.scene.voxel(level) / self.params.samples_per_voxel;
        let mut best = f32::NAN;
        let mut hit = false;
        let mut k = 0u64;
        loop {
            let t = step_t(t0, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            hit = true;
            if let Some(v) = self.sample(level, ray.at(t), req, st) {
                best = best.max(v);
            }
        }
        mip_color(&self.params.tf, hit, best)
    }

    fn slice(
        &self,
        ray: &Ray,
        origin: Vec3,
        normal: Vec3,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        let Some((w, t)) = slice_point(ray, origin, normal, self.scene.extent) else {
            return [0.0; 4];
        };
        let level = self.level_at(t);
        match self.sample(level, w, req, st) {
            Some(v) if !v.is_nan() => {
                let c = self.params.tf.lookup(v);
                [c[0], c[1], c[2], 1.0]
            }
            _ => [0.0; 4],
        }
    }
}
