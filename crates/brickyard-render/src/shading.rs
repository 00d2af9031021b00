//! Gradient shading of DVR samples on the CPU (the rule is
//! [`brickyard_core::Shading`]'s): the gradient by central differences one
//! voxel of the sample's level apart along each world axis, each
//! neighbour looked up like a sample (through the walker, so a neighbour
//! in the next brick is read from that brick, or from its stand-in while
//! it is not resident, and a frame is complete only when they are all
//! served at their level); Blinn–Phong with the light at the eye.

use crate::cpu::FrameStats;
use crate::walk::Walker;
use brickyard_cache::vm::Requests;
use brickyard_core::camera::Vec3;
use brickyard_core::{Sample, Shading};

impl<T: Sample> Walker<'_, '_, T> {
    /// The value at world point `w` at level `l` (a lookup like a
    /// sample's: counted, requested on a miss).
    fn neighbour(
        &mut self,
        l: usize,
        w: Vec3,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let (vb, frac) = self.f.coords(l, w);
        self.enter(l, vb, req, true);
        self.value(l, w, vb, frac, req, st)
    }

    /// The gradient (world units) of the sampled field of level `l` at
    /// world point `w`; `None` while a neighbour is not served at all.
    pub(crate) fn gradient(
        &mut self,
        l: usize,
        w: Vec3,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<[f64; 3]> {
        let mut g = [0.0f64; 3];
        for (a, ga) in g.iter_mut().enumerate() {
            // A voxel of level `l` along world axis `a` (volume axis 2 − a).
            let h = self.f.inv_scale[l][2 - a];
            let mut p = w;
            p[a] = w[a] + h;
            let hi = self.neighbour(l, p, req, st)?;
            p[a] = w[a] - h;
            let lo = self.neighbour(l, p, req, st)?;
            *ga = (hi as f64 - lo as f64) / (2.0 * h);
        }
        Some(g)
    }

    /// Colour `c` of the DVR sample at world point `w` of level `l` on a
    /// ray of direction `dir`, shaded by `sh` (unshaded while a neighbour
    /// is not served).
    pub(crate) fn shade(
        &mut self,
        sh: &Shading,
        c: [f32; 4],
        (l, w, dir): (usize, Vec3, Vec3),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        match self.gradient(l, w, req, st) {
            Some(g) => blinn_phong(sh, c, g, dir),
            None => c,
        }
    }
}

/// `c·(ambient + diffuse·x) + specular·x^shininess` with
/// `x = |ĝ·d̂|`, the cosine between the gradient and the ray (the light
/// and the half vector lie along the ray); `c` as it is for a zero
/// gradient. Opacity unchanged.
pub(crate) fn blinn_phong(sh: &Shading, c: [f32; 4], g: [f64; 3], dir: Vec3) -> [f32; 4] {
    match cosine(g, dir) {
        Some(x) => lit(sh, c, x),
        None => c,
    }
}

/// `|ĝ·d̂|`; `None` for a zero gradient.
#[inline]
pub(crate) fn cosine(g: [f64; 3], dir: Vec3) -> Option<f64> {
    let gg = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
    if gg == 0.0 {
        return None;
    }
    let dd = dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2];
    Some(((g[0] * dir[0] + g[1] * dir[1] + g[2] * dir[2]) / (gg * dd).sqrt()).abs())
}

/// Colour `c` lit at cosine `x` (see [`blinn_phong`]).
#[inline]
pub(crate) fn lit(sh: &Shading, c: [f32; 4], x: f64) -> [f32; 4] {
    let diffuse = sh.ambient as f64 + sh.diffuse as f64 * x;
    let specular = sh.specular as f64 * x.powf(sh.shininess as f64);
    let f = |ch: f32| (ch as f64 * diffuse + specular) as f32;
    [f(c[0]), f(c[1]), f(c[2]), c[3]]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Worked by hand: facing the light, the colour times
    /// `ambient + diffuse` plus the specular term; edge-on, the ambient
    /// part only; the sign of the gradient and its length do not matter;
    /// a zero gradient leaves the colour.
    #[test]
    fn blinn_phong_by_hand() {
        let sh = Shading {
            ambient: 0.25,
            diffuse: 0.5,
            specular: 0.125,
            shininess: 4.0,
        };
        let c = [0.8, 0.4, 0.0, 0.3];
        let facing = blinn_phong(&sh, c, [0.0, 0.0, -7.0], [0.0, 0.0, 2.0]);
        let want = [0.8 * 0.75 + 0.125, 0.4 * 0.75 + 0.125, 0.125, 0.3];
        for (a, b) in facing.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{facing:?}");
        }
        let edge = blinn_phong(&sh, c, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        assert!((edge[0] - 0.2).abs() < 1e-6 && edge[2] == 0.0, "{edge:?}");
        // At 60°: x = ½, specular ½⁴·0.125.
        let s3 = 3f64.sqrt();
        let oblique = blinn_phong(&sh, c, [s3, 0.0, 1.0], [0.0, 0.0, -1.0]);
        let want = 0.8 * (0.25 + 0.25) + 0.125 / 16.0;
        assert!((oblique[0] as f64 - want).abs() < 1e-6, "{oblique:?}");
        assert_eq!(blinn_phong(&sh, c, [0.0; 3], [0.0, 0.0, 1.0]), c);
    }
}
