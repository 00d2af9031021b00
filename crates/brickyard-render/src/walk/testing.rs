//! Fixtures for the walk's unit tests: a one-level virtual memory and a
//! DVR view of it, a seeded generator, and random steps on random rays.

use super::cells::FIX;
use super::{Frame, Grid, Track};
use crate::cpu::Scene;
use crate::params::{RenderMode, RenderParams};
use brickyard_cache::vm::{VirtualMemory, VmConfig};
use brickyard_core::camera::{intersect_box, Camera, Projection, Ray, Vec3};
use brickyard_core::{DType, Dims3, TransferFunction};

/// A ray, its span, step grid and track, and a step on it.
pub(crate) type RandomStep = (Ray, (f64, f64), Grid, Track, u64);

/// One level of `dims` voxels in bricks of `brick`, world size
/// `extent`, a DVR view of it (for frames at level 0).
pub(crate) fn fixture(
    dims: Dims3,
    brick: Dims3,
    extent: Vec3,
) -> (VirtualMemory, Scene, RenderParams) {
    fixture_of(vec![dims], brick, extent)
}

/// [`fixture`] of several levels (voxels per level).
pub(crate) fn fixture_of(
    levels: Vec<Dims3>,
    brick: Dims3,
    extent: Vec3,
) -> (VirtualMemory, Scene, RenderParams) {
    let cfg = VmConfig {
        brick,
        pool_bytes: 1 << 22,
        ..Default::default()
    };
    let vm = VirtualMemory::new(&levels, 1, DType::U8, cfg);
    let scene = Scene::new(extent, levels);
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    (vm, scene, RenderParams::new(4, 4, cam, tf, RenderMode::Dvr))
}

/// Uniform numbers in `[0, 1)` from a linear congruential generator.
pub(crate) fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
    move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// The ray towards `target` along `dir` (normalized here) from `far`
/// away, its span through the volume, its step grid of `dt` and track
/// at level 0, and the step at fraction `u` of its steps (at least
/// step 1); `None` when it misses the volume or takes under 2 steps.
pub(crate) fn random_step(
    f: &Frame,
    extent: Vec3,
    (target, dir, far): (Vec3, Vec3, f64),
    dt: f64,
    u: f64,
) -> Option<RandomStep> {
    let n = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
    let dir = dir.map(|d| d / n);
    let origin = [0, 1, 2].map(|a| target[a] - far * dir[a]);
    let ray = Ray { origin, dir };
    let (t0, t1) = intersect_box(&ray, [0.0; 3], extent)?;
    let g = Grid {
        base_t: t0,
        dt,
        inv_dt: 1.0 / dt,
    };
    // The track of this step size (not the level's).
    let track = f.track(0, &ray, ray.dir.map(|d| 1.0 / d), t1);
    let track = Track {
        dq: track.beta.map(|b| (b * dt * FIX) as i64),
        ..track
    };
    let steps = ((t1 - t0) / dt) as u64;
    if steps < 2 {
        return None;
    }
    let k0 = 1 + (u * (steps - 1) as f64) as u64;
    Some((ray, (t0, t1), g, track, k0))
}
