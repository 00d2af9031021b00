//! Cameras, rays and the world ↔ volume coordinate conventions.
//!
//! Over 800 lines: with its tests: 0.7k lines of code, 0.35k of tests.
//!
//! # WORLD COORDINATES ARE `[x, y, z]`
//!
//! Everything else in brickyard (array shapes, spacing, voxel indices, the
//! normalized positions `p` of the virtual memory) is ordered `[z, y, x]`.
//! **This module is the one exception**: cameras, rays and world points use
//! the graphics convention `[x, y, z]`. Convert with [`world_extent`],
//! [`world_to_normalized`] and [`normalized_to_world`]; never index one
//! with the other's order.
//!
//! - The volume occupies the world box `[0, X] × [0, Y] × [0, Z]` where
//!   `X = dims_x · spacing_x` (physical size, from the spacing), and so on.
//!   The centre of voxel `(k, j, i)` (`[z, y, x]` indices) is the world point
//!   `((i + 0.5)·sx, (j + 0.5)·sy, (k + 0.5)·sz)`.
//! - The normalized real position used by the virtual memory is
//!   `p = [z, y, x] ∈ [0, 1]³` with `p[a] = world[axis] / extent[axis]`
//!   (`p[0] = world[2] / Z`, `p[1] = world[1] / Y`, `p[2] = world[0] / X`).
//! - World up is **+z** for the orbit and turntable helpers: azimuth turns
//!   about the z axis, elevation lifts the eye towards +z.
//! - Image space: pixel `(i, j)` covers `[i, i+1) × [j, j+1)`, its centre is
//!   `(i + 0.5, j + 0.5)`, x grows to the right and **y grows downwards**
//!   (row 0 is the top row).

use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::fmt;

/// The largest coordinate a camera takes (world units; 1e15 µm is a
/// thousand kilometres): squared distances stay far from overflowing, and a
/// volume's size stays far above the rounding of positions around it.
pub const MAX_COORD: f64 = 1e15;

/// A 3-vector in world coordinates `[x, y, z]`.
pub type Vec3 = [f64; 3];

/// The room a default slice view leaves around the volume: the box's
/// projection fills `1 / FIT_MARGIN` of the image's limiting direction
/// ([`Camera::fit_plane`]).
pub const FIT_MARGIN: f64 = 1.05;

/// World extent `[X, Y, Z]` of a volume of `dims` voxels (`[z, y, x]`) with
/// voxel spacing `spacing` (`[z, y, x]`).
pub fn world_extent(dims: [u64; 3], spacing: [f64; 3]) -> Vec3 {
    [
        dims[2] as f64 * spacing[2],
        dims[1] as f64 * spacing[1],
        dims[0] as f64 * spacing[0],
    ]
}

/// Where a slice at `frac` (0 to 1) of an axis of `voxels` voxels spanning
/// `extent` lies: at the centre of the voxel layer that holds that
/// fraction (the last layer for 1), so that a slice shows one layer of
/// the volume rather than a blend of two, and a label image's nearest
/// voxel is never a tie (the middle of an even depth is a boundary).
pub fn slice_centre(extent: f64, voxels: u64, frac: f64) -> f64 {
    let n = voxels.max(1) as f64;
    let layer = (frac * n).floor().clamp(0.0, n - 1.0);
    (layer + 0.5) * extent / n
}

/// The voxel `[z, y, x]` of a volume of `dims` voxels spanning `extent`
/// that holds the world point `world` (points outside are clamped to the
/// nearest voxel).
pub fn world_to_voxel(world: Vec3, extent: Vec3, dims: [u64; 3]) -> [u64; 3] {
    let p = world_to_normalized(world, extent);
    [0, 1, 2].map(|a| ((p[a] * dims[a] as f64).floor().max(0.0) as u64).min(dims[a] - 1))
}

/// The voxel `[z, y, x]` of level `l` of a pyramid of sizes `levels` over
/// `extent` that holds the world point `world` (clamped to the level's
/// voxels): [`world_to_voxel`] with the level's
/// [`level_span`](crate::level_span) for its size.
pub fn world_to_level_voxel(world: Vec3, extent: Vec3, levels: &[[u64; 3]], l: usize) -> [u64; 3] {
    let p = world_to_normalized(world, extent);
    let (s, dims) = (crate::level_span(levels, l), levels[l]);
    [0, 1, 2].map(|a| ((p[a] * s[a]).floor().max(0.0) as u64).min(dims[a] - 1))
}

/// Normalized real position `p = [z, y, x]` of the world point `world`
/// (`[x, y, z]`) in a volume of world extent `extent` (`[X, Y, Z]`):
/// `p[a] = world[axis] / extent[axis]`. Not clamped: points outside the box
/// give values outside `[0, 1]`. Renderers that must match each other
/// sample-for-sample use this exact function.
#[inline]
pub fn world_to_normalized(world: Vec3, extent: Vec3) -> [f64; 3] {
    [
        world[2] / extent[2],
        world[1] / extent[1],
        world[0] / extent[0],
    ]
}

/// Inverse of [`world_to_normalized`]: the world point `[x, y, z]` of the
/// normalized position `p = [z, y, x]`.
#[inline]
pub fn normalized_to_world(p: [f64; 3], extent: Vec3) -> Vec3 {
    [p[2] * extent[0], p[1] * extent[1], p[0] * extent[2]]
}

