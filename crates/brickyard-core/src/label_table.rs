//! A label image's statistics table (`_brickyard/labels.csv`): one row per
//! label, in increasing label order, with its voxel count, bounding box
//! (inclusive), centroid and mean intensity, in voxels `[z, y, x]` of the
//! level it was labelled at. `process` writes it; the viewer, `render` and
//! the web client read it.

/// Where the table lies in a label image.
pub const PATH: &str = "_brickyard/labels.csv";

/// The table's header line (without its line end).
pub const HEADER: &str =
    "label,voxels,min_z,min_y,min_x,max_z,max_y,max_x,centroid_z,centroid_y,centroid_x,mean";

/// A label's row of the table.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelRow {
    pub voxels: u64,
    pub min: [u64; 3],
    pub max: [u64; 3],
    pub centroid: [f64; 3],
    /// Mean intensity of the image under the label, where recorded.
    pub mean: Option<f64>,
}

impl LabelRow {
    /// The bounding box, `[min_z, min_y, min_x, max_z, max_y, max_x]`.
    pub fn bounds(&self) -> [u64; 6] {
        let ([a, b, c], [d, e, f]) = (self.min, self.max);
        [a, b, c, d, e, f]
    }
}

/// Write `label`'s row of the table (with its line end).
pub fn write_row(w: &mut dyn std::io::Write, label: u64, r: &LabelRow) -> std::io::Result<()> {
    writeln!(
        w,
        "{},{},{},{},{},{},{},{},{},{},{},{}",
        label,
        r.voxels,
        r.min[0],
        r.min[1],
        r.min[2],
        r.max[0],
        r.max[1],
        r.max[2],
        r.centroid[0],
        r.centroid[1],
        r.centroid[2],
        r.mean.map(|m| m.to_string()).unwrap_or_default()
    )
}

/// `label`'s row as the JSON object of the table's `.json` twin
/// (non-finite numbers as `null`).
pub fn write_json_row(w: &mut dyn std::io::Write, label: u64, r: &LabelRow) -> std::io::Result<()> {
    let num = |v: f64| match v.is_finite() {
        true => format!("{v}"),
        false => "null".into(),
    };
    write!(
        w,
        "    {{\"label\": {}, \"voxels\": {}, \"min_zyx\": [{}, {}, {}], \"max_zyx\": [{}, {}, {}], \"centroid_zyx\": [{}, {}, {}], \"mean\": {}}}",
        label,
        r.voxels,
        r.min[0],
        r.min[1],
        r.min[2],
        r.max[0],
        r.max[1],
        r.max[2],
        num(r.centroid[0]),
        num(r.centroid[1]),
        num(r.centroid[2]),
        r.mean.map(num).unwrap_or_else(|| "null".into())
    )
}

/// Whether `line` is the table's header (the mean column may be absent).
pub fn check_header(line: &str) -> Result<(), String> {
    match line.starts_with(&HEADER[..HEADER.len() - ",mean".len()]) {
        true => Ok(()),
        false => Err(format!(
            "expected the header `label,voxels,min_z,...`, found {line:?}"
        )),
    }
}

/// Every row of a whole table's text (header first), in the file's order;
/// an error names the line it is on (the header is line 1).
pub fn parse_table(text: &str, mut f: impl FnMut(u64, LabelRow)) -> Result<(), String> {
    let mut lines = text.lines();
    check_header(lines.next().unwrap_or(""))?;
    for (i, line) in lines.enumerate().filter(|(_, l)| !l.is_empty()) {
        let (id, r) = parse_row(line).map_err(|e| format!("row {}: {e}", i + 2))?;
        f(id, r);
    }
    Ok(())
}

/// A row of the table: its label and the rest.
pub fn parse_row(line: &str) -> Result<(u64, LabelRow), String> {
    let f: Vec<&str> = line.split(',').collect();
    if f.len() < 11 {
        return Err(format!(
            "expected at least 11 columns, found {}: {line:?}",
            f.len()
        ));
    }
    let int = |i: usize| -> Result<u64, String> {
        f[i].parse()
            .map_err(|e| format!("column {}: expected a count, found {:?}: {e}", i + 1, f[i]))
    };
    let real = |i: usize| -> Result<f64, String> {
        f[i].parse()
            .map_err(|e| format!("column {}: expected a number, found {:?}: {e}", i + 1, f[i]))
    };
    Ok((
        int(0)?,
        LabelRow {
            voxels: int(1)?,
            min: [int(2)?, int(3)?, int(4)?],
            max: [int(5)?, int(6)?, int(7)?],
            centroid: [real(8)?, real(9)?, real(10)?],
            mean: f
                .get(11)
                .filter(|s| !s.is_empty())
                .map(|_| real(11))
                .transpose()?,
        },
    ))
}
