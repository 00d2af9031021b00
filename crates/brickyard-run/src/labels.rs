//! Label images drawn over a slice (`render --labels NAME`): the store's
//! `labels/NAME` must lie on the image's grid, and its slice, in the
//! labels' colours, is laid over the image's at an opacity.

use anyhow::{bail, Context, Result};
use brickyard_render::Image;
use brickyard_store::import::zarr;
use brickyard_store::omezarr::label_names;
use brickyard_store::VolumeSource;
use std::path::{Path, PathBuf};

/// The folder of the store's label image `name`, once the store lists it
/// and its level 0 has the image's voxels, spacing and origin, in the same
/// unit (the same world box: one camera shows both the same).
pub fn label_store(store: &Path, name: &str) -> Result<PathBuf> {
    if name.is_empty() || name == "." || name == ".." || name.contains(['/', '\\']) {
        bail!("labels: expected the name of one of the store's label images (labels/NAME), found {name:?}");
    }
    let names = label_names(store)?;
    if !names.iter().any(|n| n == name) {
        bail!(
            "labels: {} has no label image {name:?} ({}); processing it with a pipeline that \
             ends in label(...) writes one",
            store.display(),
            match names.is_empty() {
                true => "it has none".to_string(),
                false => format!("it has {}", names.join(", ")),
            }
        );
    }
    let dir = store.join("labels").join(name);
    let image = zarr::open(store, 0)?.meta().clone();
    let labels = zarr::open(&dir, 0)?.meta().clone();
    if let Err(how) = image.same_grid(&labels) {
        bail!(
            "{}: its level 0 is {how}, the image's: label images are drawn over the grid they \
             were made on (the same voxels, spacing, origin and unit)",
            dir.display(),
        );
    }
    if labels.channels > 1 {
        bail!(
            "{}: a label image has one channel, this one {}",
            dir.display(),
            labels.channels
        );
    }
    Ok(dir)
}

/// The `labels` group of an image that a conversion into `output` writes
/// into (`IMAGE/labels/NAME`), if any: such an output must be a label
/// image (`labels`), else an error says so.
pub fn label_target(output: &Path, labels: bool) -> Result<Option<PathBuf>> {
    let group = crate::process::label_group_of(output);
    if let (Some(g), false) = (&group, labels) {
        bail!(
            "{}: lies in {}, the label images of an image: give --labels (labels=True in \
             Python; coarser levels then take the mode of the labels, not their mean, and the \
             image lists it), or write it elsewhere",
            output.display(),
            g.display()
        );
    }
    Ok(group)
}

/// An image's `labels` group made (if missing) for a label image about to
/// be written into it: [`undo`](Self::undo) takes it back when that fails
/// and the group is still empty (an interrupted conversion left an empty
/// `labels` folder in a store that had none).
pub struct LabelGroup {
    made: Option<PathBuf>,
}

impl LabelGroup {
    /// `group` made when missing.
    pub fn make(group: &Path) -> Result<LabelGroup> {
        let made = (!group.exists()).then(|| group.to_path_buf());
        std::fs::create_dir_all(group)
            .with_context(|| format!("{}: cannot create", group.display()))?;
        Ok(LabelGroup { made })
    }

    /// The write failed: the group goes if this made it and nothing is in
    /// it.
    pub fn undo(self) {
        if let Some(g) = self.made {
            let _ = std::fs::remove_dir(g);
        }
    }
}

/// The image's geometry (`[z, y, x]` spacing, origin, and unit) that
/// labels of `labels` (a source's description) written into its group
/// `group` take: a segmentation saved without geometry on the image's grid
/// lies over it that way. `None`: the labels keep their own (they have
/// some, or lie on another grid).
pub type Geometry = (Option<[f64; 3]>, Option<[f64; 3]>, Option<String>);

