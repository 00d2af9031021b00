//! Several inputs of one grid as the channels of one volume: `convert`'s
//! `a.nii.gz b.nii.gz c.nii.gz OUT`. The inputs must agree on shape, voxel
//! type, spacing and origin (where they state them); the first input that
//! does not is named in the error with the field and both values. Channels
//! are the inputs' channels in order, named after the files (or the
//! names a file gives its channels).

use crate::error::{Result, StoreError};
use crate::source::{ChannelDisplay, SourceMeta, VolumeSource};
use brickyard_core::Dims3;
use std::ops::Range;
use std::path::Path;

/// Relative difference up to which two spacings or origins are the same
/// (headers store them as f32 or as decimal text).
const SAME: f64 = 1e-5;

/// The channels of several sources side by side.
pub struct ChannelStack {
    meta: SourceMeta,
    sources: Vec<Box<dyn VolumeSource>>,
    /// Per channel of the stack: its source and its channel there.
    map: Vec<(usize, usize)>,
}

/// Channel names made unique: a name that several channels share (files
/// of the same name in different folders) takes its file's folder in front
/// (`folder/name`, `folders[i]` for channel `i`), and one still shared
/// after that its channel number after (`name#3`). Names that occur once
/// stay as they are.
fn unique_names(names: &mut [String], folders: &[Option<String>]) {
    let count = |names: &[String], n: &str| names.iter().filter(|m| *m == n).count();
    let shared: Vec<bool> = names.iter().map(|n| count(names, n) > 1).collect();
    for (i, n) in names.iter_mut().enumerate() {
        if let (true, Some(f)) = (shared[i], &folders[i]) {
            *n = format!("{f}/{n}");
        }
    }
    let shared: Vec<bool> = names.iter().map(|n| count(names, n) > 1).collect();
    for (i, n) in names.iter_mut().enumerate() {
        if shared[i] {
            *n = format!("{n}#{i}");
        }
    }
}

/// A file's name without the volume extensions (`mni152-t1-u8.nii.gz` →
/// `mni152-t1-u8`).
pub fn channel_label(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut s = name.as_str();
    for ext in [
        ".gz", ".nii", ".nrrd", ".nhdr", ".tiff", ".tif", ".raw", ".zarr", ".ome",
    ] {
        if let Some(t) = s.strip_suffix(ext) {
            s = t;
        }
    }
    s.to_string()
}

/// A source's voxel type for messages (`u8`, `i16`), with the rescale
/// that made it, where one did (a NIfTI file's scl_slope/scl_inter widen
/// its stored numbers).
fn voxel_type(m: &SourceMeta) -> String {
    match &m.scaling {
        Some(v) if v.applied && v.dtype != v.stored => format!(
            "{} (its {} numbers rescaled by {}={}, {}={}, which makes them {}{})",
            m.dtype,
            v.stored,
            v.fields[0],
            v.slope,
            v.fields[1],
            v.inter,
            v.dtype,
            match v.fields[0] {
                "scl_slope" => format!("; --raw-values keeps them {}", v.stored),
                _ => String::new(),
            }
        ),
        _ => m.dtype.to_string(),
    }
}

/// What marks a file's voxels as labels, for messages.
fn labels_mark(path: &Path) -> &'static str {
    let name = path.to_string_lossy().to_ascii_lowercase();
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        "its NIfTI intent is \"label\""
    } else {
        "its metadata says labels"
    }
}

fn close3(a: [f64; 3], b: [f64; 3], scale: f64) -> bool {
    (0..3).all(|i| (a[i] - b[i]).abs() <= SAME * scale.max(a[i].abs()).max(b[i].abs()))
}

impl ChannelStack {
    /// Stack `sources` (at least one) as channels, after checking that they
    /// share one grid and agree on whether they hold labels.
    pub fn new(sources: Vec<Box<dyn VolumeSource>>) -> Result<ChannelStack> {
        Self::stack(sources, false)
    }

    /// [`ChannelStack::new`] for inputs taken as labels whatever their
    /// headers say (`convert --labels`): one that does not mark itself as
    /// labels (a NIfTI file without intent "label") is no mismatch.
    pub fn of_labels(sources: Vec<Box<dyn VolumeSource>>) -> Result<ChannelStack> {
        Self::stack(sources, true)
    }

