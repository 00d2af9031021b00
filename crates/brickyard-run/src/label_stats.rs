//! A label image's statistics (`_brickyard/labels.csv`, as `process`
//! writes it: one row per label in increasing label order, with its voxel
//! count, bounding box, centroid and mean intensity), read in ranges
//! through the store's storage layer, so remote label images have theirs
//! too and files of millions of labels are neither loaded nor scanned for
//! one row. The viewer's readout, its label table, and the renderers'
//! crossing of bricks that no label of a selection reaches use it.

use anyhow::{Context, Result};
use brickyard_core::label_table;
pub use brickyard_core::label_table::LabelRow;
use brickyard_render::params::{LabelBoxes, LabelSelect};
use brickyard_store::storage::{self, Span};
use std::path::{Path, PathBuf};

/// Bytes of a statistics file read per step of the search (and the
/// longest row).
pub const WINDOW: usize = 4096;

/// What the label table lists first: the rows of labels of at least
/// `min_voxels` voxels, by `by` (most first when `descending`; ties by
/// label).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TableOrder {
    pub by: SortBy,
    pub descending: bool,
    pub min_voxels: u64,
}

/// The column the label table is sorted by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SortBy {
    Voxels,
    /// Mean intensity (rows without one are left out).
    Mean,
    Label,
}

impl SortBy {
    pub const ALL: [SortBy; 3] = [SortBy::Voxels, SortBy::Mean, SortBy::Label];

    pub fn name(self) -> &'static str {
        match self {
            SortBy::Voxels => "voxels",
            SortBy::Mean => "mean",
            SortBy::Label => "label",
        }
    }

    pub fn parse(s: &str) -> Option<SortBy> {
        Self::ALL.into_iter().find(|b| b.name() == s)
    }
}

impl TableOrder {
    /// The labels of most voxels.
    pub const LARGEST: TableOrder = TableOrder {
        by: SortBy::Voxels,
        descending: true,
        min_voxels: 0,
    };

    /// The row's sort key (larger first when descending), `None`: left out.
    fn key(&self, id: u64, r: &LabelRow) -> Option<f64> {
        if r.voxels < self.min_voxels {
            return None;
        }
        let k = match self.by {
            SortBy::Voxels => r.voxels as f64,
            SortBy::Mean => r.mean.filter(|m| !m.is_nan())?,
            SortBy::Label => id as f64,
        };
        Some(if self.descending { k } else { -k })
    }
}

/// A label image's statistics file, searched by label (its rows are in
/// increasing label order, as `process` writes them). Read in ranges
/// through the store's storage, so remote label images have theirs too.
pub struct Stats {
    pub path: PathBuf,
    /// Where the rows begin (after the header).
    start: u64,
    len: u64,
}

impl Stats {
    /// The statistics of the label image at `label_dir` (`None`: it has
    /// none).
    pub fn open(label_dir: &Path) -> Result<Option<Stats>> {
        let path = label_dir.join(label_table::PATH);
        let Some(len) = storage::size(&path)? else {
            return Ok(None);
        };
        let mut st = Stats {
            path,
            start: 0,
            len,
        };
        let head = st.bytes(0, WINDOW as u64)?;
        let end = head.iter().position(|&b| b == b'\n').with_context(|| {
            format!(
                "{}: expected a header line within {WINDOW} bytes",
                st.path.display()
            )
        })?;
        label_table::check_header(&String::from_utf8_lossy(&head[..end]))
            .map_err(|e| anyhow::anyhow!("{}: {e}", st.path.display()))?;
        st.start = end as u64 + 1;
        Ok(Some(st))
    }

    /// Bytes `from..from + n` (fewer at the end of the file).
    fn bytes(&self, from: u64, n: u64) -> Result<Vec<u8>> {
        let r = from..(from + n).min(self.len);
        let mut got = storage::read_spans(&self.path, &[Span::Range(r)])?
            .with_context(|| format!("{}: gone", self.path.display()))?;
        Ok(got.swap_remove(0))
    }

