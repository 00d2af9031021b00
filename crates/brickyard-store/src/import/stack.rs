//! Several inputs of one grid as the channels of one volume: `convert`'s
//! `a.nii.gz b.nii.gz c.nii.gz OUT`. The inputs must agree on shape, voxel
//! type, spacing and origin (where they state them); the first input that
//! does not is named in the error with the field and both values. Channels
//! are the inputs' channels in order, named after the files (or the
//! names a file gives its channels).

use crate::error::{Result, StoreError};
use crate::source::{SourceMeta, VolumeSource};
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

fn close3(a: [f64; 3], b: [f64; 3], scale: f64) -> bool {
    (0..3).all(|i| (a[i] - b[i]).abs() <= SAME * scale.max(a[i].abs()).max(b[i].abs()))
}

impl ChannelStack {
    /// Stack `sources` (at least one) as channels, after checking that they
    /// share one grid.
    pub fn new(sources: Vec<Box<dyn VolumeSource>>) -> Result<ChannelStack> {
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
                return bad("dtype", format!("{:?}", m.dtype), format!("{:?}", m0.dtype));
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
                Some(l) if l != m.labels => {
                    return bad(
                        "labels",
                        format!("labels {}", m.labels),
                        format!("labels {l}"),
                    )
                }
                _ => labels = Some(m.labels),
            }
            let stem = channel_label(&m.path);
            let folder = m
                .path
                .parent()
                .and_then(|p| p.file_name())
                .map(|f| f.to_string_lossy().into_owned());
            for c in 0..m.channels {
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
}
