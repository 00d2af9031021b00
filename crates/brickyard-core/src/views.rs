//! Several views of one scene side by side in one image: stereo pairs and
//! the N views of multi-view (autostereoscopic) displays.
//!
//! A render of `count` views draws an image `count` views wide: view `v`
//! takes the columns `v·w … (v+1)·w − 1` of an image `count·w` wide, so
//! that one frame of the virtual memory, one request list and one
//! completeness figure cover all of them.
//!
//! - **Cameras** (DVR, MIP): view `v` is the camera moved
//!   `(v − (count−1)/2)·separation` along its right vector, with its
//!   frustum shifted so that the plane through the target looks the same
//!   in every view (off-axis, parallel frusta; see
//!   [`RayGen::shifted_ray`]). With two views, view 0 is the left eye.
//! - **Super-slices** (slices): view `v` composites `count` parallel
//!   slices `spacing` apart, the reference slice `count/2` being the plane
//!   itself and slice `k` lying `(k − count/2)·spacing` towards the camera.
//!   In view `v`, slice `k` is seen shifted `parallax·(v − (count−1)/2)·
//!   (k − count/2)` pixels along the image's x: no shift on the reference
//!   slice, opposite shifts in front of and behind it, growing from one
//!   view to the next.

use crate::camera::{length, sub, Camera, Ray, RayGen};
use crate::ConfigError;
use serde::{Deserialize, Serialize};

/// Most views one image holds.
pub const MAX_VIEWS: u32 = 16;

/// The farthest a super-slice's slice may shift in pixels (`parallax`
/// times the views' and slices' reach): its layers span the shifts.
pub const MAX_SHIFT: f64 = 4096.0;

/// How many views, and how they differ.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Views {
    /// Views side by side (2 ≤ count ≤ [`MAX_VIEWS`]).
    pub count: u32,
    /// Cameras: world distance between neighbouring eyes.
    #[serde(default)]
    pub separation: f64,
    /// Super-slices: pixels of shift between neighbouring views, per
    /// slice away from the reference slice.
    #[serde(default)]
    pub parallax: f64,
    /// Super-slices: world distance between neighbouring slices.
    #[serde(default)]
    pub spacing: f64,
    /// Draw this view alone: the image is one view wide (e.g. to spread
    /// the views over several renderers, or to time one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alone: Option<u32>,
}

impl Views {
    /// Check the fields, for an image `width` pixels wide.
    pub fn validate(&self, width: u32) -> Result<(), ConfigError> {
        let bad = |f: &str, m: String| Err(ConfigError::new("views", f, m));
        if !(2..=MAX_VIEWS).contains(&self.count) {
            return bad(
                "count",
                format!("needs 2 to {MAX_VIEWS} views, got {}", self.count),
            );
        }
        if let Some(v) = self.alone {
            if v >= self.count {
                return bad(
                    "alone",
                    format!("view {v} of {} views does not exist", self.count),
                );
            }
        } else if !width.is_multiple_of(self.count) {
            return bad(
                "count",
                format!(
                    "the image ({width} pixels wide) must hold {} views of equal width",
                    self.count
                ),
            );
        }
        for (f, x) in [
            ("separation", self.separation),
            ("parallax", self.parallax),
            ("spacing", self.spacing),
        ] {
            if !x.is_finite() {
                return bad(f, format!("must be finite, got {x}"));
            }
        }
        if self.spacing < 0.0 {
            return bad(
                "spacing",
                format!("must be 0 or more, got {}", self.spacing),
            );
        }
        // A super-slice's layers span its slices' shifts: memory and time
        // grow with them (a parallax of 1e9 took 16 GB; 1e30 indexed out
        // of bounds), so the farthest shift is at most MAX_SHIFT pixels.
        let reach = (self.count as f64 - 1.0) * 0.5 * (self.count / 2) as f64;
        if self.parallax.abs() * reach > MAX_SHIFT {
            return bad(
                "parallax",
                format!(
                    "shifts a slice by up to {:e} pixels, more than {MAX_SHIFT}: at most {} pixels with {} views",
                    self.parallax.abs() * reach,
                    (MAX_SHIFT / reach * 100.0).floor() / 100.0,
                    self.count
                ),
            );
        }
        Ok(())
    }

