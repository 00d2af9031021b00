//! Float RGBA images (premultiplied alpha), PNG output and comparison.

use std::fmt;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// A `width × height` image of premultiplied linear RGBA in `[0, 1]`,
/// row-major, row 0 at the top: pixel `(x, y)` is `rgba[y · width + x]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<[f32; 4]>,
}

/// Writing a PNG failed.
#[derive(Debug)]
pub struct PngError {
    pub path: PathBuf,
    pub message: String,
}

impl fmt::Display for PngError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}: cannot write PNG: {}",
            self.path.display(),
            self.message
        )
    }
}

impl std::error::Error for PngError {}

#[inline]
fn to_u8(v: f32) -> u8 {
    // NaN maps to 0 (`as` saturates and sends NaN to 0).
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Image {
    /// Lay `labels` (a slice of labels: premultiplied, each pixel a
    /// label's opaque colour or clear) over this image at `opacity`: where
    /// a label is, the image keeps `1 − opacity` of itself and takes
    /// `opacity` of the label's colour; elsewhere it is unchanged. The
    /// viewer, the web page and `render --labels` all lay labels so.
    pub fn lay_labels_over(&mut self, labels: &Image, opacity: f32) -> Result<(), String> {
        if (self.width, self.height) != (labels.width, labels.height) {
            return Err(format!(
                "the label image's slice is {}×{}, the image's {}×{}",
                labels.width, labels.height, self.width, self.height
            ));
        }
        for (p, q) in self.rgba.iter_mut().zip(&labels.rgba) {
            let a = opacity * q[3];
            for i in 0..3 {
                p[i] = p[i] * (1.0 - a) + opacity * q[i];
            }
            p[3] = p[3] * (1.0 - a) + a;
        }
        Ok(())
    }

    /// A fully transparent image.
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            rgba: vec![[0.0; 4]; width as usize * height as usize],
        }
    }

    #[inline]
    pub fn get(&self, x: u32, y: u32) -> [f32; 4] {
        self.rgba[y as usize * self.width as usize + x as usize]
    }

    #[inline]
    pub fn set(&mut self, x: u32, y: u32, v: [f32; 4]) {
        self.rgba[y as usize * self.width as usize + x as usize] = v;
    }

    /// 8-bit RGBA (straight alpha, as PNG stores it) of this image composited
    /// over `background` (straight RGBA; alpha 1 gives an opaque image,
    /// `[0, 0, 0, 0]` keeps the image's own transparency). Values are
    /// written as they are (no gamma conversion), clamped to `[0, 1]` and
    /// rounded to the nearest of 0…255.
    pub fn to_rgba8(&self, background: [f32; 4]) -> Vec<u8> {
        let ba = background[3];
        let bg = [
            background[0] * ba,
            background[1] * ba,
            background[2] * ba,
            ba,
        ];
        let mut out = Vec::with_capacity(self.rgba.len() * 4);
        for p in &self.rgba {
            let k = 1.0 - p[3];
            let c = [0, 1, 2, 3].map(|i| p[i] + k * bg[i]);
            let a = c[3];
            if a > 0.0 {
                out.extend_from_slice(&[
                    to_u8(c[0] / a),
                    to_u8(c[1] / a),
                    to_u8(c[2] / a),
                    to_u8(a),
                ]);
            } else {
                out.extend_from_slice(&[0, 0, 0, 0]);
            }
        }
        out
    }

    /// Write the image, over `background` (see [`Image::to_rgba8`]), as an
    /// 8-bit RGBA PNG.
    pub fn write_png(&self, path: &Path, background: [f32; 4]) -> Result<(), PngError> {
        let err = |m: String| PngError {
            path: path.into(),
            message: m,
        };
        let rgba = self.to_rgba8(background);
        write_whole(path, |out| {
            let mut enc = png::Encoder::new(out, self.width, self.height);
            enc.set_color(png::ColorType::Rgba);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header()?;
            w.write_image_data(&rgba)?;
            w.finish()?;
            Ok(())
        })
        .map_err(|e| err(e.to_string()))
    }

    fn check_same_size(&self, other: &Image) {
        assert!(
            self.width == other.width && self.height == other.height,
            "comparing images of different sizes: {}×{} and {}×{}",
            self.width,
            self.height,
            other.width,
            other.height
        );
    }

    /// Largest absolute difference of any channel of any pixel.
    /// Panics when the sizes differ.
    pub fn max_abs_diff(&self, other: &Image) -> f32 {
        self.check_same_size(other);
        self.rgba
            .iter()
            .zip(&other.rgba)
            .flat_map(|(a, b)| (0..4).map(move |i| (a[i] - b[i]).abs()))
            .fold(0.0, f32::max)
    }

    /// Mean absolute difference over all channels of all pixels.
    /// Panics when the sizes differ.
    pub fn mean_abs_diff(&self, other: &Image) -> f64 {
        self.check_same_size(other);
        let n = self.rgba.len() * 4;
        if n == 0 {
            return 0.0;
        }
        let s: f64 = self
            .rgba
            .iter()
            .zip(&other.rgba)
            .flat_map(|(a, b)| (0..4).map(move |i| (a[i] - b[i]).abs() as f64))
            .sum();
        s / n as f64
    }

    /// Peak signal-to-noise ratio in dB over all four channels, peak 1.0:
    /// `10 · log10(1 / MSE)`; infinite for identical images.
    /// Panics when the sizes differ.
    pub fn psnr(&self, other: &Image) -> f64 {
        self.check_same_size(other);
        let n = self.rgba.len() * 4;
        if n == 0 {
            return f64::INFINITY;
        }
        let s: f64 = self
            .rgba
            .iter()
            .zip(&other.rgba)
            .flat_map(|(a, b)| {
                (0..4).map(move |i| {
                    let d = (a[i] - b[i]) as f64;
                    d * d
                })
            })
            .sum();
        let mse = s / n as f64;
        if mse == 0.0 {
            f64::INFINITY
        } else {
            10.0 * (1.0 / mse).log10()
        }
    }

    /// Fraction of pixels whose alpha is at least `threshold`.
    pub fn coverage(&self, threshold: f32) -> f64 {
        if self.rgba.is_empty() {
            return 0.0;
        }
        self.rgba.iter().filter(|p| p[3] >= threshold).count() as f64 / self.rgba.len() as f64
    }
}