/// See [`Geometry`].
pub fn inherited_geometry(
    group: &Path,
    labels: &brickyard_store::SourceMeta,
) -> Result<Option<Geometry>> {
    // (A label image that cannot be one is refused before its group is
    // made.)
    brickyard_store::builder::check_labels(group, labels, true)?;
    let image = group.parent().unwrap_or(group);
    let im = zarr::open(image, 0)?.meta().clone();
    let plain = labels.spacing.is_none() && labels.origin.is_none();
    Ok((plain && im.dims == labels.dims && im.spacing.is_some())
        .then(|| (im.spacing, im.origin, im.unit.clone())))
}

/// What [`finish_label_image`] did not do, for the report: why no
/// statistics table was written, and how the label image lies off its
/// image's grid (it is listed, but not drawn over the image).
#[derive(Debug, Default)]
pub struct LabelImageNotes {
    pub no_table: Option<String>,
    pub off_grid: Option<String>,
}

/// What follows the conversion of a label image into `output`: in an
/// image's `group`, it is marked as the image's and listed; its statistics
/// table is written from its voxels (with the image's means when on its
/// grid), in at most `max_bytes`. The notes say what was not done (the
/// label image stays usable).
pub fn finish_label_image(
    output: &Path,
    group: Option<&Path>,
    max_bytes: u64,
    progress: &dyn brickyard_store::Progress,
    cancel: &std::sync::atomic::AtomicBool,
) -> Result<LabelImageNotes> {
    let mut notes = LabelImageNotes::default();
    if let Some(g) = group {
        crate::process::publish_label_image(g, output)?;
    }
    let image = group.and_then(Path::parent);
    if let Some(im) = image {
        let (a, b) = (zarr::open(im, 0)?, zarr::open(output, 0)?);
        if let Err(how) = a.meta().same_grid(b.meta()) {
            notes.off_grid = Some(format!(
                "it is listed, but drawn over the image (render --labels) and given the \
                 image's mean intensities only on the image's grid: its level 0 is {how}, the \
                 image's"
            ));
        }
    }
    notes.no_table =
        crate::label_stats::write_from_voxels(output, image, max_bytes, progress, cancel)?;
    Ok(notes)
}

/// Lay `labels` (a slice of labels) over `img` at `opacity`
/// ([`Image::lay_labels_over`]).
pub fn overlay(img: &mut Image, labels: &Image, opacity: f32) -> Result<()> {
    img.lay_labels_over(labels, opacity)
        .map_err(|e| anyhow::anyhow!("labels: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_lie_over_the_image_at_their_opacity() {
        let img = |px: Vec<[f32; 4]>| Image {
            width: px.len() as u32,
            height: 1,
            rgba: px,
        };
        // Grey image; a red label on the first pixel, clear on the second;
        // the third pixel outside the image's slice (clear) under a label.
        let mut base = img(vec![
            [0.5, 0.5, 0.5, 1.0],
            [0.25, 0.25, 0.25, 1.0],
            [0.0; 4],
        ]);
        let lab = img(vec![[1.0, 0.0, 0.0, 1.0], [0.0; 4], [0.0, 0.0, 1.0, 1.0]]);
        overlay(&mut base, &lab, 0.25).unwrap();
        assert_eq!(base.rgba[0], [0.625, 0.375, 0.375, 1.0]);
        assert_eq!(base.rgba[1], [0.25, 0.25, 0.25, 1.0]);
        assert_eq!(base.rgba[2], [0.0, 0.0, 0.25, 0.25]);
        // Opacity 1: the label's colour alone.
        let mut base = img(vec![[0.5, 0.5, 0.5, 1.0]]);
        overlay(&mut base, &img(vec![[0.0, 1.0, 0.0, 1.0]]), 1.0).unwrap();
        assert_eq!(base.rgba[0], [0.0, 1.0, 0.0, 1.0]);
        // Sizes must agree.
        let e = overlay(&mut base, &lab, 0.5).unwrap_err().to_string();
        assert!(e.contains("3×1") && e.contains("1×1"), "{e}");
    }
}