    /// The first whole line that starts at or after `pos`: its start, the
    /// start of the next one and its text (`None`: no line starts there).
    /// Rows are at most `WINDOW` bytes long.
    fn line_at(&mut self, pos: u64) -> Result<Option<(u64, u64, String)>> {
        // A line starts at `pos` when the byte before it ends a line.
        let from = pos.max(self.start) - 1;
        if from + 1 >= self.len {
            return Ok(None);
        }
        let buf = self.bytes(from, 2 * WINDOW as u64)?;
        let nl = |b: &[u8]| b.iter().position(|&c| c == b'\n');
        let long = || anyhow::anyhow!("a row longer than {WINDOW} bytes");
        let s = nl(&buf[..buf.len().min(WINDOW + 1)]).ok_or_else(long)?;
        let begin = from + s as u64 + 1;
        if begin >= self.len {
            return Ok(None);
        }
        let rest = &buf[s + 1..];
        let (line, next) = match nl(rest) {
            Some(e) => (&rest[..e], begin + e as u64 + 1),
            None if from + buf.len() as u64 == self.len => (rest, self.len),
            None => return Err(long()),
        };
        Ok(Some((
            begin,
            next,
            String::from_utf8_lossy(line).into_owned(),
        )))
    }

    /// The row of `label`, if the file has one: a binary search over byte
    /// positions for the first row whose label is not below it.
    pub fn row(&mut self, label: u64) -> Result<Option<LabelRow>> {
        let label_of = |line: &str| -> Result<u64> {
            let f = line.split(',').next().unwrap_or("");
            f.parse()
                .with_context(|| format!("expected a label in the first column, found {f:?}"))
        };
        let (mut lo, mut hi) = (self.start, self.len);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            match self.line_at(mid)? {
                None => hi = mid,
                Some((_, next, line)) if label_of(&line)? < label => lo = next,
                Some(_) => hi = mid,
            }
        }
        let Some((_, _, line)) = self.line_at(lo)? else {
            return Ok(None);
        };
        if label_of(&line)? != label {
            return Ok(None);
        }
        parse_row(&line).map(|(_, r)| Some(r))
    }

    /// The first `n` labels in `order` (ties by label), read through the
    /// whole file `chunk` bytes at a time, keeping `n` rows.
    pub fn top(&mut self, n: usize, order: TableOrder, chunk: u64) -> Result<Vec<(u64, LabelRow)>> {
        use std::cmp::Reverse;
        use std::collections::BinaryHeap;
        /// A sort key in the heap's total order.
        struct Key(f64);
        impl PartialEq for Key {
            fn eq(&self, o: &Self) -> bool {
                self.cmp(o).is_eq()
            }
        }
        impl Eq for Key {}
        impl PartialOrd for Key {
            fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
                Some(self.cmp(o))
            }
        }
        impl Ord for Key {
            fn cmp(&self, o: &Self) -> std::cmp::Ordering {
                self.0.total_cmp(&o.0)
            }
        }
        let mut heap: BinaryHeap<Reverse<(Key, Reverse<u64>)>> = BinaryHeap::new();
        let mut rows: std::collections::HashMap<u64, LabelRow> = Default::default();
        self.each_row(chunk, |id, r| {
            let Some(k) = order.key(id, &r) else {
                return;
            };
            heap.push(Reverse((Key(k), Reverse(id))));
            rows.insert(id, r);
            if heap.len() > n {
                if let Some(Reverse((_, Reverse(out)))) = heap.pop() {
                    rows.remove(&out);
                }
            }
        })?;
        let mut out: Vec<(f64, u64)> = heap
            .into_iter()
            .map(|Reverse((Key(k), Reverse(id)))| (k, id))
            .collect();
        out.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        Ok(out
            .into_iter()
            .map(|(_, id)| (id, rows.remove(&id).expect("kept")))
            .collect())
    }

    /// Every row, in the file's order, read `chunk` bytes at a time.
    fn each_row(&mut self, chunk: u64, mut f: impl FnMut(u64, LabelRow)) -> Result<()> {
        let (mut pos, mut rest) = (self.start, Vec::<u8>::new());
        while pos < self.len {
            let got = self.bytes(pos, chunk)?;
            pos += got.len() as u64;
            rest.extend_from_slice(&got);
            let end = match rest.iter().rposition(|&b| b == b'\n') {
                Some(e) => e + 1,
                None if pos >= self.len => rest.len(),
                None => continue,
            };
            for line in String::from_utf8_lossy(&rest[..end])
                .lines()
                .filter(|l| !l.is_empty())
            {
                let (id, r) = parse_row(line)?;
                f(id, r);
            }
            rest.drain(..end);
        }
        Ok(())
    }

    /// The bounding boxes of labels `ids` (increasing, as a [`LabelSelect`]
    /// keeps them; of a label image whose level 0
    /// is `dims`; the statistics' coordinates are its voxels): labels
    /// without a row have no voxels and no box. Up to 64 labels are found
    /// one by one; more, in one read through the file.
    pub fn boxes(&mut self, ids: &[i32], dims: [u64; 3]) -> Result<LabelBoxes> {
        let mut boxes = vec![];
        if ids.len() <= 64 {
            for &id in ids.iter().filter(|&&i| i > 0) {
                if let Some(r) = self.row(id as u64)? {
                    boxes.push(r.bounds());
                }
            }
        } else {
            // (`ids` are in increasing order, as a selection keeps them.)
            self.each_row(1 << 20, |id, r| {
                if i32::try_from(id).is_ok_and(|i| ids.binary_search(&i).is_ok()) {
                    boxes.push(r.bounds());
                }
            })?;
        }
        Ok(LabelBoxes { dims, boxes })
    }
}