/// Write the file at `path` whole or not at all: into a temporary file
/// beside it, then renamed over it, so that a failure (a full disk, a
/// killed process) leaves the file that was there, and never a cut-off
/// one. A path that names something other than a regular file (a device
/// such as `/dev/null` or `/dev/stdout`, a FIFO) is written directly; a
/// symbolic link's target is replaced, not the link.
pub fn write_whole(
    path: &Path,
    write: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
) -> std::io::Result<()> {
    use std::io::Write as _;
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        let mut w = BufWriter::new(File::create(path)?);
        write(&mut w)?;
        return w.flush();
    }
    let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let name = real.file_name().unwrap_or_default().to_string_lossy();
    let tmp = real.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    let r = (|| {
        let mut w = BufWriter::new(File::create(&tmp)?);
        write(&mut w)?;
        w.into_inner().map_err(|e| e.into_error())?.sync_data()?;
        std::fs::rename(&tmp, &real)
    })();
    if r.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::{write_whole, Image};

    /// A write that fails part way (a full disk) leaves the file that was
    /// there, whole, and nothing beside it; one that succeeds replaces it.
    #[test]
    fn a_failed_write_leaves_the_old_file() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("r.png");
        std::fs::write(&p, b"the old image").unwrap();
        let e = write_whole(&p, |w| {
            w.write_all(b"half of a new")?;
            Err(std::io::Error::other("no space left"))
        });
        assert!(e.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"the old image");
        let names: Vec<_> = std::fs::read_dir(d.path()).unwrap().flatten().collect();
        assert_eq!(names.len(), 1, "left beside it: {names:?}");
        write_whole(&p, |w| w.write_all(b"new")).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        // Through a link: the target is replaced, the link stays.
        let link = d.path().join("link.png");
        std::os::unix::fs::symlink(&p, &link).unwrap();
        write_whole(&link, |w| w.write_all(b"via the link")).unwrap();
        assert!(link.symlink_metadata().unwrap().file_type().is_symlink());
        assert_eq!(std::fs::read(&p).unwrap(), b"via the link");
        // A device is written to, not replaced.
        Image::new(4, 4)
            .write_png(std::path::Path::new("/dev/null"), [0.0; 4])
            .unwrap();
        use std::os::unix::fs::FileTypeExt;
        assert!(std::fs::metadata("/dev/null")
            .unwrap()
            .file_type()
            .is_char_device());
    }
}