#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline]
pub fn length(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`; a zero vector stays zero.
#[inline]
pub fn normalize(a: Vec3) -> Vec3 {
    let l = length(a);
    if l > 0.0 {
        scale(a, 1.0 / l)
    } else {
        a
    }
}

/// A ray in world coordinates: the points `origin + t·dir`, `t ≥ 0`;
/// `dir` has unit length, so `t` is a world distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

impl Ray {
    /// The point at parameter `t`.
    #[inline]
    pub fn at(&self, t: f64) -> Vec3 {
        [
            self.origin[0] + t * self.dir[0],
            self.origin[1] + t * self.dir[1],
            self.origin[2] + t * self.dir[2],
        ]
    }
}

/// The part of `ray` (`t ≥ 0`) inside the closed box `[min, max]` (world,
/// `[x, y, z]`), as `(t0, t1)` with `0 ≤ t0 ≤ t1`, or `None` when the ray
/// misses the box, only touches it in a single point, or the box lies
/// behind the origin. A ray starting inside the box gets `t0 = 0`.
/// Components of `dir` that are exactly zero are handled (the ray is inside
/// that slab everywhere or nowhere).
pub fn intersect_box(ray: &Ray, min: Vec3, max: Vec3) -> Option<(f64, f64)> {
    let d = ray.dir;
    intersect_box_inv(ray, [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]], min, max)
}

/// [`intersect_box`] given `inv_dir = 1 / ray.dir` per axis (for a caller
/// that needs the inverse too); the same result.
#[inline]
pub fn intersect_box_inv(ray: &Ray, inv_dir: Vec3, min: Vec3, max: Vec3) -> Option<(f64, f64)> {
    let mut t0 = 0.0f64;
    let mut t1 = f64::INFINITY;
    for a in 0..3 {
        let o = ray.origin[a];
        let d = ray.dir[a];
        if d == 0.0 {
            if o < min[a] || o > max[a] {
                return None;
            }
            continue;
        }
        let inv = inv_dir[a];
        let (ta, tb) = ((min[a] - o) * inv, (max[a] - o) * inv);
        let (ta, tb) = if ta > tb { (tb, ta) } else { (ta, tb) };
        // Comparisons rather than `f64::max`/`min` (which handle NaN in
        // more instructions): a NaN is ignored either way.
        t0 = if ta > t0 { ta } else { t0 };
        t1 = if tb < t1 { tb } else { t1 };
    }
    if t1 > t0 {
        Some((t0, t1))
    } else {
        None
    }
}

/// How the camera projects.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Projection {
    /// Pinhole camera with a vertical field of view in degrees (0 < fov < 180).
    Perspective { fov_y_deg: f64 },
    /// Parallel rays; `height` is the world size of the image's height.
    Orthographic { height: f64 },
}

/// A look-at camera. **World coordinates `[x, y, z]`** (see the module docs).
///
/// The view direction is `target − eye`; `up` need not be unit length nor
/// orthogonal to the view direction, only not parallel to it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "serde_json::Value")]
pub struct Camera {
    pub projection: Projection,
    pub eye: Vec3,
    pub target: Vec3,
    pub up: Vec3,
}

/// Orthonormal camera frame: `right`, `up` (on screen) and `forward`
/// (view direction). `right = forward × up_hint` normalized,
/// `up = right × forward`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Basis {
    pub right: Vec3,
    pub up: Vec3,
    pub forward: Vec3,
}

/// Rays of one camera for one image size, with the frame precomputed.
/// [`Camera::ray`] goes through this, so both give identical rays.
#[derive(Debug, Clone, Copy)]
pub struct RayGen {
    eye: Vec3,
    basis: Basis,
    width: f64,
    height: f64,
    /// Perspective: `tan(fov_y / 2)`; orthographic: half the view height.
    half_h: f64,
    perspective: bool,
}

impl RayGen {
    /// The ray through the continuous image position `(px, py)`: pixel
    /// `(i, j)` has its centre at `(i + 0.5, j + 0.5)`; y grows downwards.
    #[inline]
    pub fn ray(&self, px: f64, py: f64) -> Ray {
        self.ray_at(self.column(px), self.row(py))
    }

    /// The part of [`ray`](Self::ray) that depends on `px` alone: the
    /// offset along the right vector (per unit of forward distance in
    /// perspective). A renderer computes it once per column.
    #[inline]
    pub fn column(&self, px: f64) -> f64 {
        let aspect = self.width / self.height;
        (2.0 * px / self.width - 1.0) * self.half_h * aspect
    }

    /// The part of [`ray`](Self::ray) that depends on `py` alone: the
    /// offset along the up vector.
    #[inline]
    pub fn row(&self, py: f64) -> f64 {
        (1.0 - 2.0 * py / self.height) * self.half_h
    }

    /// The ray at the offsets [`column`](Self::column) and
    /// [`row`](Self::row) give: `ray(px, py)` is `ray_at(column(px),
    /// row(py))`, bit for bit.
    #[inline]
    pub fn ray_at(&self, sx: f64, sy: f64) -> Ray {
        let b = &self.basis;
        let off = add(scale(b.right, sx), scale(b.up, sy));
        if self.perspective {
            Ray {
                origin: self.eye,
                dir: normalize(add(b.forward, off)),
            }
        } else {
            Ray {
                origin: add(self.eye, off),
                dir: b.forward,
            }
        }
    }

    /// The ray through `(px, py)` of a camera moved `eye_shift` world units
    /// along its right vector whose frustum is shifted so that the plane
    /// `distance` in front of the unmoved eye looks the same (off-axis,
    /// parallel frusta: what stereo and multi-view displays need; no
    /// toe-in). Orthographic cameras get the matching oblique projection:
    /// parallel rays from the moved eye's plane through the same points of
    /// that plane. `eye_shift = 0` gives [`RayGen::ray`] exactly.
    #[inline]
    pub fn shifted_ray(&self, px: f64, py: f64, eye_shift: f64, distance: f64) -> Ray {
        if eye_shift == 0.0 {
            return self.ray(px, py);
        }
        let aspect = self.width / self.height;
        let sx = (2.0 * px / self.width - 1.0) * self.half_h * aspect;
        let sy = (1.0 - 2.0 * py / self.height) * self.half_h;
        let b = &self.basis;
        let slope = eye_shift / distance;
        if self.perspective {
            let off = add(scale(b.right, sx - slope), scale(b.up, sy));
            Ray {
                origin: add(self.eye, scale(b.right, eye_shift)),
                dir: normalize(add(b.forward, off)),
            }
        } else {
            let off = add(scale(b.right, sx + eye_shift), scale(b.up, sy));
            Ray {
                origin: add(self.eye, off),
                dir: normalize(sub(b.forward, scale(b.right, slope))),
            }
        }
    }

    /// The ray through the centre of pixel `(i, j)`.
    #[inline]
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        self.ray(i as f64 + 0.5, j as f64 + 0.5)
    }

    /// The eye: where perspective rays start.
    pub fn eye(&self) -> Vec3 {
        self.eye
    }

    /// Whether rays fan out from the eye (else they are parallel).
    pub fn is_perspective(&self) -> bool {
        self.perspective
    }

    /// The image's width and height in pixels.
    pub fn size(&self) -> [f64; 2] {
        [self.width, self.height]
    }

    /// `point` in the camera's frame: its offset from the eye along
    /// `right`, `up` and `forward`. The last is the ray parameter of its
    /// depth: perspective, the distance from the eye along the view
    /// direction; orthographic, from the eye's plane.
    #[inline]
    pub fn eye_coords(&self, point: Vec3) -> Vec3 {
        let v = sub(point, self.eye);
        let b = &self.basis;
        [dot(v, b.right), dot(v, b.up), dot(v, b.forward)]
    }

    /// The continuous image position of a point given by its
    /// [`eye_coords`](Self::eye_coords); perspective needs `z > 0`.
    #[inline]
    pub fn image_of(&self, [x, y, z]: Vec3) -> [f64; 2] {
        let (sx, sy) = if self.perspective {
            (x / z, y / z)
        } else {
            (x, y)
        };
        let nx = sx / (self.half_h * self.width / self.height);
        let ny = sy / self.half_h;
        [
            (nx + 1.0) * 0.5 * self.width,
            (1.0 - ny) * 0.5 * self.height,
        ]
    }

    /// The continuous image position `(px, py)` (pixel centres at `+0.5`,
    /// y down) where the world point `point` appears, or `None` when it
    /// lies on or behind the eye's plane (perspective only). Inverse of
    /// [`RayGen::ray`]: the ray through the returned position passes
    /// through `point`.
    pub fn project(&self, point: Vec3) -> Option<[f64; 2]> {
        let v = self.eye_coords(point);
        if self.perspective && v[2] <= 0.0 {
            return None;
        }
        Some(self.image_of(v))
    }
}

