//! What a 3D view shows at a pixel, for a readout: the point along the
//! pixel's ray that its picture comes from. MIP: the greatest sample; DVR:
//! the first sample where the opacity gathered reaches one half; a label
//! image's surfaces: the first label drawn. The walk reads through a
//! sampler the caller gives (the viewer's readers of the store, the web
//! client's resident bricks), at the levels the view draws along the ray.

use crate::cpu::Lod;
use crate::params::LabelSelect;
use crate::reference::{RenderMode, RenderParams};
use brickyard_core::camera::{intersect_box, length, Camera, Ray, Vec3};
use brickyard_core::{Dims3, TransferFunction};

/// How a view chose levels along its pixels' rays: its camera, its
/// frame's height and the level of detail it was drawn with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drawn {
    pub camera: Camera,
    pub height: u32,
    pub lod: Lod,
}

impl Drawn {
    /// The level drawn at distance `t` along a ray of a volume of `levels`
    /// levels whose level-0 voxel is `voxel0` (as the renderers choose).
    pub fn level(&self, t: f64, voxel0: f64, levels: usize) -> usize {
        let fp = self.camera.pixel_footprint(t, self.height);
        self.lod.level_for(fp, voxel0, levels)
    }
}

/// What a 3D view draws along its pixels' rays.
#[derive(Clone, Debug, PartialEq)]
pub enum Look {
    /// MIP of one channel: the sample of greatest value.
    Mip { channel: usize },
    /// DVR: the first sample where the opacity gathered along the ray
    /// reaches one half, through each channel's transfer function (several
    /// channels: their opacities combined), at `samples` per voxel of the
    /// level drawn, opacities corrected to steps of `reference` (`None`:
    /// a voxel of the level drawn, as [`crate::RenderParams::reference_step`]).
    Dvr {
        tfs: Vec<(usize, TransferFunction)>,
        samples: f64,
        reference: Option<f64>,
    },
    /// A label image's surfaces: the first label drawn.
    Labels(Option<LabelSelect>),
}

impl Look {
    /// What a view drawing `p` looks for along its rays (`channel`: the
    /// channel a DVR of one channel shows): `None` for slices and several
    /// views at once.
    pub fn of(p: &RenderParams, channel: usize) -> Option<Look> {
        if p.views.is_some() {
            return None;
        }
        Some(match p.mode {
            RenderMode::Mip => Look::Mip {
                // (Several channels: the first shown.)
                channel: p.channels.first().map_or(channel, |s| s.channel),
            },
            RenderMode::Dvr if p.labels => Look::Labels(p.label_select.clone()),
            RenderMode::Dvr => Look::Dvr {
                tfs: match p.channels.is_empty() {
                    true => vec![(channel, p.tf.clone())],
                    false => p.channels.iter().map(|s| (s.channel, s.dvr_tf())).collect(),
                },
                samples: p.samples_per_voxel,
                reference: p.reference_step,
            },
            _ => return None,
        })
    }

    /// The channel whose value the point is read from first (a label
    /// image's: 0).
    pub fn first_channel(&self) -> usize {
        match self {
            Look::Mip { channel } => *channel,
            Look::Dvr { tfs, .. } => tfs.first().map_or(0, |t| t.0),
            Look::Labels(_) => 0,
        }
    }

    /// How the point is found, for readouts.
    pub fn name(&self) -> &'static str {
        match self {
            Look::Mip { .. } => "the MIP's maximum",
            Look::Dvr { .. } => "the DVR's half-opacity point",
            Look::Labels(_) => "the first label drawn",
        }
    }
}

/// A label image's stored value as a label (0 for what is no label).
pub fn label_id(v: f64) -> u64 {
    let id = (v + 0.5).floor();
    if id >= 1.0 {
        id as u64
    } else {
        0
    }
}

/// The smallest voxel edge of level `l` of a pyramid of sizes `dims`
/// (`[z, y, x]`) over `extent` (`[X, Y, Z]`): the extent over the level's
/// [`level_span`](brickyard_core::level_span).
pub fn voxel_edge(dims: &[Dims3], l: usize, extent: Vec3) -> f64 {
    let s = brickyard_core::level_span(dims, l);
    [0, 1, 2]
        .map(|a| extent[a] / s[2 - a])
        .into_iter()
        .fold(f64::INFINITY, f64::min)
}