    fn stack(sources: Vec<Box<dyn VolumeSource>>, as_labels: bool) -> Result<ChannelStack> {
        let Some(first) = sources.first() else {
            return Err(StoreError::invalid(
                "(no input)",
                "inputs",
                "at least one input is needed",
            ));
        };
        let m0 = first.meta().clone();
        let mut meta = SourceMeta::new(m0.path.clone(), m0.dims, 0, m0.dtype);
        let mut map = vec![];
        // The folder of each channel's file (for names that files share).
        let mut folders = vec![];
        let mut spacing = None;
        let mut origin = None;
        let mut unit = None;
        let mut labels = None;
        // How each channel is shown, where its input says.
        let mut display = vec![];
        for (i, s) in sources.iter().enumerate() {
            let m = s.meta();
            let bad = |field: &str, this: String, there: String| {
                Err(StoreError::invalid(
                    &m.path,
                    field,
                    format!(
                        "channels from several files need one grid: this file has {this}, {} has {there}",
                        m0.path.display()
                    ),
                ))
            };
            if m.dims != m0.dims {
                let xyz = |d: Dims3| format!("{}×{}×{} (x×y×z)", d[2], d[1], d[0]);
                return bad("dims", xyz(m.dims), xyz(m0.dims));
            }
            if m.dtype != m0.dtype {
                return bad("dtype", voxel_type(m), voxel_type(&m0));
            }
            if let Some(sp) = m.spacing {
                match spacing {
                    Some((s0, ref p)) if !close3(sp, s0, 0.0) => {
                        let p: &std::path::PathBuf = p;
                        return Err(StoreError::invalid(
                            &m.path,
                            "spacing",
                            format!(
                                "channels from several files need one grid: this file has spacing {sp:?} (z, y, x), {} has {s0:?}",
                                p.display()
                            ),
                        ));
                    }
                    Some(_) => {}
                    None => spacing = Some((sp, m.path.clone())),
                }
            }
            if let Some(o) = m.origin {
                // Origins compared at the scale of the spacing.
                let scale = spacing
                    .as_ref()
                    .map_or(1.0, |(s, _)| s[0].max(s[1]).max(s[2]));
                match origin {
                    Some((o0, ref p)) if !close3(o, o0, scale) => {
                        let p: &std::path::PathBuf = p;
                        return Err(StoreError::invalid(
                            &m.path,
                            "origin",
                            format!(
                                "channels from several files need one grid: this file has origin {o:?} (z, y, x), {} has {o0:?}",
                                p.display()
                            ),
                        ));
                    }
                    Some(_) => {}
                    None => origin = Some((o, m.path.clone())),
                }
            }
            if unit.is_none() {
                unit = m.unit.clone();
            }
            match labels {
                Some(l) if l != m.labels && !as_labels => {
                    let (marked, plain) = match m.labels {
                        true => (&m.path, &m0.path),
                        false => (&m0.path, &m.path),
                    };
                    return Err(StoreError::invalid(
                        &m.path,
                        "labels",
                        format!(
                            "{} marks its voxels as labels ({}) and {} does not: the channels \
                             of one volume are all labels or all intensities. --labels takes \
                             every input as labels, but a label image has one channel: convert \
                             {} on its own (--labels, e.g. into STORE/labels/NAME)",
                            marked.display(),
                            labels_mark(marked),
                            plain.display(),
                            marked.display()
                        ),
                    ));
                }
                _ => labels = Some(m.labels || as_labels),
            }
            let stem = channel_label(&m.path);
            let folder = m
                .path
                .parent()
                .and_then(|p| p.file_name())
                .map(|f| f.to_string_lossy().into_owned());
            for c in 0..m.channels {
                display.push(match m.channel_display.len() == m.channels {
                    true => m.channel_display[c].clone(),
                    false => ChannelDisplay::default(),
                });
                map.push((i, c));
                folders.push(folder.clone());
                let name = match m.channel_names.get(c) {
                    Some(n) if m.channels > 1 => format!("{stem}:{n}"),
                    Some(n) => n.clone(),
                    None if m.channels > 1 => format!("{stem}:{c}"),
                    None => stem.clone(),
                };
                meta.channel_names.push(name);
            }
            for n in &m.notes {
                meta.notes.push(format!("{}: {n}", m.path.display()));
            }
            if sources.len() > 1 {
                meta.notes.push(format!(
                    "channel{} {} from {}",
                    if m.channels > 1 { "s" } else { "" },
                    (map.len() - m.channels..map.len())
                        .map(|c| c.to_string())
                        .collect::<Vec<_>>()
                        .join(", "),
                    m.path.display()
                ));
            }
        }
        unique_names(&mut meta.channel_names, &folders);
        meta.channels = map.len();
        meta.spacing = spacing.map(|(s, _)| s);
        meta.origin = origin.map(|(o, _)| o);
        meta.unit = unit;
        meta.labels = labels.unwrap_or(false);
        if display.iter().any(|d| !d.is_empty()) {
            meta.channel_display = display;
        }
        meta.scaling = m0.scaling.clone();
        meta.read_bytes = sources
            .iter()
            .map(|s| s.meta().read_bytes)
            .max()
            .unwrap_or(0);
        Ok(ChannelStack { meta, sources, map })
    }
}