impl Camera {
    /// A look-at camera. Call [`Camera::validate`] on untrusted input.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, projection: Projection) -> Camera {
        Camera {
            projection,
            eye,
            target,
            up,
        }
    }

    /// A camera on a sphere of radius `distance` around `target`, world up
    /// +z. Azimuth 0 puts the eye on the −y side looking towards +y (x to
    /// the right, z up on screen); positive azimuth turns the eye
    /// counter-clockwise seen from +z (azimuth 90: eye on the +x side).
    /// Elevation lifts the eye towards +z (90: looking straight down −z,
    /// with +y up on screen at azimuth 0). The camera's `up` is the
    /// elevation tangent, so every elevation, ±90 included, is well defined.
    pub fn orbit(
        target: Vec3,
        distance: f64,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
    ) -> Camera {
        let (sa, ca) = azimuth_deg.to_radians().sin_cos();
        let (se, ce) = elevation_deg.to_radians().sin_cos();
        let offset = [distance * ce * sa, -distance * ce * ca, distance * se];
        let up = [-se * sa, se * ca, ce];
        Camera {
            projection,
            eye: add(target, offset),
            target,
            up,
        }
    }

    /// An orbit camera that frames the whole box `[0, extent]` (world
    /// `[x, y, z]`): it looks at the box centre and its view contains the
    /// box's bounding sphere vertically (for images at least as wide as
    /// they are tall, horizontally too; [`Camera::fit_image`] fits both
    /// for any image). Orthographic: `height` in `projection` is replaced
    /// by the sphere's diameter.
    pub fn fit(
        extent: Vec3,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
    ) -> Camera {
        let centre = scale(extent, 0.5);
        let r = length(extent) * 0.5;
        let (distance, projection) = match projection {
            Projection::Perspective { fov_y_deg } => {
                let half = (fov_y_deg * 0.5).to_radians();
                (r / half.sin(), projection)
            }
            Projection::Orthographic { .. } => {
                (2.0 * r, Projection::Orthographic { height: 2.0 * r })
            }
        };
        Camera::orbit(centre, distance, azimuth_deg, elevation_deg, projection)
    }

    /// [`Camera::fit`] for a `width × height` image: the box's bounding
    /// sphere lies within the image's height **and** its width (the
    /// narrower of the two limits; the same camera as `fit` for images at
    /// least as wide as they are tall). The sphere, not the box's
    /// projection, so that every direction (a turntable's frames) is
    /// framed alike. A box whose projection would fall between two rows
    /// or columns of pixel centres (under a pixel across, an even number
    /// of pixels) is moved half a pixel onto the nearest ones
    /// ([`Camera::on_pixel_centres`]).
    pub fn fit_image(
        extent: Vec3,
        azimuth_deg: f64,
        elevation_deg: f64,
        projection: Projection,
        width: u32,
        height: u32,
    ) -> Camera {
        let aspect = width.max(1) as f64 / height.max(1) as f64;
        let cam = if aspect >= 1.0 {
            Camera::fit(extent, azimuth_deg, elevation_deg, projection)
        } else {
            let centre = scale(extent, 0.5);
            let r = length(extent) * 0.5;
            let (distance, projection) = match projection {
                Projection::Perspective { fov_y_deg } => {
                    // The horizontal half-angle limits.
                    let half = ((fov_y_deg * 0.5).to_radians().tan() * aspect).atan();
                    (r / half.sin(), projection)
                }
                Projection::Orthographic { .. } => (
                    2.0 * r,
                    Projection::Orthographic {
                        height: 2.0 * r / aspect,
                    },
                ),
            };
            Camera::orbit(centre, distance, azimuth_deg, elevation_deg, projection)
        };
        cam.on_pixel_centres(extent, width, height)
    }

    /// The default camera of a slice: orthographic, looking along `normal`
    /// at the plane through `origin` (as [`Camera::facing_plane`] orients
    /// it), centred on the box `[0, extent]`'s centre projected into the
    /// plane, and as tall as the box's projection needs to fit the
    /// `width × height` image in both directions with [`FIT_MARGIN`]
    /// (for a normal along z and a square image: `max(X, Y) · 1.05`).
    /// Sub-pixel projections are moved onto pixel centres as in
    /// [`Camera::fit_image`].
    pub fn fit_plane(extent: Vec3, origin: Vec3, normal: Vec3, width: u32, height: u32) -> Camera {
        let n = normalize(normal);
        // The box's centre in the plane: for the default plane (a normal
        // along z through the centre's x and y) the offset is exactly zero
        // and the target is `origin` itself.
        let d = sub(scale(extent, 0.5), origin);
        let centre = add(origin, sub(d, scale(n, dot(d, n))));
        let b = Camera::facing_plane(centre, normal, 1.0).basis();
        // The projection of a box onto a unit axis spans Σ |axis_a| · extent_a.
        let span = |axis: Vec3| (0..3).map(|a| axis[a].abs() * extent[a]).sum::<f64>();
        let aspect = width.max(1) as f64 / height.max(1) as f64;
        let h = span(b.up).max(span(b.right) / aspect) * FIT_MARGIN;
        // A volume of zero size (never from a store) still gets a camera.
        let h = if h > 0.0 { h } else { 1.0 };
        Camera::facing_plane(centre, normal, h).on_pixel_centres(extent, width, height)
    }

    /// This camera moved half a pixel (or less) along its right and up
    /// vectors where the projection of the box `[0, extent]` into a
    /// `width × height` image covers no pixel centre across that
    /// direction (it is under a pixel across and falls between two): then
    /// its middle moves onto the nearest pixel centre, and the rays
    /// through that row or column meet it. Where it covers one already
    /// (every box a pixel or more across), or a corner lies behind a
    /// perspective eye, the camera is unchanged.
    pub fn on_pixel_centres(self, extent: Vec3, width: u32, height: u32) -> Camera {
        let (w, h) = (width.max(1), height.max(1));
        let rg = self.ray_gen(w, h);
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for c in 0..8 {
            let p = [0, 1, 2].map(|a| if c >> a & 1 == 1 { extent[a] } else { 0.0 });
            let Some(q) = rg.project(p) else {
                return self;
            };
            for k in 0..2 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        // How far (in pixels) the projection's middle moves, per image axis.
        let mut delta = [0.0; 2];
        for k in 0..2 {
            if !(lo[k].is_finite() && hi[k].is_finite()) {
                return self;
            }
            // Pixel centres at i + 0.5: one lies in [lo, hi] unless both
            // round to the same gap.
            if (lo[k] - 0.5).ceil() > (hi[k] - 0.5).floor() {
                let mid = 0.5 * (lo[k] + hi[k]);
                delta[k] = ((mid - 0.5).round() + 0.5) - mid;
            }
        }
        if delta == [0.0; 2] {
            return self;
        }
        let b = self.basis();
        let fp = self.pixel_footprint(length(sub(self.target, self.eye)), h);
        // Moving the camera right moves the image left; moving it up
        // moves the image down (y grows downwards).
        let shift = add(scale(b.right, -delta[0] * fp), scale(b.up, delta[1] * fp));
        Camera {
            eye: add(self.eye, shift),
            target: add(self.target, shift),
            ..self
        }
    }

    /// An orthographic camera looking along `normal` at the plane through
    /// `origin`, the plane filling a view `height` world units tall. The eye
    /// sits `height` in front of the plane. On screen: for a normal along
    /// ±z, x goes right and y **down** (like an image of an `[y, x]` slice);
    /// otherwise world +z is up.
    pub fn facing_plane(origin: Vec3, normal: Vec3, height: f64) -> Camera {
        let n = normalize(normal);
        let up = if n[0].abs() < 1e-9 && n[1].abs() < 1e-9 {
            [0.0, -1.0, 0.0]
        } else {
            [0.0, 0.0, 1.0]
        };
        Camera {
            projection: Projection::Orthographic { height },
            eye: sub(origin, scale(n, height)),
            target: origin,
            up,
        }
    }

    /// The camera frame. Assumes a valid camera ([`Camera::validate`]).
    pub fn basis(&self) -> Basis {
        let forward = normalize(sub(self.target, self.eye));
        let right = normalize(cross(forward, self.up));
        let up = cross(right, forward);
        Basis { right, up, forward }
    }

    /// Precomputed ray generation for a `width × height` image.
    pub fn ray_gen(&self, width: u32, height: u32) -> RayGen {
        let (half_h, perspective) = match self.projection {
            Projection::Perspective { fov_y_deg } => ((fov_y_deg * 0.5).to_radians().tan(), true),
            Projection::Orthographic { height } => (height * 0.5, false),
        };
        RayGen {
            eye: self.eye,
            basis: self.basis(),
            width: width as f64,
            height: height as f64,
            half_h,
            perspective,
        }
    }

    /// The ray through the continuous image position `(px, py)` of a
    /// `width × height` image. **Pixel `(i, j)` has its centre at
    /// `(i + 0.5, j + 0.5)`** (pass `i as f64 + 0.5`); y grows downwards.
    /// Perspective rays start at the eye; orthographic rays start on the
    /// plane through the eye perpendicular to the view direction. For many
    /// rays use [`Camera::ray_gen`] (same result, frame computed once).
    pub fn ray(&self, px: f64, py: f64, width: u32, height: u32) -> Ray {
        self.ray_gen(width, height).ray(px, py)
    }

    /// The continuous image position `(px, py)` (pixel centres at `+0.5`,
    /// y down) where the world point `point` appears in a `width × height`
    /// image, or `None` when it lies on or behind the eye's plane
    /// (perspective only). Inverse of [`Camera::ray`]: the ray through the
    /// returned position passes through `point`.
    pub fn project(&self, point: Vec3, width: u32, height: u32) -> Option<[f64; 2]> {
        self.ray_gen(width, height).project(point)
    }

    /// World size of one pixel (its height) at distance `distance_along_ray`
    /// from the eye, for an image `height` pixels tall: for choosing the
    /// level of detail. Perspective: `2·d·tan(fov_y/2) / height` (exact for
    /// the central ray; off-axis rays, whose distance overstates the depth
    /// by `1/cos θ`, get a slightly larger, i.e. coarser, value).
    /// Orthographic: `view height / height` at every distance.
    pub fn pixel_footprint(&self, distance_along_ray: f64, height: u32) -> f64 {
        match self.projection {
            Projection::Perspective { fov_y_deg } => {
                2.0 * distance_along_ray * (fov_y_deg * 0.5).to_radians().tan() / height as f64
            }
            Projection::Orthographic { height: h } => h / height as f64,
        }
    }

    /// Frame `i` of a `frames`-frame turntable: this camera rotated by
    /// `360° · i / frames` about the world z axis through the target (eye
    /// and up rotate; positive angles counter-clockwise seen from +z, the
    /// same sense as the orbit azimuth).
    pub fn turntable(&self, frames: u32, i: u32) -> Camera {
        let angle = if frames == 0 {
            0.0
        } else {
            360.0 * i as f64 / frames as f64
        };
        let (s, c) = angle.to_radians().sin_cos();
        let rot = |v: Vec3| [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]];
        Camera {
            projection: self.projection,
            eye: add(self.target, rot(sub(self.eye, self.target))),
            target: self.target,
            up: rot(self.up),
        }
    }

    /// Check that the camera can produce rays: finite numbers, eye ≠
    /// target, up not parallel to the view direction, 0 < fov < 180,
    /// orthographic height > 0.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let err = |field: &str, msg: String| Err(ConfigError::new("camera", field, msg));
        for (name, v) in [("eye", self.eye), ("target", self.target), ("up", self.up)] {
            if v.iter().any(|x| !x.is_finite()) {
                return err(name, format!("must be finite numbers, got {v:?}"));
            }
            // Beyond this, distances and their squares overflow (or lose
            // every digit of a volume's size), and rays get no direction.
            if v.iter().any(|x| x.abs() > MAX_COORD) {
                return err(
                    name,
                    format!("must be within ±{MAX_COORD:e} (world units), got {v:?}"),
                );
            }
        }
        match self.projection {
            Projection::Perspective { fov_y_deg } => {
                if !(fov_y_deg > 0.0 && fov_y_deg < 180.0) {
                    return err(
                        "projection.fov_y_deg",
                        format!("must be between 0 and 180 degrees (exclusive), got {fov_y_deg}"),
                    );
                }
            }
            Projection::Orthographic { height } => {
                if !(height > 0.0 && height.is_finite()) {
                    return err(
                        "projection.height",
                        format!("must be a positive world length, got {height}"),
                    );
                }
            }
        }
        let f = sub(self.target, self.eye);
        let lf = length(f);
        if lf == 0.0 {
            return err(
                "target",
                "equals eye: the view direction is undefined".into(),
            );
        }
        let lu = length(self.up);
        if lu == 0.0 || length(cross(f, self.up)) <= 1e-9 * lf * lu {
            return err(
                "up",
                format!("{:?} is zero or parallel to the view direction", self.up),
            );
        }
        Ok(())
    }

    /// Parse a camera from JSON, e.g.
    /// `{"projection": {"type": "perspective", "fov_y_deg": 30},
    ///   "eye": [0, -500, 100], "target": [128, 128, 80], "up": [0, 0, 1]}`
    /// (`up` defaults to `[0, 0, 1]`). Errors name the offending field.
    pub fn from_json(s: &str) -> Result<Camera, ConfigError> {
        let v: Value = serde_json::from_str(s).map_err(|e| ConfigError::syntax("camera", &e))?;
        Camera::try_from(v)
    }

    /// The camera as pretty JSON (what [`Camera::from_json`] reads).
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a camera always serializes")
    }
}