    /// View `v`'s position from the middle of the row, in neighbour steps:
    /// `v − (count − 1)/2`.
    pub fn offset(&self, v: u32) -> f64 {
        v as f64 - (self.count as f64 - 1.0) * 0.5
    }

    /// The reference slice of a super-slice: `count / 2`.
    pub fn reference_slice(&self) -> u32 {
        self.count / 2
    }

    /// The views an image holds: all, or the one drawn alone.
    pub fn drawn(&self) -> std::ops::Range<u32> {
        match self.alone {
            Some(v) => v..v + 1,
            None => 0..self.count,
        }
    }

    /// Views side by side in the image: 1 when one is drawn alone.
    pub fn columns(&self) -> u32 {
        if self.alone.is_some() {
            1
        } else {
            self.count
        }
    }

    /// Slice `k`'s distance from the reference slice, towards the camera.
    pub fn slice_depth(&self, k: u32) -> f64 {
        (k as f64 - self.reference_slice() as f64) * self.spacing
    }

    /// Pixels slice `k` is shifted by in view `v` (along the image's x).
    pub fn slice_shift(&self, v: u32, k: u32) -> f64 {
        self.parallax * self.offset(v) * (k as f64 - self.reference_slice() as f64)
    }
}

/// The rays of an image of several views (or of one, `views = None`): the
/// pixel columns of view `v` are `v·w … (v+1)·w − 1`, `w` the view width.
#[derive(Debug, Clone, Copy)]
pub struct ViewRays {
    gen: RayGen,
    count: u32,
    /// The first view of the image (a view drawn alone).
    first: u32,
    view_width: u32,
    separation: f64,
    distance: f64,
    offset0: f64,
}

impl ViewRays {
    /// Rays of `camera` for an image `width × height` holding `views`
    /// (assumed valid, [`Views::validate`]).
    pub fn new(camera: &Camera, views: Option<&Views>, width: u32, height: u32) -> ViewRays {
        let count = views.map_or(1, |v| v.count).max(1);
        let view_width = width / views.map_or(1, |v| v.columns()).max(1);
        ViewRays {
            gen: camera.ray_gen(view_width, height),
            count,
            first: views.and_then(|v| v.alone).unwrap_or(0),
            view_width,
            separation: views.map_or(0.0, |v| v.separation),
            distance: length(sub(camera.target, camera.eye)),
            offset0: -(count as f64 - 1.0) * 0.5,
        }
    }

    /// Width of one view in pixels.
    pub fn view_width(&self) -> u32 {
        self.view_width
    }

    /// The view of pixel column `i` and the column within it.
    #[inline]
    pub fn view_of(&self, i: u32) -> (u32, u32) {
        let v = (i / self.view_width).min(self.count - 1 - self.first);
        (self.first + v, i - v * self.view_width)
    }

    /// The ray of view `v` through its continuous position `(px, py)`.
    #[inline]
    pub fn ray(&self, v: u32, px: f64, py: f64) -> Ray {
        let shift = (v as f64 + self.offset0) * self.separation;
        self.gen.shifted_ray(px, py, shift, self.distance)
    }

    /// The one view's ray generator when there is one view (pixel `(i,
    /// j)`'s ray is then its [`RayGen::pixel_ray`]).
    #[inline]
    pub fn single(&self) -> Option<&RayGen> {
        (self.count == 1).then_some(&self.gen)
    }