impl ChannelStack {
    /// Name the channels `names` (one per channel) instead of after the
    /// files.
    pub fn with_names(mut self, names: &[String]) -> Result<ChannelStack> {
        if names.len() != self.meta.channels {
            return Err(StoreError::invalid(
                &self.meta.path,
                "channel names",
                format!(
                    "{} names given for {} channels",
                    names.len(),
                    self.meta.channels
                ),
            ));
        }
        self.meta.channel_names = names.to_vec();
        Ok(self)
    }
}

impl VolumeSource for ChannelStack {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        crate::source::check_region(&self.meta, c, &z, &y, &x, out);
        let (s, sc) = self.map[c];
        self.sources[s].read_region(sc, z, y, x, out)
    }

    fn preferred_read(&self) -> Dims3 {
        self.sources[0].preferred_read()
    }

    fn chunk_absent(
        &self,
        c: usize,
        v: Dims3,
    ) -> Option<(std::path::PathBuf, crate::source::Absence)> {
        let (s, sc) = self.map[c];
        self.sources[s].chunk_absent(sc, v)
    }

    fn prefetch(&self, c: usize, region: [Range<u64>; 3]) -> usize {
        let (s, sc) = self.map[c];
        self.sources[s].prefetch(sc, region)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::{Kind, Procedural};
    use crate::source::test_util::read_all;
    use brickyard_core::DType;

    struct Renamed(Procedural, SourceMeta);

    impl VolumeSource for Renamed {
        fn meta(&self) -> &SourceMeta {
            &self.1
        }
        fn read_region(
            &self,
            c: usize,
            z: Range<u64>,
            y: Range<u64>,
            x: Range<u64>,
            out: &mut [u8],
        ) -> Result<()> {
            self.0.read_region(c, z, y, x, out)
        }
    }

    fn src(kind: Kind, dims: Dims3, name: &str, spacing: [f64; 3]) -> Box<dyn VolumeSource> {
        let p = Procedural::new(kind, dims, DType::U8);
        let mut m = p.meta().clone();
        m.path = name.into();
        m.spacing = Some(spacing);
        Box::new(Renamed(p, m))
    }

    #[test]
    fn channels_come_from_their_files() {
        let d = [6, 7, 9];
        let s = ChannelStack::new(vec![
            src(Kind::Mandelbulb, d, "/x/t1.nii.gz", [1.0; 3]),
            src(Kind::MarschnerLobb, d, "/x/gm.nii", [1.0; 3]),
        ])
        .unwrap();
        assert_eq!(s.meta().channels, 2);
        assert_eq!(s.meta().channel_names, ["t1", "gm"]);
        let a = Procedural::new(Kind::Mandelbulb, d, DType::U8);
        let b = Procedural::new(Kind::MarschnerLobb, d, DType::U8);
        assert_eq!(read_all(&s, 0), read_all(&a, 0));
        assert_eq!(read_all(&s, 1), read_all(&b, 0));
        assert_ne!(read_all(&s, 0), read_all(&s, 1));
    }

    #[test]
    fn names_that_files_share_are_made_unique() {
        let d = [6, 7, 9];
        let names = |paths: &[&str]| {
            let s = ChannelStack::new(
                paths
                    .iter()
                    .map(|p| src(Kind::Mandelbulb, d, p, [1.0; 3]))
                    .collect(),
            )
            .unwrap();
            s.meta().channel_names.clone()
        };
        // Files of one name in different folders: the folder in front; a
        // name of its own stays.
        assert_eq!(
            names(&["/d/ch1/img.tif", "/d/ch2/img.tif", "/d/dapi.tif"]),
            ["ch1/img", "ch2/img", "dapi"]
        );
        // The same file twice: the channel number after.
        assert_eq!(
            names(&["/d/a/v.nii", "/d/a/v.nii", "/d/b/v.nii"]),
            ["a/v#0", "a/v#1", "b/v"]
        );
        assert_eq!(names(&["t1.nii", "t1.nii.gz"]), ["t1#0", "t1#1"]);
    }

    #[test]
    fn a_different_grid_is_refused_naming_file_and_field() {
        let e = ChannelStack::new(vec![
            src(Kind::Mandelbulb, [6, 7, 9], "/x/a.nii", [1.0; 3]),
            src(Kind::Mandelbulb, [6, 7, 8], "/x/b.nii", [1.0; 3]),
        ])
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("/x/b.nii") && e.contains("dims") && e.contains("9×7×6"),
            "{e}"
        );
        let e = ChannelStack::new(vec![
            src(Kind::Mandelbulb, [6, 7, 9], "/x/a.nii", [1.0; 3]),
            src(Kind::Mandelbulb, [6, 7, 9], "/x/c.nii", [1.0, 1.0, 1.5]),
        ])
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("/x/c.nii") && e.contains("spacing") && e.contains("1.5"),
            "{e}"
        );
        // Equal up to a header's f32 rounding: accepted.
        assert!(ChannelStack::new(vec![
            src(Kind::Mandelbulb, [6, 7, 9], "/x/a.nii", [1.0; 3]),
            src(
                Kind::Mandelbulb,
                [6, 7, 9],
                "/x/d.nii",
                [1.0, 1.0, 1.0 + 1e-7]
            ),
        ])
        .is_ok());
    }

    /// A source `src` makes, changed by `edit`.
    fn edited(
        kind: Kind,
        name: &str,
        dtype: DType,
        edit: impl FnOnce(&mut SourceMeta),
    ) -> Box<dyn VolumeSource> {
        let p = Procedural::new(kind, [6, 7, 9], dtype);
        let mut m = p.meta().clone();
        m.path = name.into();
        edit(&mut m);
        Box::new(Renamed(p, m))
    }

    #[test]
    fn labels_given_override_what_the_files_say() {
        let mixed = || {
            vec![
                edited(Kind::Mandelbulb, "/x/seg.nii.gz", DType::U8, |m| {
                    m.labels = true
                }),
                edited(Kind::Mandelbulb, "/x/t1.nii.gz", DType::U8, |_| {}),
            ]
        };
        // Without --labels: the difference named (the intent), --labels
        // named, no talk of a grid.
        let e = ChannelStack::new(mixed()).err().unwrap().to_string();
        assert!(
            e.contains("/x/seg.nii.gz marks its voxels as labels")
                && e.contains("NIfTI intent is \"label\"")
                && e.contains("/x/t1.nii.gz does not")
                && e.contains("--labels")
                && !e.contains("grid")
                && !e.contains("labels false"),
            "{e}"
        );
        // --labels given: every input is labels.
        let s = ChannelStack::of_labels(mixed()).unwrap();
        assert!(s.meta().labels);
        let s = ChannelStack::of_labels(vec![
            edited(Kind::Mandelbulb, "/x/a.nii", DType::U8, |_| {}),
            edited(Kind::Mandelbulb, "/x/b.nii", DType::U8, |_| {}),
        ])
        .unwrap();
        assert!(s.meta().labels);
    }

    #[test]
    fn voxel_types_are_named_as_on_the_command_line() {
        let e = ChannelStack::new(vec![
            edited(Kind::Mandelbulb, "/x/a.nii", DType::U8, |_| {}),
            edited(Kind::Mandelbulb, "/x/b.nii", DType::I16, |_| {}),
        ])
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("this file has i16, /x/a.nii has u8") && !e.contains("I16"),
            "{e}"
        );
        // A rescale that widened the stored numbers: said.
        let e = ChannelStack::new(vec![
            edited(Kind::Mandelbulb, "/x/a.nii", DType::U8, |_| {}),
            edited(Kind::Mandelbulb, "/x/scl.nii", DType::I16, |m| {
                m.scaling = Some(crate::import::scale::ValueScaling {
                    fields: ["scl_slope", "scl_inter"],
                    slope: 2.0,
                    inter: -1.0,
                    stored: DType::U8,
                    dtype: DType::I16,
                    applied: true,
                    scanned: None,
                })
            }),
        ])
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("i16 (its u8 numbers rescaled by scl_slope=2, scl_inter=-1")
                && e.contains("--raw-values keeps them u8"),
            "{e}"
        );
    }

    #[test]
    fn each_input_keeps_how_its_channels_are_shown() {
        let shown = ChannelDisplay {
            color: Some([0, 0, 255]),
            window: Some([100.0, 500.0]),
            active: Some(false),
        };
        let given = shown.clone();
        let s = ChannelStack::new(vec![
            edited(Kind::Mandelbulb, "/x/a.nii", DType::U8, |_| {}),
            edited(Kind::Mandelbulb, "/x/b.zarr", DType::U8, |m| {
                m.channel_display = vec![given]
            }),
        ])
        .unwrap();
        assert_eq!(s.meta().channel_display, [ChannelDisplay::default(), shown]);
        // None given: none kept (the converter's defaults).
        let s = ChannelStack::new(vec![
            edited(Kind::Mandelbulb, "/x/a.nii", DType::U8, |_| {}),
            edited(Kind::Mandelbulb, "/x/b.nii", DType::U8, |_| {}),
        ])
        .unwrap();
        assert!(s.meta().channel_display.is_empty());
    }
}