impl TryFrom<Value> for Camera {
    type Error = ConfigError;
    /// The camera of a camera file; a slice's plane in it
    /// ([`CameraFile`]) is checked and left out.
    fn try_from(v: Value) -> Result<Camera, ConfigError> {
        CameraFile::try_from(v).map(|f| f.camera)
    }
}

/// A camera file as `render --save-camera` writes it and `render --camera`
/// reads it: the camera and, for a slice, its plane, in the terms of
/// `render`'s options: `slice_origin` (a point of the plane, world
/// `[x, y, z]` as `--slice-origin`) and `slice_normal` (as
/// `--slice-normal`, not normalized). Files without the plane (older ones,
/// the viewer's, those of 3D views) read with both `None`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraFile {
    pub camera: Camera,
    pub slice_origin: Option<Vec3>,
    pub slice_normal: Option<Vec3>,
}

impl CameraFile {
    /// Parse a camera file: [`Camera::from_json`]'s fields and the
    /// optional `slice_origin` (within ±[`MAX_COORD`]) and `slice_normal`
    /// (non-zero). Errors name the offending field.
    pub fn from_json(s: &str) -> Result<CameraFile, ConfigError> {
        let v: Value = serde_json::from_str(s).map_err(|e| ConfigError::syntax("camera", &e))?;
        CameraFile::try_from(v)
    }

    /// The file as pretty JSON: the camera's fields as
    /// [`Camera::to_json`] writes them, then the plane's where there is
    /// one.
    pub fn to_json(&self) -> String {
        #[derive(Serialize)]
        struct Out<'a> {
            #[serde(flatten)]
            camera: &'a Camera,
            #[serde(skip_serializing_if = "Option::is_none")]
            slice_origin: Option<Vec3>,
            #[serde(skip_serializing_if = "Option::is_none")]
            slice_normal: Option<Vec3>,
        }
        let out = Out {
            camera: &self.camera,
            slice_origin: self.slice_origin,
            slice_normal: self.slice_normal,
        };
        serde_json::to_string_pretty(&out).expect("a camera file always serializes")
    }
}

impl TryFrom<Value> for CameraFile {
    type Error = ConfigError;
    fn try_from(v: Value) -> Result<CameraFile, ConfigError> {
        let o = Fields::new(
            "camera",
            &v,
            &[
                "projection",
                "eye",
                "target",
                "up",
                "slice_origin",
                "slice_normal",
            ],
        )?;
        let pv = o.required("projection")?;
        let projection = parse_projection(pv)?;
        let cam = Camera {
            projection,
            eye: o.vec3("eye")?.ok_or_else(|| o.missing("eye"))?,
            target: o.vec3("target")?.ok_or_else(|| o.missing("target"))?,
            up: o.vec3("up")?.unwrap_or([0.0, 0.0, 1.0]),
        };
        cam.validate()?;
        let slice_origin = o.vec3("slice_origin")?;
        if let Some(p) = slice_origin.filter(|p| p.iter().any(|x| x.abs() > MAX_COORD)) {
            return Err(o.err(
                "slice_origin",
                format!("must be within ±{MAX_COORD:e} (world units), got {p:?}"),
            ));
        }
        let slice_normal = o.vec3("slice_normal")?;
        if let Some(n) = slice_normal.filter(|n| !(1e-12..=f64::MAX).contains(&length(*n))) {
            return Err(o.err(
                "slice_normal",
                format!("must be a non-zero vector of finite length, got {n:?}"),
            ));
        }
        Ok(CameraFile {
            camera: cam,
            slice_origin,
            slice_normal,
        })
    }
}

fn parse_projection(v: &Value) -> Result<Projection, ConfigError> {
    let what = "camera";
    let obj = v.as_object().ok_or_else(|| {
        ConfigError::new(
            what,
            "projection",
            format!(
                "expected an object like {{\"type\": \"perspective\", \"fov_y_deg\": 30}} or \
                 {{\"type\": \"orthographic\", \"height\": 100}}, got {}",
                brief(v)
            ),
        )
    })?;
    let ty = obj.get("type").and_then(Value::as_str).ok_or_else(|| {
        ConfigError::new(
            what,
            "projection.type",
            "missing or not a string; expected \"perspective\" or \"orthographic\"",
        )
    })?;
    let num = |key: &str| -> Result<f64, ConfigError> {
        let field = format!("projection.{key}");
        match obj.get(key) {
            None => Err(ConfigError::new(
                what,
                &field,
                format!("missing (required for a {ty} projection)"),
            )),
            Some(x) => x.as_f64().ok_or_else(|| {
                ConfigError::new(what, &field, format!("expected a number, got {}", brief(x)))
            }),
        }
    };
    let check_keys = |allowed: &[&str]| -> Result<(), ConfigError> {
        for k in obj.keys() {
            if k != "type" && !allowed.contains(&k.as_str()) {
                return Err(ConfigError::new(
                    what,
                    &format!("projection.{k}"),
                    format!("unknown field for a {ty} projection (expected {allowed:?})"),
                ));
            }
        }
        Ok(())
    };
    match ty {
        "perspective" => {
            check_keys(&["fov_y_deg"])?;
            Ok(Projection::Perspective {
                fov_y_deg: num("fov_y_deg")?,
            })
        }
        "orthographic" => {
            check_keys(&["height"])?;
            Ok(Projection::Orthographic {
                height: num("height")?,
            })
        }
        other => Err(ConfigError::new(
            what,
            "projection.type",
            format!("unknown projection {other:?}; expected \"perspective\" or \"orthographic\""),
        )),
    }
}

/// An invalid camera or transfer function (JSON or values), naming the
/// field at fault.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigError {
    /// What was being read: `"camera"`, `"transfer function"`.
    pub what: String,
    /// The field at fault (`"eye"`, `"opacity[2]"`, `"projection.type"`);
    /// empty for errors of the whole document (JSON syntax).
    pub field: String,
    pub message: String,
}

impl ConfigError {
    pub fn new(what: &str, field: &str, message: impl Into<String>) -> ConfigError {
        ConfigError {
            what: what.into(),
            field: field.into(),
            message: message.into(),
        }
    }