/// `select` with the bounding boxes of the labels it draws, from the
/// statistics of the label image at `label_dir` (level 0 of size `dims`),
/// where it draws only some and the image has statistics; as it is
/// otherwise.
pub fn with_boxes(
    mut select: LabelSelect,
    label_dir: &Path,
    dims: [u64; 3],
) -> Result<LabelSelect> {
    if !select.hide {
        if let Some(mut st) = Stats::open(label_dir)? {
            let boxes = st
                .boxes(&select.ids, dims)
                .with_context(|| format!("{}", st.path.display()))?;
            select.boxes = Some(boxes);
        }
    }
    Ok(select)
}

/// Write the statistics table of the label image at `label_dir` from its
/// voxels (a label image converted from a file, which no labelling pass
/// made here): `_brickyard/labels.csv` and its `.json` twin, each whole or
/// not at all. `image`: the store it labels, whose channel 0 gives each
/// label's mean intensity when its level 0 is on the labels' grid. The
/// table may take `max_bytes`. `Ok(Some(why))`: no table, and why (too many
/// labels, or a voxel that is not a label); the image stays usable.
pub fn write_from_voxels(
    label_dir: &Path,
    image: Option<&Path>,
    max_bytes: u64,
    progress: &dyn brickyard_store::Progress,
    cancel: &std::sync::atomic::AtomicBool,
) -> Result<Option<String>> {
    use brickyard_store::import::zarr;
    use brickyard_store::VolumeSource;
    let labels = zarr::open(label_dir, 0)?;
    let dims = labels.meta().dims;
    let image = match image {
        Some(p) => {
            let im = zarr::open(p, 0)?;
            im.meta().same_grid(labels.meta()).is_ok().then_some(im)
        }
        None => None,
    };
    let intensity = image.as_ref().map(|im| (im as &dyn VolumeSource, 0));
    // Blocks of a brick (whole slices of a large volume would hold
    // gigabytes at once).
    let block = [64; 3];
    let rows = match brickyard_process::tally::tally(
        &labels, intensity, block, max_bytes, progress, cancel,
    )? {
        Ok(rows) => rows,
        Err(why) => return Ok(Some(why.to_string())),
    };
    let dir = label_dir.join("_brickyard");
    std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let whole = |name: &str, f: &dyn Fn(&mut dyn std::io::Write) -> std::io::Result<()>| {
        let path = dir.join(name);
        let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let write = || -> std::io::Result<()> {
            let mut w = std::io::BufWriter::new(std::fs::File::create(&tmp)?);
            f(&mut w)?;
            std::io::Write::flush(&mut w)?;
            std::fs::rename(&tmp, &path)
        };
        write()
            .inspect_err(|_| {
                let _ = std::fs::remove_file(&tmp);
            })
            .with_context(|| format!("{}: cannot write", path.display()))
    };
    whole("labels.csv", &|w| {
        writeln!(w, "{}", label_table::HEADER)?;
        for (id, r) in &rows {
            label_table::write_row(w, *id, r)?;
        }
        Ok(())
    })?;
    whole("labels.json", &|w| {
        write!(
            w,
            "{{\n  \"count\": {},\n  \"dims_zyx\": [{}, {}, {}],\n  \"from\": \"voxels\",\n  \"intensity_channel\": {},\n  \"labels\": [",
            rows.len(),
            dims[0],
            dims[1],
            dims[2],
            if intensity.is_some() { "0" } else { "null" }
        )?;
        for (i, (id, r)) in rows.iter().enumerate() {
            w.write_all(if i == 0 { b"\n" } else { b",\n" })?;
            label_table::write_json_row(w, *id, r)?;
        }
        w.write_all(b"\n  ]\n}\n")
    })?;
    Ok(None)
}