    /// The ray through the centre of pixel `(i, j)` of the whole image.
    #[inline]
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        if self.count == 1 {
            return self.gen.pixel_ray(i, j);
        }
        let (v, x) = self.view_of(i);
        self.ray(v, x as f64 + 0.5, j as f64 + 0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{dot, Projection};

    fn views(count: u32, separation: f64) -> Views {
        Views {
            count,
            separation,
            parallax: 0.0,
            spacing: 0.0,
            alone: None,
        }
    }

    /// Off-axis stereo: the eyes sit apart along the camera's right vector
    /// and see the target plane alike; points off that plane show
    /// horizontal parallax only, crossed in front of it and uncrossed
    /// behind.
    #[test]
    fn off_axis_views_agree_on_the_target_plane_only() {
        for projection in [
            Projection::Perspective { fov_y_deg: 40.0 },
            Projection::Orthographic { height: 3.0 },
        ] {
            let cam = Camera::look_at([0.0, -5.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0], projection);
            let v = views(2, 0.4);
            let vr = ViewRays::new(&cam, Some(&v), 200, 80);
            assert_eq!(vr.view_width(), 100);
            let (l, r) = (vr.pixel_ray(30, 20), vr.pixel_ray(130, 20));
            let right = cam.basis().right;
            assert!((dot(sub(r.origin, l.origin), right) - 0.4).abs() < 1e-12);
            // Both rays meet the target plane (y = 0) at one point.
            let hit = |ray: &Ray, y: f64| {
                let t = (y - ray.origin[1]) / ray.dir[1];
                ray.at(t)
            };
            let (a, b) = (hit(&l, 0.0), hit(&r, 0.0));
            assert!(length(sub(a, b)) < 1e-12, "{a:?} {b:?}");
            // The rays of one pixel cross on the plane: in front of it the
            // left eye's ray lies to the left, behind it to the right, at
            // the same height (horizontal parallax only).
            let (a, b) = (hit(&l, -1.0), hit(&r, -1.0));
            assert!(a[0] < b[0] && (a[2] - b[2]).abs() < 1e-12);
            let (a, b) = (hit(&l, 1.0), hit(&r, 1.0));
            assert!(a[0] > b[0]);
        }
    }

    #[test]
    fn one_view_is_the_camera_itself() {
        let cam = Camera::look_at(
            [1.0, -5.0, 2.0],
            [0.0; 3],
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y_deg: 30.0 },
        );
        let vr = ViewRays::new(&cam, None, 64, 48);
        let rg = cam.ray_gen(64, 48);
        for (i, j) in [(0, 0), (13, 40), (63, 47)] {
            let (a, b) = (vr.pixel_ray(i, j), rg.pixel_ray(i, j));
            assert_eq!((a.origin, a.dir), (b.origin, b.dir));
        }
        // The middle view of an odd count is the camera too.
        let vr = ViewRays::new(&cam, Some(&views(3, 0.5)), 192, 48);
        let (a, b) = (vr.pixel_ray(64 + 13, 40), rg.pixel_ray(13, 40));
        assert_eq!((a.origin, a.dir), (b.origin, b.dir));
    }

    #[test]
    fn a_view_drawn_alone_is_that_view_of_the_whole() {
        let cam = Camera::look_at(
            [1.0, -5.0, 2.0],
            [0.0; 3],
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y_deg: 30.0 },
        );
        let all = views(4, 0.3);
        let whole = ViewRays::new(&cam, Some(&all), 4 * 32, 24);
        let one = Views {
            alone: Some(2),
            ..all
        };
        assert!(one.validate(32).is_ok());
        assert!(Views {
            alone: Some(4),
            ..all
        }
        .validate(32)
        .is_err());
        let alone = ViewRays::new(&cam, Some(&one), 32, 24);
        for (i, j) in [(0, 0), (17, 9), (31, 23)] {
            let (a, b) = (alone.pixel_ray(i, j), whole.pixel_ray(2 * 32 + i, j));
            assert_eq!((a.origin, a.dir), (b.origin, b.dir));
        }
    }

    #[test]
    fn super_slice_shifts_follow_depth_and_view() {
        let v = Views {
            count: 8,
            separation: 0.0,
            parallax: 4.0,
            spacing: 1.0,
            alone: None,
        };
        assert_eq!(v.reference_slice(), 4);
        assert_eq!(v.slice_shift(0, 4), 0.0);
        assert_eq!(v.slice_shift(7, 4), 0.0);
        assert_eq!(v.slice_shift(0, 0), 4.0 * -3.5 * -4.0);
        assert_eq!(v.slice_shift(7, 7), 4.0 * 3.5 * 3.0);
        assert_eq!(v.slice_depth(0), -4.0);
        assert_eq!(v.slice_depth(7), 3.0);
    }

    #[test]
    fn bad_views_are_refused_with_the_field() {
        let e = views(1, 0.1).validate(64).unwrap_err().to_string();
        assert!(e.contains("count") && e.contains("got 1"), "{e}");
        let e = views(3, 0.1).validate(64).unwrap_err().to_string();
        assert!(e.contains("64 pixels wide"), "{e}");
        let e = views(2, f64::NAN).validate(64).unwrap_err().to_string();
        assert!(e.contains("separation"), "{e}");
        assert!(views(2, 0.1).validate(64).is_ok());
    }
}