    /// A JSON syntax error.
    pub fn syntax(what: &str, e: &serde_json::Error) -> ConfigError {
        ConfigError::new(what, "", format!("invalid JSON: {e}"))
    }
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.field.is_empty() {
            write!(f, "{}: {}", self.what, self.message)
        } else {
            write!(f, "{}: field `{}`: {}", self.what, self.field, self.message)
        }
    }
}

impl std::error::Error for ConfigError {}

/// A short rendering of a JSON value for error messages.
pub(crate) fn brief(v: &Value) -> String {
    let s = v.to_string();
    if s.chars().count() > 60 {
        format!("{}…", s.chars().take(57).collect::<String>())
    } else {
        s
    }
}

/// Field access on a JSON object with errors that name the field.
pub(crate) struct Fields<'a> {
    pub what: &'static str,
    pub obj: &'a serde_json::Map<String, Value>,
}

impl<'a> Fields<'a> {
    /// `v` must be an object whose keys are all in `allowed`.
    pub fn new(what: &'static str, v: &'a Value, allowed: &[&str]) -> Result<Self, ConfigError> {
        let obj = v.as_object().ok_or_else(|| {
            ConfigError::new(
                what,
                "",
                format!("expected a JSON object, got {}", brief(v)),
            )
        })?;
        for k in obj.keys() {
            if !allowed.contains(&k.as_str()) {
                return Err(ConfigError::new(
                    what,
                    k,
                    format!("unknown field (expected one of {allowed:?})"),
                ));
            }
        }
        Ok(Fields { what, obj })
    }

    pub fn missing(&self, key: &str) -> ConfigError {
        ConfigError::new(self.what, key, "missing")
    }

