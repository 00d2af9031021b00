//! The product renderers' optics: what a sample's value becomes on screen.
//! Transfer-function application (MIP and slice colours), opacity
//! correction for the step length, front-to-back compositing with early
//! termination, and the additive mix of several channels. The CPU modes
//! (`dvr`, `mip`, `slice`) call these; `optics.wgsl` is the device twin.
//! The in-core reference has its own implementation of the same rules.

use crate::params::ChannelStyle;
use brickyard_core::TransferFunction;

/// DVR stops a ray once its accumulated opacity reaches this.
pub const EARLY_TERMINATION: f32 = 0.99;

/// Opacity for a step of `exponent = Δ/Δ_ref` reference steps:
/// `1 − (1 − α)^exponent` (exactly `α` when the exponent is 1).
#[inline]
pub fn correct_opacity(alpha: f32, exponent: f32) -> f32 {
    if exponent == 1.0 {
        alpha
    } else if exponent == exponent.trunc() && exponent.abs() <= 64.0 {
        // Whole exponents (a level 2^l coarser than the reference step)
        // by multiplication: much cheaper than a general power.
        1.0 - (1.0 - alpha).powi(exponent as i32)
    } else {
        1.0 - (1.0 - alpha).powf(exponent)
    }
}

/// Front-to-back compositing of one sample of straight-alpha colour `c`
/// (opacity corrected by `exponent`) into the premultiplied `acc`.
/// Returns true when the ray is opaque enough to stop.
#[inline]
pub fn composite(acc: &mut [f32; 4], c: [f32; 4], exponent: f32) -> bool {
    if c[3] <= 0.0 {
        return false;
    }
    composite_visible(acc, c, exponent)
}

/// [`composite`] for a sample known to have positive opacity.
#[inline(always)]
pub fn composite_visible(acc: &mut [f32; 4], c: [f32; 4], exponent: f32) -> bool {
    let a = correct_opacity(c[3], exponent);
    let wgt = (1.0 - acc[3]) * a;
    acc[0] += wgt * c[0];
    acc[1] += wgt * c[1];
    acc[2] += wgt * c[2];
    acc[3] += wgt;
    acc[3] >= EARLY_TERMINATION
}

/// The pixel of a MIP ray: the transfer function's colour of the maximum,
/// opaque where the ray took a sample.
#[inline]
pub fn mip_color(tf: &TransferFunction, hit: bool, best: f32) -> [f32; 4] {
    if !hit || best.is_nan() {
        return if hit { [0.0, 0.0, 0.0, 1.0] } else { [0.0; 4] };
    }
    let c = tf.lookup(best);
    [c[0], c[1], c[2], 1.0]
}

/// The pixel of a slice of one channel: the transfer function's colour of
/// the value, opaque; transparent where nothing served the sample or the
/// value is NaN.
#[inline]
pub fn slice_color(tf: &TransferFunction, value: Option<f32>) -> [f32; 4] {
    match value {
        Some(v) if !v.is_nan() => {
            let c = tf.lookup(v);
            [c[0], c[1], c[2], 1.0]
        }
        _ => [0.0; 4],
    }
}

/// Intensity of `value` for a channel shown with `style`: its window
/// mapped to `[0, 1]`, clamped (NaN: 0).
#[inline]
pub fn channel_intensity(style: &ChannelStyle, value: f32) -> f32 {
    let [lo, hi] = style.window;
    let x = ((value - lo) / (hi - lo)).clamp(0.0, 1.0);
    if x.is_nan() {
        0.0
    } else {
        x
    }
}

/// Additive mix of channel intensities: `Σ colour·intensity`, clamped to 1,
/// opaque.
#[inline]
pub fn mix_channels(styles: &[ChannelStyle], values: impl Iterator<Item = f32>) -> [f32; 4] {
    let mut rgb = [0.0f32; 3];
    for (s, v) in styles.iter().zip(values) {
        let i = channel_intensity(s, v);
        for (c, w) in rgb.iter_mut().zip(s.color) {
            *c += w * i;
        }
    }
    [rgb[0].min(1.0), rgb[1].min(1.0), rgb[2].min(1.0), 1.0]
}