/// The point a 3D view (`drawn`, drawing `look`) shows along its pixel's
/// `ray` through a volume spanning `extent` whose levels have the sizes
/// `dims`: its world position, the level drawn there and the value read
/// (`None`: nothing drawn along it). Steps from where the ray enters the
/// volume, each reading `sample(level, world point, channel)` (`None`:
/// nothing there to read, passed over) at the level the view draws at that
/// distance: half a voxel of that level long (MIP: a quarter, as a maximum
/// may lie in a voxel the ray only grazes), or the DVR's own sampling rate;
/// the first half a step in, or half-way through a shorter chord.
pub fn seen_point<E>(
    ray: &Ray,
    extent: Vec3,
    dims: &[Dims3],
    drawn: &Drawn,
    look: &Look,
    mut sample: impl FnMut(usize, Vec3, usize) -> Result<Option<f64>, E>,
) -> Result<Option<(Vec3, usize, f64)>, E> {
    let Some((t0, t1)) = intersect_box(ray, [0.0; 3], extent) else {
        return Ok(None);
    };
    let edge: Vec<f64> = (0..dims.len())
        .map(|l| voxel_edge(dims, l, extent))
        .collect();
    let (voxel0, levels) = (edge[0], dims.len());
    let per_voxel = match look {
        Look::Dvr { samples, .. } => samples.max(0.25),
        Look::Mip { .. } => 4.0,
        Look::Labels(_) => 2.0,
    };
    let (mut t, mut first) = (t0, true);
    // DVR: the opacity gathered; MIP: the greatest sample.
    let mut gathered = 0.0;
    let mut best: Option<(f64, Vec3, usize)> = None;
    loop {
        let level = drawn.level(t, voxel0, levels);
        let dt = edge[level] / per_voxel / length(ray.dir);
        if first {
            t = (t0 + 0.5 * dt).min(0.5 * (t0 + t1));
            first = false;
        }
        if t >= t1 {
            break;
        }
        let w = ray.at(t);
        match look {
            Look::Mip { channel } => {
                if let Some(x) = sample(level, w, *channel)? {
                    if best.is_none_or(|b| x > b.0) {
                        best = Some((x, w, level));
                    }
                }
            }
            Look::Dvr { tfs, reference, .. } => {
                // The channels' opacities combined, corrected to this
                // step's length.
                let mut through = 1.0;
                let mut first_value = None;
                for (c, tf) in tfs {
                    if let Some(x) = sample(level, w, *c)? {
                        first_value.get_or_insert(x);
                        through *= 1.0 - tf.lookup(x as f32)[3].clamp(0.0, 1.0) as f64;
                    }
                }
                let r = reference.unwrap_or(edge[level]);
                let a = 1.0 - through.powf(dt * length(ray.dir) / r);
                gathered += (1.0 - gathered) * a;
                if gathered >= 0.5 {
                    return Ok(Some((w, level, first_value.unwrap_or(0.0))));
                }
            }
            Look::Labels(select) => {
                if let Some(x) = sample(level, w, 0)? {
                    let id = label_id(x);
                    if id != 0 && select.as_ref().is_none_or(|s| s.shows(id as i32)) {
                        return Ok(Some((w, level, x)));
                    }
                }
            }
        }
        t += dt;
    }
    Ok(best.map(|(x, w, l)| (w, l, x)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::camera::Projection;

    /// A ray along +x through a 16 × 4 × 4 volume of unit voxels whose
    /// value is `f(x)`, sampled at level 0 (one level).
    fn along_x(look: &Look, f: impl Fn(f64) -> Option<f64>) -> Option<(Vec3, usize, f64)> {
        let ray = Ray {
            origin: [-5.0, 2.0, 2.0],
            dir: [1.0, 0.0, 0.0],
        };
        let camera = Camera::look_at(
            [-5.0, 2.0, 2.0],
            [0.0, 2.0, 2.0],
            [0.0, 0.0, 1.0],
            Projection::Orthographic { height: 4.0 },
        );
        let drawn = Drawn {
            camera,
            height: 4,
            lod: Lod::Fixed(0),
        };
        seen_point::<()>(
            &ray,
            [16.0, 4.0, 4.0],
            &[[4, 4, 16]],
            &drawn,
            look,
            |l, w, _| {
                assert_eq!(l, 0);
                Ok(f(w[0].floor()))
            },
        )
        .unwrap()
    }

    #[test]
    fn the_mip_point_is_the_greatest_sample_and_the_labels_the_first_drawn() {
        let peak = |x: f64| Some(if x == 11.0 { 9.0 } else { x.min(5.0) });
        let (w, _, v) = along_x(&Look::Mip { channel: 0 }, peak).unwrap();
        assert_eq!((w[0].floor(), v), (11.0, 9.0));
        // Labels 3 from x = 6, 4 from x = 9: the first drawn of a selection.
        let labels = |x: f64| {
            Some(if x >= 9.0 {
                4.0
            } else if x >= 6.0 {
                3.0
            } else {
                0.0
            })
        };
        let (w, _, v) = along_x(&Look::Labels(None), labels).unwrap();
        assert_eq!((w[0].floor(), v), (6.0, 3.0));
        let only_4 = Some(LabelSelect::new(vec![4], false));
        let (w, _, v) = along_x(&Look::Labels(only_4), labels).unwrap();
        assert_eq!((w[0].floor(), v), (9.0, 4.0));
        // Nothing there to read: nothing found.
        assert!(along_x(&Look::Mip { channel: 0 }, |_| None).is_none());
    }

    #[test]
    fn the_dvr_point_is_where_the_opacity_gathered_reaches_one_half() {
        // Opacity 0 before x = 4, then 0.2 per unit step: 1 − 0.8^k passes
        // 1/2 at the fourth unit voxel (0.59), x = 7.
        let tf = TransferFunction::new(
            [0.0, 1.0],
            vec![[0.0, 0.0], [0.5, 0.0], [0.5001, 0.2], [1.0, 0.2]],
            brickyard_core::transfer::ColorMap::Preset(brickyard_core::transfer::Preset::Grayscale),
        )
        .unwrap();
        let look = Look::Dvr {
            tfs: vec![(0, tf)],
            samples: 1.0,
            reference: None,
        };
        let (w, _, v) = along_x(&look, |x| Some(if x >= 4.0 { 1.0 } else { 0.0 })).unwrap();
        assert_eq!((w[0].floor(), v), (7.0, 1.0));
        // Clear everywhere: nothing.
        assert!(along_x(&look, |_| Some(0.0)).is_none());
    }
}