    pub fn required(&self, key: &str) -> Result<&'a Value, ConfigError> {
        self.obj.get(key).ok_or_else(|| self.missing(key))
    }

    pub fn err(&self, field: &str, msg: impl Into<String>) -> ConfigError {
        ConfigError::new(self.what, field, msg)
    }

    /// An array of exactly `N` numbers at `field` (for messages).
    pub fn numbers<const N: usize>(&self, field: &str, v: &Value) -> Result<[f64; N], ConfigError> {
        let bad = || {
            self.err(
                field,
                format!("expected an array of {N} numbers, got {}", brief(v)),
            )
        };
        let a = v.as_array().ok_or_else(bad)?;
        if a.len() != N {
            return Err(bad());
        }
        let mut out = [0.0; N];
        for (o, x) in out.iter_mut().zip(a) {
            *o = x.as_f64().ok_or_else(bad)?;
        }
        Ok(out)
    }

    /// Optional `[x, y, z]`.
    pub fn vec3(&self, key: &str) -> Result<Option<Vec3>, ConfigError> {
        self.obj
            .get(key)
            .map(|v| self.numbers::<3>(key, v))
            .transpose()
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn a_slice_lies_at_the_centre_of_the_layer_holding_its_fraction() {
        // 60 layers of 4 units: the middle (0.5) is layer 30's centre, not
        // the boundary at 120; 1 is the last layer; 0 the first.
        assert_eq!(slice_centre(240.0, 60, 0.5), 122.0);
        assert_eq!(slice_centre(240.0, 60, 1.0), 238.0);
        assert_eq!(slice_centre(240.0, 60, 0.0), 2.0);
        assert_eq!(slice_centre(240.0, 60, 0.4999), 118.0);
        assert_eq!(slice_centre(3.0, 1, 0.7), 1.5);
    }

    use super::*;

    #[test]
    fn world_points_map_to_the_voxels_that_hold_them() {
        let (extent, dims) = ([20.0, 10.0, 5.0], [5, 10, 20]);
        assert_eq!(world_to_voxel([0.0; 3], extent, dims), [0, 0, 0]);
        assert_eq!(world_to_voxel([19.99, 0.5, 4.99], extent, dims), [4, 0, 19]);
        // The far faces belong to the last voxels; points outside clamp.
        assert_eq!(world_to_voxel(extent, extent, dims), [4, 9, 19]);
        assert_eq!(world_to_voxel([-3.0, 11.0, 2.5], extent, dims), [2, 9, 0]);
    }

    fn close(a: Vec3, b: Vec3, eps: f64) -> bool {
        (0..3).all(|i| (a[i] - b[i]).abs() <= eps)
    }

    /// Distance from `p` to the ray's line.
    fn dist_to_ray(r: &Ray, p: Vec3) -> f64 {
        let v = sub(p, r.origin);
        length(sub(v, scale(r.dir, dot(v, r.dir))))
    }

    const PERSP: Projection = Projection::Perspective { fov_y_deg: 40.0 };
    const ORTHO: Projection = Projection::Orthographic { height: 30.0 };

    fn cameras() -> Vec<Camera> {
        let mut v = vec![];
        for proj in [PERSP, ORTHO] {
            for (az, el) in [
                (0.0, 0.0),
                (30.0, 20.0),
                (-135.0, -60.0),
                (90.0, 90.0),
                (10.0, -90.0),
            ] {
                v.push(Camera::orbit([5.0, -3.0, 2.0], 50.0, az, el, proj));
            }
            v.push(Camera::look_at(
                [1.0, 2.0, 3.0],
                [4.0, -6.0, 8.0],
                [0.3, 0.1, 1.0],
                proj,
            ));
        }
        v
    }

    #[test]
    fn normalized_round_trip() {
        let ext = [10.0, 20.0, 40.0];
        let w = [2.5, 5.0, 30.0];
        let p = world_to_normalized(w, ext);
        assert_eq!(p, [0.75, 0.25, 0.25]);
        assert_eq!(normalized_to_world(p, ext), w);
        assert_eq!(world_extent([4, 5, 6], [2.0, 1.0, 0.5]), [3.0, 5.0, 8.0]);
    }

    #[test]
    fn centre_ray_hits_target_and_rays_are_unit() {
        for cam in cameras() {
            cam.validate().unwrap();
            for (w, h) in [(64, 64), (100, 50), (33, 71)] {
                let r = cam.ray(w as f64 / 2.0, h as f64 / 2.0, w, h);
                assert!(dist_to_ray(&r, cam.target) < 1e-9, "{cam:?} {w}x{h}");
                let f = normalize(sub(cam.target, cam.eye));
                assert!(close(r.dir, f, 1e-12));
                for (px, py) in [(0.5, 0.5), (w as f64 - 0.5, 3.5), (7.25, h as f64 - 0.5)] {
                    let r = cam.ray(px, py, w, h);
                    assert!((length(r.dir) - 1.0).abs() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn orthographic_rays_are_parallel_and_evenly_spaced() {
        let cam = Camera::orbit([0.0; 3], 100.0, 25.0, 35.0, ORTHO);
        let (w, h) = (40u32, 20u32);
        let b = cam.basis();
        let r00 = cam.ray(0.5, 0.5, w, h);
        for j in 0..h {
            for i in 0..w {
                let r = cam.ray(i as f64 + 0.5, j as f64 + 0.5, w, h);
                assert_eq!(r.dir, b.forward);
                // One pixel = height/h world units, right and down.
                let d = sub(r.origin, r00.origin);
                let step = 30.0 / h as f64;
                assert!((dot(d, b.right) - i as f64 * step).abs() < 1e-9);
                assert!((dot(d, b.up) + j as f64 * step).abs() < 1e-9);
                assert!(dot(d, b.forward).abs() < 1e-9);
            }
        }
        // The image spans `height` vertically and height·aspect horizontally.
        let top = cam.ray(20.0, 0.0, w, h);
        let bottom = cam.ray(20.0, 20.0, w, h);
        assert!((length(sub(top.origin, bottom.origin)) - 30.0).abs() < 1e-9);
        let left = cam.ray(0.0, 10.0, w, h);
        let right = cam.ray(40.0, 10.0, w, h);
        assert!((length(sub(left.origin, right.origin)) - 60.0).abs() < 1e-9);
    }

    #[test]
    fn image_axes_right_and_down() {
        // Looking along +y from the -y side (azimuth 0): x to the right, z up.
        let cam = Camera::orbit([0.0; 3], 10.0, 0.0, 0.0, PERSP);
        assert!(close(cam.eye, [0.0, -10.0, 0.0], 1e-12));
        let b = cam.basis();
        assert!(close(b.right, [1.0, 0.0, 0.0], 1e-12));
        assert!(close(b.up, [0.0, 0.0, 1.0], 1e-12));
        // Pixel (0, 0) is top-left: its ray goes left (-x) and up (+z).
        let r = cam.ray(0.5, 0.5, 8, 8);
        assert!(r.dir[0] < 0.0 && r.dir[2] > 0.0);
        // Azimuth 90: eye on +x; elevation 90: looking down -z with +y up.
        let c = Camera::orbit([0.0; 3], 10.0, 90.0, 0.0, PERSP);
        assert!(close(c.eye, [10.0, 0.0, 0.0], 1e-12));
        let c = Camera::orbit([0.0; 3], 10.0, 0.0, 90.0, PERSP);
        assert!(close(c.eye, [0.0, 0.0, 10.0], 1e-12));
        let b = c.basis();
        assert!(close(b.forward, [0.0, 0.0, -1.0], 1e-12));
        assert!(close(b.right, [1.0, 0.0, 0.0], 1e-12));
        assert!(close(b.up, [0.0, 1.0, 0.0], 1e-12));
        // A plane facing +z shows x right and y down.
        let c = Camera::facing_plane([1.0, 1.0, 1.0], [0.0, 0.0, 1.0], 4.0);
        let b = c.basis();
        assert!(close(b.right, [1.0, 0.0, 0.0], 1e-12));
        assert!(close(b.up, [0.0, -1.0, 0.0], 1e-12));
    }

    #[test]
    fn pixel_footprint_matches_ray_spacing() {
        let (w, h) = (256u32, 256u32);
        let cam = Camera::orbit([0.0; 3], 80.0, 10.0, 20.0, PERSP);
        for d in [1.0, 80.0, 1000.0] {
            // Two rays through neighbouring pixels at the image centre,
            // followed to distance d: their separation is one pixel.
            let a = cam.ray(127.5, 128.0, w, h);
            let b = cam.ray(128.5, 128.0, w, h);
            let sep = length(sub(a.at(d), b.at(d)));
            let fp = cam.pixel_footprint(d, h);
            assert!((sep - fp).abs() / fp < 1e-4, "{sep} vs {fp}");
        }
        let cam = Camera::orbit([0.0; 3], 80.0, 10.0, 20.0, ORTHO);
        let a = cam.ray(3.5, 3.5, w, h);
        let b = cam.ray(3.5, 4.5, w, h);
        let fp = cam.pixel_footprint(12.0, h);
        assert!((length(sub(a.origin, b.origin)) - fp).abs() < 1e-12);
        assert!((fp - 30.0 / 256.0).abs() < 1e-15);
    }

    #[test]
    fn project_inverts_ray() {
        for cam in cameras() {
            let (w, h) = (64u32, 48u32);
            for (px, py) in [(0.5, 0.5), (63.5, 47.5), (20.25, 30.75), (32.0, 24.0)] {
                let r = cam.ray(px, py, w, h);
                let p = r.at(37.0);
                let q = cam.project(p, w, h).unwrap();
                assert!(
                    (q[0] - px).abs() < 1e-7 && (q[1] - py).abs() < 1e-7,
                    "{q:?}"
                );
            }
        }
        let cam = Camera::orbit([0.0; 3], 10.0, 0.0, 0.0, PERSP);
        assert!(cam.project([0.0, -20.0, 0.0], 8, 8).is_none());
        // The depth of a point on the central ray is its ray parameter.
        for cam in cameras() {
            let rg = cam.ray_gen(64, 48);
            let z = rg.eye_coords(rg.ray(32.0, 24.0).at(37.0))[2];
            assert!((z - 37.0).abs() < 1e-9, "{z}");
        }
    }

    #[test]
    fn fit_frames_the_box() {
        let ext = [200.0, 150.0, 60.0];
        for proj in [PERSP, ORTHO] {
            for (az, el) in [(0.0, 0.0), (30.0, 20.0), (200.0, -70.0), (0.0, 90.0)] {
                let cam = Camera::fit(ext, az, el, proj);
                assert!(close(cam.target, [100.0, 75.0, 30.0], 1e-12));
                for c in 0..8 {
                    let p = [0, 1, 2].map(|a| if c >> a & 1 == 1 { ext[a] } else { 0.0 });
                    let q = cam.project(p, 100, 100).unwrap();
                    assert!(
                        (0.0..=100.0).contains(&q[0]) && (0.0..=100.0).contains(&q[1]),
                        "corner {p:?} at {q:?} ({proj:?}, {az}, {el})"
                    );
                }
            }
        }
    }

    /// The continuous image box `[x0, x1] × [y0, y1]` (pixels) that the
    /// box `[0, ext]` projects to.
    fn projected_box(cam: &Camera, ext: Vec3, w: u32, h: u32) -> [f64; 4] {
        let mut b = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for c in 0..8 {
            let p = [0, 1, 2].map(|a| if c >> a & 1 == 1 { ext[a] } else { 0.0 });
            let q = cam.project(p, w, h).unwrap();
            b = [
                b[0].min(q[0]),
                b[1].max(q[0]),
                b[2].min(q[1]),
                b[3].max(q[1]),
            ];
        }
        b
    }

    const SIZES: [(u32, u32); 8] = [
        (100, 100),
        (150, 400),
        (400, 150),
        (400, 1),
        (1, 400),
        (4000, 1),
        (1024, 64),
        (33, 71),
    ];

    #[test]
    fn fit_image_frames_the_bounding_sphere_in_both_directions() {
        let ext = [150.5, 185.0, 158.0];
        let r = length(ext) * 0.5;
        for proj in [PERSP, ORTHO] {
            for (az, el) in [(30.0, 20.0), (0.0, 0.0), (200.0, -70.0), (90.0, 90.0)] {
                for (w, h) in SIZES {
                    let cam = Camera::fit_image(ext, az, el, proj, w, h);
                    cam.validate().unwrap();
                    let what = format!("{proj:?} {az} {el} {w}x{h}");
                    if w >= h {
                        let fit = Camera::fit(ext, az, el, proj);
                        assert_eq!(cam, fit.on_pixel_centres(ext, w, h), "{what}");
                    }
                    // The sphere touches the narrower direction's edges and
                    // stays within the other's.
                    let (wf, hf) = (w as f64, h as f64);
                    let rg = cam.ray_gen(w, h);
                    let b = cam.basis();
                    let d = length(sub(cam.target, cam.eye));
                    let (right, up) = match cam.projection {
                        Projection::Orthographic { height } => {
                            (height * 0.5 * wf / hf, height * 0.5)
                        }
                        Projection::Perspective { fov_y_deg } => {
                            // The half-angles' sines: the sphere's angular
                            // radius asin(r / d) must not exceed them.
                            let t = (fov_y_deg * 0.5).to_radians().tan();
                            let s = |t: f64| t / (1.0 + t * t).sqrt();
                            (d * s(t * wf / hf), d * s(t))
                        }
                    };
                    assert!(
                        r <= right * (1.0 + 1e-9) && r <= up * (1.0 + 1e-9),
                        "{what}"
                    );
                    assert!((r - right.min(up)).abs() <= 1e-9 * r, "{what}");
                    // Every corner inside the image.
                    let q = projected_box(&cam, ext, w, h);
                    assert!(
                        q[0] >= 0.0 && q[1] <= wf && q[2] >= 0.0 && q[3] <= hf,
                        "{what}: {q:?}"
                    );
                    // The box's centre projects to the image's centre, or
                    // within half a pixel of it for a box under a pixel
                    // across (moved onto pixel centres).
                    let c = rg.project(scale(ext, 0.5)).unwrap();
                    for (k, n) in [(0, wf), (1, hf)] {
                        let off = (c[k] - n / 2.0).abs();
                        let small = [q[1] - q[0], q[3] - q[2]][k] < 1.0;
                        assert!(off < 1e-6 || small && off <= 0.5 + 1e-6, "{what}: {c:?}");
                    }
                    assert!(close(b.forward, normalize(sub(cam.target, cam.eye)), 1e-12));
                }
            }
        }
    }

    #[test]
    fn fit_plane_fits_the_box_projection_with_the_margin() {
        let ext = [150.5, 185.0, 158.0];
        let normals = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -2.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 0.3, 0.2],
            [-0.4, 1.0, 0.7],
        ];
        for n in normals {
            for origin in [scale(ext, 0.5), [75.25, 92.5, 31.75], [10.0, 170.0, 150.0]] {
                for (w, h) in SIZES {
                    let cam = Camera::fit_plane(ext, origin, n, w, h);
                    cam.validate().unwrap();
                    let what = format!("{n:?} {origin:?} {w}x{h}");
                    let (wf, hf) = (w as f64, h as f64);
                    let b = cam.basis();
                    // Face on, the target in the plane.
                    assert!(close(b.forward, normalize(n), 1e-12), "{what}");
                    assert!(
                        dot(sub(cam.target, origin), normalize(n)).abs() < 1e-9,
                        "{what}"
                    );
                    // The projection fills 1/1.05 of one direction and at
                    // most that of the other, centred.
                    let q = projected_box(&cam, ext, w, h);
                    let (fw, fh) = ((q[1] - q[0]) / wf, (q[3] - q[2]) / hf);
                    let fill = 1.0 / FIT_MARGIN;
                    assert!(fw <= fill + 1e-9 && fh <= fill + 1e-9, "{what}: {fw} {fh}");
                    assert!((fw.max(fh) - fill).abs() < 1e-9, "{what}: {fw} {fh}");
                    // Centred, or within half a pixel of it where the box is
                    // under a pixel across (moved onto pixel centres).
                    let mid = [(q[0] + q[1]) / 2.0, (q[2] + q[3]) / 2.0];
                    for (k, n) in [(0, wf), (1, hf)] {
                        let off = (mid[k] - n / 2.0).abs();
                        let small = [q[1] - q[0], q[3] - q[2]][k] < 1.0;
                        assert!(off < 1e-6 || small && off <= 0.5 + 1e-6, "{what}: {q:?}");
                    }
                    // The margin's pixels are clear: the edge columns and rows
                    // of every image at least 40 pixels across that way.
                    if w >= 40 {
                        assert!(q[0] > 1.0 && q[1] < wf - 1.0, "{what}: {q:?}");
                    }
                    if h >= 40 {
                        assert!(q[2] > 1.0 && q[3] < hf - 1.0, "{what}: {q:?}");
                    }
                }
            }
        }
        // The default plane of a square image: the old view, bit for bit.
        let o = [75.25, 92.5, 79.25];
        assert_eq!(
            Camera::fit_plane(ext, o, [0.0, 0.0, 1.0], 200, 200),
            Camera::facing_plane(o, [0.0, 0.0, 1.0], 185.0 * 1.05)
        );
        // A portrait image: the width limits (150.5 across 150 pixels).
        let cam = Camera::fit_plane(ext, o, [0.0, 0.0, 1.0], 150, 400);
        assert_eq!(
            cam.projection,
            Projection::Orthographic {
                height: 150.5 * 1.05 * 400.0 / 150.0
            }
        );
    }

    #[test]
    fn a_box_thinner_than_a_pixel_is_moved_onto_pixel_centres() {
        // 4096 × 4 × 4 seen face on in 1024 × 64: 4.2 world units a pixel,
        // the box 0.95 pixel tall, centred on the boundary of rows 31 and
        // 32: the rays of the pixel centres missed it.
        let ext = [4096.0, 4.0, 4.0];
        let o = [2048.0, 2.0, 2.5];
        for (w, h) in [(1024, 64), (1024, 1), (1024, 2), (64, 1024), (4000, 1)] {
            let cam = Camera::fit_plane(ext, o, [0.0, 0.0, 1.0], w, h);
            let (mut rows, mut cols) = (vec![false; h as usize], vec![false; w as usize]);
            for j in 0..h {
                for i in 0..w {
                    let r = cam.ray(i as f64 + 0.5, j as f64 + 0.5, w, h);
                    if intersect_box(&r, [0.0; 3], ext).is_some() {
                        (rows[j as usize], cols[i as usize]) = (true, true);
                    }
                }
            }
            let count = |v: &[bool]| v.iter().filter(|x| **x).count();
            // One row across the thin side; the long one fills the
            // width less the margin.
            let (thin, long) = (count(&rows), count(&cols) as f64);
            // World units a pixel: the limiting direction's.
            let px = (ext[0] / w as f64).max(ext[1] / h as f64) * FIT_MARGIN;
            let fill = ext[0] / px;
            assert!(
                thin == 1 && long >= fill.floor() - 1.0 && long <= fill.ceil(),
                "{w}x{h}: {thin} {long}"
            );
            // Moved by half a pixel at most, along the screen only.
            let fp = cam.pixel_footprint(1.0, h);
            let m = sub(cam.target, o);
            assert!(length(m) <= 0.5 * fp * 2f64.sqrt() + 1e-9, "{w}x{h}: {m:?}");
            assert!(m[2].abs() < 1e-12);
        }
        // A small perspective view: the sphere fit leaves a large volume
        // under a pixel in a 1-pixel-high image; the middle column is lit.
        let ext = [150.5, 185.0, 158.0];
        for proj in [PERSP, ORTHO] {
            for (w, h) in [(400, 1), (4000, 1), (2, 2)] {
                let cam = Camera::fit_image(ext, 30.0, 20.0, proj, w, h);
                let hit = (0..w).any(|i| {
                    let r = cam.ray(i as f64 + 0.5, 0.5, w, h);
                    intersect_box(&r, [0.0; 3], ext).is_some()
                });
                assert!(hit, "{proj:?} {w}x{h}");
            }
        }
        // Boxes a pixel or more across stay where they were.
        let cam = Camera::facing_plane([5.0, 5.0, 5.0], [0.0, 0.0, 1.0], 20.0);
        assert_eq!(cam.on_pixel_centres([10.0; 3], 20, 20), cam);
        assert_eq!(cam.on_pixel_centres([10.0; 3], 2, 2), cam);
    }

    #[test]
    fn turntable_rotates_about_z() {
        let cam = Camera::orbit([1.0, 2.0, 3.0], 10.0, 0.0, 30.0, PERSP);
        assert_eq!(cam.turntable(8, 0), cam);
        let q = cam.turntable(4, 1);
        let expect = Camera::orbit([1.0, 2.0, 3.0], 10.0, 90.0, 30.0, PERSP);
        assert!(close(q.eye, expect.eye, 1e-9));
        assert!(close(q.up, expect.up, 1e-9));
        let full = cam.turntable(5, 5);
        assert!(close(full.eye, cam.eye, 1e-9));
        for i in 0..7 {
            let c = cam.turntable(7, i);
            assert!((length(sub(c.eye, c.target)) - 10.0).abs() < 1e-9);
            assert!((c.eye[2] - cam.eye[2]).abs() < 1e-9);
        }
    }

    #[test]
    fn box_intersection() {
        let (lo, hi) = ([0.0; 3], [2.0, 4.0, 8.0]);
        let r = Ray {
            origin: [1.0, 1.0, -2.0],
            dir: [0.0, 0.0, 1.0],
        };
        assert_eq!(intersect_box(&r, lo, hi), Some((2.0, 10.0)));
        // Starting inside.
        let r = Ray {
            origin: [1.0, 1.0, 1.0],
            dir: [0.0, 0.0, 1.0],
        };
        assert_eq!(intersect_box(&r, lo, hi), Some((0.0, 7.0)));
        // Behind.
        let r = Ray {
            origin: [1.0, 1.0, 10.0],
            dir: [0.0, 0.0, 1.0],
        };
        assert_eq!(intersect_box(&r, lo, hi), None);
        // Parallel to a slab, outside it.
        let r = Ray {
            origin: [3.0, 1.0, -2.0],
            dir: [0.0, 0.0, 1.0],
        };
        assert_eq!(intersect_box(&r, lo, hi), None);
        // Parallel and exactly on a face: inside the closed box.
        let r = Ray {
            origin: [0.0, 1.0, -2.0],
            dir: [0.0, 0.0, 1.0],
        };
        assert_eq!(intersect_box(&r, lo, hi), Some((2.0, 10.0)));
        // Diagonal through two corners.
        let d = normalize([2.0, 4.0, 8.0]);
        let r = Ray {
            origin: scale(d, -1.0),
            dir: d,
        };
        let (t0, t1) = intersect_box(&r, lo, hi).unwrap();
        assert!((t0 - 1.0).abs() < 1e-12 && (t1 - 1.0 - length(hi)).abs() < 1e-12);
        // Grazing an edge: touches the box in a single point.
        let r = Ray {
            origin: [-1.0, 3.0, 4.0],
            dir: normalize([1.0, 1.0, 0.0]),
        };
        assert_eq!(intersect_box(&r, lo, hi), None);
        // Missing.
        let r = Ray {
            origin: [-1.0, -1.0, -1.0],
            dir: normalize([-1.0, 1.0, 1.0]),
        };
        assert_eq!(intersect_box(&r, lo, hi), None);
        // Random rays: entry and exit points lie on the box surface.
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut hits = 0;
        for _ in 0..2000 {
            let o = [rnd() * 6.0 - 2.0, rnd() * 8.0 - 2.0, rnd() * 12.0 - 2.0];
            let d = normalize([rnd() - 0.5, rnd() - 0.5, rnd() - 0.5]);
            let r = Ray { origin: o, dir: d };
            if let Some((t0, t1)) = intersect_box(&r, lo, hi) {
                hits += 1;
                let mid = r.at(0.5 * (t0 + t1));
                assert!((0..3).all(|a| mid[a] >= -1e-9 && mid[a] <= hi[a] + 1e-9));
                for t in [t0, t1] {
                    let p = r.at(t);
                    let on_face =
                        (0..3).any(|a| (p[a] - lo[a]).abs() < 1e-9 || (p[a] - hi[a]).abs() < 1e-9);
                    let inside = (0..3).all(|a| p[a] > -1e-9 && p[a] < hi[a] + 1e-9);
                    assert!(inside && (on_face || t == 0.0), "{r:?} {t0} {t1}");
                }
            } else {
                // Dense check: no point of the ray is strictly inside.
                for k in 0..400 {
                    let p = r.at(k as f64 * 0.05);
                    assert!(!(0..3).all(|a| p[a] > 1e-6 && p[a] < hi[a] - 1e-6), "{r:?}");
                }
            }
        }
        assert!(hits > 200);
    }

    #[test]
    fn json_round_trip() {
        // serde_json's default float parser may be off by one ulp.
        let same = |a: &Camera, b: &Camera| {
            a.projection == b.projection
                && close(a.eye, b.eye, 1e-12)
                && close(a.target, b.target, 1e-12)
                && close(a.up, b.up, 1e-12)
        };
        for cam in cameras() {
            let s = cam.to_json();
            assert!(same(&Camera::from_json(&s).unwrap(), &cam), "{s}");
            let v: Camera = serde_json::from_str(&s).unwrap();
            assert!(same(&v, &cam));
        }
        let c = Camera::from_json(
            r#"{"projection": {"type": "orthographic", "height": 5}, "eye": [0, 0, 10], "target": [0, 0, 0], "up": [0, 1, 0]}"#,
        )
        .unwrap();
        assert_eq!(c.projection, Projection::Orthographic { height: 5.0 });
        // up defaults to +z.
        let c = Camera::from_json(
            r#"{"projection": {"type": "perspective", "fov_y_deg": 30}, "eye": [0, -9, 0], "target": [0, 0, 0]}"#,
        )
        .unwrap();
        assert_eq!(c.up, [0.0, 0.0, 1.0]);
    }

    #[test]
    fn camera_files_keep_a_slices_plane() {
        let cam = Camera::fit_plane(
            [150.5, 185.0, 158.0],
            [75.25, 92.5, 31.75],
            [1.0, 0.3, 0.2],
            200,
            200,
        );
        let f = CameraFile {
            camera: cam,
            slice_origin: Some([75.25, 92.5, 31.75]),
            slice_normal: Some([1.0, 0.3, 0.2]),
        };
        let s = f.to_json();
        assert!(
            s.contains("\"slice_origin\"") && s.contains("\"slice_normal\""),
            "{s}"
        );
        // The camera's fields first, as Camera::to_json writes them.
        assert!(s.starts_with(cam.to_json().trim_end_matches("\n}")), "{s}");
        let back = CameraFile::from_json(&s).unwrap();
        assert_eq!(back.slice_origin, f.slice_origin);
        assert_eq!(back.slice_normal, f.slice_normal);
        assert!(close(back.camera.eye, cam.eye, 1e-12));
        // Reading the same text twice gives the same numbers.
        assert_eq!(CameraFile::from_json(&s).unwrap(), back);
        // A camera reader takes the file too (the viewer reads them).
        assert!(close(
            Camera::from_json(&s).unwrap().target,
            cam.target,
            1e-12
        ));
        // Files without a plane: none, and written as before.
        let plain = CameraFile {
            camera: cam,
            slice_origin: None,
            slice_normal: None,
        };
        assert_eq!(plain.to_json(), cam.to_json());
        let old = CameraFile::from_json(&cam.to_json()).unwrap();
        assert_eq!((old.slice_origin, old.slice_normal), (None, None));
        // Bad planes name the field.
        let p = r#""projection": {"type": "orthographic", "height": 5}, "eye": [0, 0, 10], "target": [0, 0, 0], "up": [0, 1, 0]"#;
        for (extra, field, msg) in [
            (r#""slice_normal": [0, 0, 0]"#, "`slice_normal`", "non-zero"),
            (r#""slice_normal": [0, 1]"#, "`slice_normal`", "3 numbers"),
            (
                r#""slice_origin": [2e15, 0, 0]"#,
                "`slice_origin`",
                "within ±1e15",
            ),
            (r#""slice_origin": "middle""#, "`slice_origin`", "3 numbers"),
            (r#""slice": [0, 0, 1]"#, "`slice`", "unknown field"),
        ] {
            let json = format!("{{{p}, {extra}}}");
            for e in [
                CameraFile::from_json(&json).unwrap_err().to_string(),
                Camera::from_json(&json).unwrap_err().to_string(),
            ] {
                assert!(e.contains(field) && e.contains(msg), "{json}\n→ {e}");
            }
        }
    }

    #[test]
    fn bad_json_names_the_field() {
        let p = r#""projection": {"type": "perspective", "fov_y_deg": 30}"#;
        let cases = [
            (format!(r#"{{{p}, "target": [0, 0, 0]}}"#), "`eye`", "missing"),
            (format!(r#"{{{p}, "eye": [0, 0], "target": [0, 0, 0]}}"#), "`eye`", "3 numbers"),
            (format!(r#"{{{p}, "eye": [0, "a", 1], "target": [0, 0, 0]}}"#), "`eye`", "3 numbers"),
            (format!(r#"{{{p}, "eye": [0, 0, 1], "target": [0, 0, 1]}}"#), "`target`", "equals eye"),
            (format!(r#"{{{p}, "eye": [0, 0, 1], "target": [0, 0, 0], "up": [0, 0, 2]}}"#), "`up`", "parallel"),
            (format!(r#"{{{p}, "eye": [0, 0, 1], "target": [0, 0, 0], "fov": 3}}"#), "`fov`", "unknown field"),
            (r#"{"projection": {"type": "fisheye"}, "eye": [0, 0, 1], "target": [0, 0, 0]}"#.into(), "`projection.type`", "fisheye"),
            (r#"{"projection": {"type": "perspective", "fov_y_deg": 180}, "eye": [0, 0, 1], "target": [0, 0, 0]}"#.into(), "`projection.fov_y_deg`", "between 0 and 180"),
            (r#"{"projection": {"type": "perspective"}, "eye": [0, 0, 1], "target": [0, 0, 0]}"#.into(), "`projection.fov_y_deg`", "missing"),
            (r#"{"projection": {"type": "orthographic", "height": -1}, "eye": [0, 0, 1], "target": [0, 0, 0]}"#.into(), "`projection.height`", "positive"),
            (r#"{"projection": "perspective", "eye": [0, 0, 1], "target": [0, 0, 0]}"#.into(), "`projection`", "expected an object"),
            (r#"{"projection": {"type": "perspective", "fov_y_deg": 30}, "eye": [0, 0, 1],"#.into(), "", "invalid JSON"),
            ("[1, 2]".into(), "", "expected a JSON object"),
            // Far apart: the distance overflowed to infinity, the tests of
            // the direction compared NaN, and rays had none (renders hung).
            (format!(r#"{{{p}, "eye": [1e308, 0, 0], "target": [-1e308, 0, 0]}}"#), "`eye`", "within ±1e15"),
            (format!(r#"{{{p}, "eye": [1e154, 0, 0], "target": [0, 0, 0]}}"#), "`eye`", "within ±1e15"),
            (format!(r#"{{{p}, "eye": [0, 0, 1], "target": [0, -2e15, 0]}}"#), "`target`", "within ±1e15"),
            (format!(r#"{{{p}, "eye": [0, 0, 1], "target": [0, 0, 0], "up": [1e300, 0, 0]}}"#), "`up`", "within ±1e15"),
        ];
        for (json, field, msg) in cases {
            let e = Camera::from_json(&json).unwrap_err().to_string();
            assert!(e.starts_with("camera: "), "{e}");
            assert!(e.contains(field) && e.contains(msg), "{json}\n→ {e}");
            // The serde path gives the same message.
            if let Ok(v) = serde_json::from_str::<Value>(&json) {
                let e2 = serde_json::from_value::<Camera>(v).unwrap_err().to_string();
                assert!(e2.contains(msg), "{e2}");
            }
        }
    }
}