/// A row of the statistics: its label and the rest.
fn parse_row(line: &str) -> Result<(u64, LabelRow)> {
    label_table::parse_row(line).map_err(anyhow::Error::msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats_file(rows: &[(u64, u64)]) -> (tempfile::TempDir, Stats) {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("_brickyard")).unwrap();
        let mut s = String::from(
            "label,voxels,min_z,min_y,min_x,max_z,max_y,max_x,centroid_z,centroid_y,centroid_x,mean\n",
        );
        for (l, n) in rows {
            // Rows of different lengths, as real ones are.
            s += &format!("{l},{n},1,2,3,4,5,6,{}.25,2.5,3.5,{}\n", l % 7, l * 10);
        }
        std::fs::write(d.path().join("_brickyard/labels.csv"), s).unwrap();
        let st = Stats::open(d.path()).unwrap().unwrap();
        (d, st)
    }

    #[test]
    fn rows_are_found_by_label_in_files_of_any_length() {
        // Labels with gaps: every present one is found, every absent one
        // is not, in files of 1 to 3000 rows (the search windows of 4 KiB
        // then hold many rows, or part of the file).
        for n in [1u64, 2, 3, 10, 257, 3000] {
            let rows: Vec<(u64, u64)> = (0..n).map(|i| (3 * i + 2, 1000 + i * i)).collect();
            let (_d, mut st) = stats_file(&rows);
            for (l, v) in &rows {
                let r = st
                    .row(*l)
                    .unwrap()
                    .unwrap_or_else(|| panic!("{n} rows: label {l}"));
                assert_eq!(r.voxels, *v);
                assert_eq!(r.centroid[0], (l % 7) as f64 + 0.25);
                assert_eq!(r.mean, Some((l * 10) as f64));
            }
            for l in [0, 1, 3, 4, 3 * n + 2, u64::MAX] {
                assert_eq!(st.row(l).unwrap(), None, "{n} rows: label {l}");
            }
        }
    }

    #[test]
    fn the_largest_labels_are_kept_while_the_file_is_read() {
        // 3000 rows, sizes in a scrambled order with ties.
        let rows: Vec<(u64, u64)> = (1..=3000u64).map(|i| (i, i * 7919 % 1013)).collect();
        let (_d, mut st) = stats_file(&rows);
        // (Reads of 4000 bytes: lines cross their ends.)
        let got = st.top(25, TableOrder::LARGEST, 4000).unwrap();
        let mut want = rows.clone();
        want.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        let got: Vec<(u64, u64)> = got.iter().map(|(id, r)| (*id, r.voxels)).collect();
        assert_eq!(got, want[..25].to_vec());
        assert_eq!(
            st.top(5000, TableOrder::LARGEST, 1 << 20).unwrap().len(),
            3000
        );
        // Other orders, against the rows sorted here: the smallest of at
        // least 500 voxels; the least and greatest means (the file's mean
        // is ten times the label: by label, in effect); the last labels.
        let order = |by, descending, min_voxels| TableOrder {
            by,
            descending,
            min_voxels,
        };
        let ids = |got: Vec<(u64, LabelRow)>| got.into_iter().map(|(id, _)| id).collect::<Vec<_>>();
        let mut want: Vec<(u64, u64)> = rows.iter().filter(|r| r.1 >= 500).copied().collect();
        want.sort_by(|a, b| a.1.cmp(&b.1).then(a.0.cmp(&b.0)));
        let want_ids: Vec<u64> = want[..10].iter().map(|r| r.0).collect();
        assert_eq!(
            ids(st.top(10, order(SortBy::Voxels, false, 500), 4000).unwrap()),
            want_ids
        );
        assert_eq!(
            ids(st.top(4, order(SortBy::Mean, false, 0), 4000).unwrap()),
            vec![1, 2, 3, 4]
        );
        assert_eq!(
            ids(st.top(3, order(SortBy::Mean, true, 0), 4000).unwrap()),
            vec![3000, 2999, 2998]
        );
        assert_eq!(
            ids(st.top(3, order(SortBy::Label, true, 0), 4000).unwrap()),
            vec![3000, 2999, 2998]
        );
        let big: Vec<u64> = rows
            .iter()
            .filter(|r| r.1 >= 1000)
            .map(|r| r.0)
            .take(5)
            .collect();
        assert_eq!(
            ids(st.top(5, order(SortBy::Label, false, 1000), 4000).unwrap()),
            big
        );
    }

    #[test]
    fn a_statistics_file_of_another_shape_is_refused_by_name() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("_brickyard")).unwrap();
        std::fs::write(d.path().join("_brickyard/labels.csv"), "id,size\n1,2\n").unwrap();
        let e = format!("{:#}", Stats::open(d.path()).err().unwrap());
        assert!(
            e.contains("labels.csv") && e.contains("expected the header"),
            "{e}"
        );
        assert!(Stats::open(&d.path().join("none")).unwrap().is_none());
    }
}