/// Each rule against values worked out by hand (not against the
/// reference renderer, which has its own implementation).
#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::transfer::ColorMap;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() <= 1e-6
    }

    #[test]
    fn opacity_correction() {
        // Exponent 1: the opacity itself, bit for bit.
        assert_eq!(correct_opacity(0.3, 1.0), 0.3);
        // Two reference steps at 0.5: 1 − 0.5² = 0.75; three at 0.2:
        // 1 − 0.8³ = 0.488.
        assert!(close(correct_opacity(0.5, 2.0), 0.75));
        assert!(close(correct_opacity(0.2, 3.0), 0.488));
        // Half a step at 0.75: 1 − √0.25 = 0.5; a quarter at 0.9375:
        // 1 − 0.0625^¼ = 0.5.
        assert!(close(correct_opacity(0.75, 0.5), 0.5));
        assert!(close(correct_opacity(0.9375, 0.25), 0.5));
        // Opaque stays opaque, transparent stays transparent.
        assert_eq!(correct_opacity(1.0, 0.5), 1.0);
        assert_eq!(correct_opacity(0.0, 3.0), 0.0);
    }

    #[test]
    fn compositing_front_to_back() {
        let mut acc = [0.0f32; 4];
        // Red at 0.5: C = 0.5·(1, 0, 0), A = 0.5.
        assert!(!composite(&mut acc, [1.0, 0.0, 0.0, 0.5], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.0, 0.5]);
        // Blue at 0.5 behind it: weight (1 − 0.5)·0.5 = 0.25.
        assert!(!composite(&mut acc, [0.0, 0.0, 1.0, 0.5], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.25, 0.75]);
        // A transparent sample changes nothing.
        assert!(!composite(&mut acc, [0.0, 1.0, 0.0, 0.0], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.25, 0.75]);
        // Green at 0.5 over two reference steps: α' = 0.75, weight
        // 0.25·0.75 = 0.1875, A = 0.9375.
        assert!(!composite(&mut acc, [0.0, 1.0, 0.0, 0.5], 2.0));
        assert!(close(acc[1], 0.1875) && close(acc[3], 0.9375), "{acc:?}");
        // An opaque sample ends the ray: A = 1 ≥ 0.99.
        assert!(composite(&mut acc, [1.0, 1.0, 1.0, 1.0], 1.0));
        assert!(close(acc[3], 1.0) && close(acc[0], 0.5625), "{acc:?}");
    }

    #[test]
    fn early_termination_at_the_threshold() {
        // Alpha 0.5 per step: A = 1 − 0.5ⁿ reaches 0.99 at n = 7 (0.9921875),
        // not at n = 6 (0.984375).
        let mut acc = [0.0f32; 4];
        let mut n = 0;
        loop {
            n += 1;
            if composite(&mut acc, [1.0, 1.0, 1.0, 0.5], 1.0) {
                break;
            }
        }
        assert_eq!(n, 7);
        assert_eq!(acc[3], 0.9921875);
    }

    #[test]
    fn mip_and_slice_colours() {
        // Grey ramp over the window [0, 10], opacity 0 (neither mode uses
        // the opacity).
        let tf = TransferFunction::new(
            [0.0, 10.0],
            vec![[0.0, 0.0]],
            ColorMap::Points(vec![[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]]),
        )
        .unwrap();
        assert_eq!(mip_color(&tf, true, 5.0), [0.5, 0.5, 0.5, 1.0]);
        assert_eq!(mip_color(&tf, true, 20.0), [1.0, 1.0, 1.0, 1.0]);
        // A ray that took only NaN samples is black; one that took none
        // stays transparent.
        assert_eq!(mip_color(&tf, true, f32::NAN), [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(mip_color(&tf, false, 5.0), [0.0; 4]);
        assert_eq!(slice_color(&tf, Some(2.5)), [0.25, 0.25, 0.25, 1.0]);
        assert_eq!(slice_color(&tf, Some(f32::NAN)), [0.0; 4]);
        assert_eq!(slice_color(&tf, None), [0.0; 4]);
    }

    #[test]
    fn channels_add_up() {
        let green = ChannelStyle {
            channel: 0,
            color: [0.0, 1.0, 0.0],
            window: [0.0, 200.0],
            tf: None,
            levels: None,
        };
        let magenta = ChannelStyle {
            channel: 1,
            color: [1.0, 0.0, 1.0],
            window: [100.0, 300.0],
            tf: None,
            levels: None,
        };
        assert_eq!(channel_intensity(&green, 50.0), 0.25);
        assert_eq!(channel_intensity(&green, -5.0), 0.0);
        assert_eq!(channel_intensity(&green, 500.0), 1.0);
        assert_eq!(channel_intensity(&green, f32::NAN), 0.0);
        let styles = [green, magenta];
        // 0.25 green and 0.5 magenta.
        let px = mix_channels(&styles, [50.0, 200.0].into_iter());
        assert_eq!(px, [0.5, 0.25, 0.5, 1.0]);
        // The sum is clamped to 1 per component.
        let both = [
            ChannelStyle {
                color: [0.8, 0.8, 0.0],
                ..styles[0].clone()
            },
            ChannelStyle {
                color: [0.6, 0.0, 0.0],
                ..styles[1].clone()
            },
        ];
        let px = mix_channels(&both, [200.0, 300.0].into_iter());
        assert_eq!(px, [1.0, 0.8, 0.0, 1.0]);
        // No value: black, still opaque.
        let px = mix_channels(&styles, [f32::NAN, f32::NAN].into_iter());
        assert_eq!(px, [0.0, 0.0, 0.0, 1.0]);
    }
}
