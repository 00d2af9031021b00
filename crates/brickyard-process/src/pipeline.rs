//! Pipelines as text: `gauss(1.5) | threshold(0.3) | label(26)`.
//!
//! Grammar: stages separated by `|`; a stage is a name, optionally followed
//! by arguments in parentheses separated by commas. Whitespace is ignored.
//!
//! | stage | arguments | result |
//! |---|---|---|
//! | `gauss(s)` / `gauss(sx,sy,sz)` | σ in voxels, or with a unit (`1.5um`) | f32 |
//! | `gradmag(s)` / `gradmag(sx,sy,sz)` | as `gauss` | f32 |
//! | `sobel` | none | f32 |
//! | `threshold(t)` | a number | u8 mask, `1` where value > t |
//! | `window(lo,hi)` | two numbers, lo ≤ hi | u8 mask, `1` where lo ≤ value ≤ hi |
//! | `label(6)` / `label(26)` | connectivity (default 26) | u32 labels; last stage only |

use std::fmt;

/// A length along the axes, in voxels or in a physical unit.
#[derive(Debug, Clone, PartialEq)]
pub enum Sigma {
    /// σ in voxels, `[z, y, x]`.
    Voxels([f64; 3]),
    /// σ in `unit` (an OME-NGFF unit name such as `micrometer`), `[z, y, x]`.
    Physical { value: [f64; 3], unit: String },
}

/// One stage of a pipeline.
#[derive(Debug, Clone, PartialEq)]
pub enum Op {
    Gauss(Sigma),
    GradMag(Sigma),
    Sobel,
    Threshold(f64),
    Window(f64, f64),
    /// Median of the box reaching this many voxels from each voxel,
    /// `[z, y, x]`.
    Median([u64; 3]),
    Label(u8),
}

/// A number as a message shows it: as written where short, in exponent
/// form where huge or tiny (`gauss(1e308)` was said with 309 digits).
pub fn short(x: f64) -> String {
    let a = x.abs();
    if a != 0.0 && a.is_finite() && !(1e-4..1e9).contains(&a) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

impl Op {
    /// The stage as it would be written.
    pub fn text(&self) -> String {
        fn sig(s: &Sigma) -> String {
            let (v, u) = match s {
                Sigma::Voxels(v) => (v, String::new()),
                Sigma::Physical { value, unit } => (value, unit_suffix(unit).to_string()),
            };
            if v[0] == v[1] && v[1] == v[2] {
                format!("{}{u}", short(v[0]))
            } else {
                format!("{}{u},{}{u},{}{u}", short(v[2]), short(v[1]), short(v[0]))
            }
        }
        match self {
            Op::Gauss(s) => format!("gauss({})", sig(s)),
            Op::GradMag(s) => format!("gradmag({})", sig(s)),
            Op::Sobel => "sobel".into(),
            Op::Threshold(t) => format!("threshold({})", short(*t)),
            Op::Window(a, b) => format!("window({},{})", short(*a), short(*b)),
            Op::Median(r) if r[0] == r[1] && r[1] == r[2] => format!("median({})", r[0]),
            Op::Median(r) => format!("median({},{},{})", r[2], r[1], r[0]),
            Op::Label(c) => format!("label({c})"),
        }
    }
}

/// A parse error: what was found, where, and what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct ParseError {
    /// The offending text.
    pub token: String,
    /// Byte offset of the token in the pipeline text.
    pub pos: usize,
    pub expected: String,
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pipeline: at {:?} (byte {}): expected {}",
            self.token, self.pos, self.expected
        )
    }
}

impl std::error::Error for ParseError {}

/// A parsed pipeline.
#[derive(Debug, Clone, PartialEq)]
pub struct Pipeline {
    pub ops: Vec<Op>,
}

const STAGES: &str = "a stage: gauss(SIGMA), gradmag(SIGMA), sobel, median(R), threshold(T), \
     window(LO,HI) or label(6|26)";

/// Unit suffixes accepted on σ and the OME-NGFF unit they stand for.
const UNITS: [(&str, &str); 6] = [
    ("nm", "nanometer"),
    ("um", "micrometer"),
    ("µm", "micrometer"),
    ("mm", "millimeter"),
    ("cm", "centimeter"),
    ("m", "meter"),
];

fn unit_suffix(unit: &str) -> &str {
    UNITS
        .iter()
        .find(|(_, u)| *u == unit)
        .map(|(s, _)| *s)
        .unwrap_or(unit)
}

impl Pipeline {
    pub fn parse(text: &str) -> Result<Pipeline, ParseError> {
        let mut ops = vec![];
        // Where each stage begins, for messages.
        let mut starts = vec![];
        let mut pos = 0;
        for part in text.split('|') {
            let start = pos + (part.len() - part.trim_start().len());
            pos += part.len() + 1;
            let s = part.trim();
            if s.is_empty() {
                return Err(ParseError {
                    token: part.to_string(),
                    pos: start,
                    expected: STAGES.into(),
                });
            }
            ops.push(parse_stage(s, start)?);
            starts.push((start, s));
        }
        for (i, op) in ops.iter().enumerate() {
            if matches!(op, Op::Label(_)) && i + 1 != ops.len() {
                return Err(ParseError {
                    token: starts[i].1.to_string(),
                    pos: starts[i].0,
                    expected: "label(...) as the last stage (labels are not filtered further)"
                        .into(),
                });
            }
        }
        Ok(Pipeline { ops })
    }

    /// The pipeline as text, normalised.
    pub fn text(&self) -> String {
        self.ops.iter().map(Op::text).collect::<Vec<_>>().join("|")
    }

    /// On a label image, whose values are names: the stages that would mix
    /// label ids as if they were intensities (averages, gradients,
    /// medians) before a threshold, window or labelling makes a mask of
    /// them. Empty where the pipeline suits labels (`threshold(0)` keeps
    /// every label, `window(a,b)` the labels a to b, and filters after
    /// them smooth the mask).
    pub fn mixes_label_ids(&self) -> Vec<&Op> {
        self.ops
            .iter()
            .take_while(|op| !matches!(op, Op::Threshold(_) | Op::Window(..) | Op::Label(_)))
            .filter(|op| {
                matches!(
                    op,
                    Op::Gauss(_) | Op::GradMag(_) | Op::Sobel | Op::Median(_)
                )
            })
            .collect()
    }

    /// The note for [`Pipeline::mixes_label_ids`] on the label image
    /// `name`, or `None` where the pipeline suits labels.
    pub fn label_ids_note(&self, name: &str) -> Option<String> {
        let mixing = self.mixes_label_ids();
        let first = mixing.first()?;
        Some(format!(
            "{name} is a label image: {} treat{} its label ids as intensities (the result depends on \
             how the labels happen to be numbered); threshold(0) first makes a mask of all its \
             labels (e.g. \"threshold(0)|{}\"), window(a,b) of the labels a to b",
            mixing.iter().map(|op| op.text()).collect::<Vec<_>>().join(", "),
            if mixing.len() == 1 { "s" } else { "" },
            first.text()
        ))
    }

    /// Whether the result is a label or mask image (written with mode
    /// downsampling, under `labels/`).
    pub fn is_label_output(&self) -> bool {
        matches!(
            self.ops.last(),
            Some(Op::Label(_) | Op::Threshold(_) | Op::Window(..))
        )
    }
}

fn parse_stage(s: &str, pos: usize) -> Result<Op, ParseError> {
    let err = |token: &str, off: usize, expected: &str| ParseError {
        token: token.to_string(),
        pos: pos + off,
        expected: expected.to_string(),
    };
    let (name, args, args_off) = match s.find('(') {
        Some(i) => {
            if !s.ends_with(')') {
                return Err(err(s, 0, "a closing ')' at the end of the stage"));
            }
            let inner = &s[i + 1..s.len() - 1];
            let args: Vec<(&str, usize)> = if inner.trim().is_empty() {
                vec![]
            } else {
                let mut off = i + 1;
                inner
                    .split(',')
                    .map(|a| {
                        let o = off + (a.len() - a.trim_start().len());
                        off += a.len() + 1;
                        (a.trim(), o)
                    })
                    .collect()
            };
            (s[..i].trim(), args, i)
        }
        None => (s, vec![], s.len()),
    };
    let number = |a: &(&str, usize), what: &str| -> Result<f64, ParseError> {
        match a.0.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(err(a.0, a.1, &format!("{what} (a finite number)"))),
        }
    };
    let count = |n: &[usize], what: &str| -> Result<(), ParseError> {
        if n.contains(&args.len()) {
            Ok(())
        } else {
            Err(err(
                s,
                args_off,
                &format!("{name} with {what}, found {} argument(s)", args.len()),
            ))
        }
    };
    match name {
        "gauss" | "gradmag" => {
            count(&[1, 3], "one σ or three (x,y,z)")?;
            let mut vals = vec![];
            let mut unit: Option<Option<&str>> = None;
            for a in &args {
                let (num, u) = split_unit(a.0);
                let v = match num.parse::<f64>() {
                    Ok(v) if v.is_finite() && v > 0.0 => v,
                    _ => {
                        return Err(err(
                            a.0,
                            a.1,
                            "σ: a positive number, optionally with a unit (nm, um, mm, cm, m)",
                        ))
                    }
                };
                let u = match u {
                    "" => None,
                    u => match UNITS.iter().find(|(s, _)| *s == u) {
                        Some((_, n)) => Some(*n),
                        None => return Err(err(a.0, a.1, "a unit among nm, um, mm, cm, m")),
                    },
                };
                if unit.is_some_and(|p| p != u) {
                    return Err(err(a.0, a.1, "the same unit (or none) on every σ"));
                }
                unit = Some(u);
                vals.push(v);
            }
            // Arguments are x, y, z; internally z, y, x.
            let zyx = if vals.len() == 1 {
                [vals[0]; 3]
            } else {
                [vals[2], vals[1], vals[0]]
            };
            let sigma = match unit.flatten() {
                None => Sigma::Voxels(zyx),
                Some(u) => Sigma::Physical {
                    value: zyx,
                    unit: u.to_string(),
                },
            };
            Ok(if name == "gauss" {
                Op::Gauss(sigma)
            } else {
                Op::GradMag(sigma)
            })
        }
        "sobel" => {
            count(&[0], "no arguments")?;
            Ok(Op::Sobel)
        }
        "median" => {
            count(&[1, 3], "one radius or three (x,y,z)")?;
            let max = crate::kernels::MAX_MEDIAN_RADIUS;
            let mut vals = vec![];
            for a in &args {
                match a.0.parse::<u64>() {
                    Ok(v) if v as usize <= max => vals.push(v),
                    _ => {
                        return Err(err(
                            a.0,
                            a.1,
                            &format!(
                                "a radius in voxels: a whole number from 0 to {max} (the box \
                                 is 2R+1 voxels across)"
                            ),
                        ))
                    }
                }
            }
            Ok(Op::Median(if vals.len() == 1 {
                [vals[0]; 3]
            } else {
                [vals[2], vals[1], vals[0]]
            }))
        }
        "threshold" => {
            count(&[1], "one argument: the threshold")?;
            Ok(Op::Threshold(number(&args[0], "threshold")?))
        }
        "window" => {
            count(&[2], "two arguments: LO,HI")?;
            let lo = number(&args[0], "LO")?;
            let hi = number(&args[1], "HI")?;
            if lo > hi {
                return Err(err(s, 0, "window(LO,HI) with LO <= HI"));
            }
            Ok(Op::Window(lo, hi))
        }
        "label" => {
            count(&[0, 1], "no argument or the connectivity 6 or 26")?;
            let c = match args.first().map(|a| (a.0, a)) {
                None | Some(("26", _)) => 26,
                Some(("6", _)) => 6,
                Some((_, a)) => return Err(err(a.0, a.1, "connectivity 6 or 26")),
            };
            Ok(Op::Label(c))
        }
        _ => Err(err(name, 0, STAGES)),
    }
}

/// Split `1.5um` into `("1.5", "um")`.
fn split_unit(a: &str) -> (&str, &str) {
    let i = a
        .find(|c: char| !(c.is_ascii_digit() || matches!(c, '.' | 'e' | 'E' | '+' | '-')))
        .unwrap_or(a.len());
    (a[..i].trim(), a[i..].trim())
}

#[cfg(test)]
mod tests {
    #[test]
    fn filters_before_a_mask_mix_label_ids_and_after_it_do_not() {
        let mixing = |t: &str| {
            Pipeline::parse(t)
                .unwrap()
                .mixes_label_ids()
                .iter()
                .map(|op| op.text())
                .collect::<Vec<_>>()
        };
        assert_eq!(mixing("gauss(2)"), ["gauss(2)"]);
        assert_eq!(
            mixing("median(1)|sobel|threshold(3)"),
            ["median(1)", "sobel"]
        );
        assert!(mixing("threshold(0)|gauss(2)").is_empty());
        assert!(mixing("window(3,5)|gradmag(1)").is_empty());
        assert!(mixing("label(26)").is_empty());
        let p = Pipeline::parse("gauss(2)|sobel").unwrap();
        let note = p.label_ids_note("labels/cells").unwrap();
        assert!(
            note.starts_with("labels/cells is a label image: gauss(2), sobel treat its"),
            "{note}"
        );
        assert!(note.contains("\"threshold(0)|gauss(2)\""), "{note}");
        assert!(Pipeline::parse("threshold(0)")
            .unwrap()
            .label_ids_note("x")
            .is_none());
    }

    use super::*;

    /// Huge and tiny numbers are said in exponent form (σ 1e308 took 309
    /// digits in each of the three places a message named it), and the
    /// text parses back to the same stages.
    #[test]
    fn numbers_in_stage_text_stay_short() {
        let p = Pipeline::parse("gauss(1e308)|threshold(0.00001)|window(-2.5e12,3)").unwrap();
        assert_eq!(p.text(), "gauss(1e308)|threshold(1e-5)|window(-2.5e12,3)");
        assert_eq!(Pipeline::parse(&p.text()).unwrap().ops, p.ops);
        assert_eq!(short(1.5), "1.5");
        assert_eq!(short(0.0), "0");
    }

    #[test]
    fn parses_a_chain() {
        let p = Pipeline::parse(" gauss(1.5) | threshold(0.3)|label(26) ").unwrap();
        assert_eq!(
            p.ops,
            vec![
                Op::Gauss(Sigma::Voxels([1.5; 3])),
                Op::Threshold(0.3),
                Op::Label(26)
            ]
        );
        assert_eq!(p.text(), "gauss(1.5)|threshold(0.3)|label(26)");
        assert!(p.is_label_output());
        let p = Pipeline::parse("gradmag(1,2,3)|sobel|window(-1,2.5)|label").unwrap();
        assert_eq!(p.ops[0], Op::GradMag(Sigma::Voxels([3.0, 2.0, 1.0])));
        assert_eq!(p.ops[3], Op::Label(26));
        let p = Pipeline::parse("gauss(1.5um)").unwrap();
        assert_eq!(
            p.ops[0],
            Op::Gauss(Sigma::Physical {
                value: [1.5; 3],
                unit: "micrometer".into()
            })
        );
        assert!(!p.is_label_output());
        assert_eq!(p.text(), "gauss(1.5um)");
    }

    #[test]
    fn medians_parse_x_first_and_refuse_what_is_not_a_small_radius() {
        let p = Pipeline::parse("median(1)|median(2,0,1)").unwrap();
        assert_eq!(p.ops, vec![Op::Median([1; 3]), Op::Median([1, 0, 2])]);
        assert_eq!(p.text(), "median(1)|median(2,0,1)");
        for bad in ["median(1.5)", "median(-1)", "median(8)", "median(x)"] {
            let e = Pipeline::parse(bad).unwrap_err();
            assert!(
                e.expected.contains("whole number from 0 to 7"),
                "{bad}: {e}"
            );
        }
        let e = Pipeline::parse("median(1,2)").unwrap_err();
        assert!(e.expected.contains("one radius or three"), "{e}");
        let e = Pipeline::parse("medain(1)").unwrap_err();
        assert!(e.expected.contains("median(R)"), "{e}");
    }

    #[test]
    fn errors_name_the_token() {
        let e = Pipeline::parse("gauss(1.5)|treshold(3)").unwrap_err();
        assert_eq!(e.token, "treshold");
        assert_eq!(e.pos, 11);
        assert!(e.to_string().contains("threshold(T)"), "{e}");
        let e = Pipeline::parse("gauss(abc)").unwrap_err();
        assert_eq!(e.token, "abc");
        assert!(e.expected.contains("σ"));
        let e = Pipeline::parse("gauss(-1)").unwrap_err();
        assert_eq!(e.token, "-1");
        let e = Pipeline::parse("gauss(1.5").unwrap_err();
        assert!(e.expected.contains("')'"));
        let e = Pipeline::parse("label(8)").unwrap_err();
        assert_eq!(e.token, "8");
        let e = Pipeline::parse("label(6)|gauss(1)").unwrap_err();
        assert!(e.expected.contains("last stage"));
        let e = Pipeline::parse("gauss(1)|threshold(0)|label(6)| label(6)").unwrap_err();
        assert!(e.expected.contains("last stage"));
        assert_eq!((e.token.as_str(), e.pos), ("label(6)", 22));
        let e = Pipeline::parse("gauss(1)||sobel").unwrap_err();
        assert_eq!(e.pos, 9);
        let e = Pipeline::parse("window(3,1)").unwrap_err();
        assert!(e.expected.contains("LO <= HI"));
        let e = Pipeline::parse("gauss(1,2)").unwrap_err();
        assert!(e.expected.contains("found 2"), "{e}");
        let e = Pipeline::parse("gauss(1um,2mm,1um)").unwrap_err();
        assert_eq!(e.token, "2mm");
        let e = Pipeline::parse("gauss(1furlong)").unwrap_err();
        assert!(e.expected.contains("unit"));
        let e = Pipeline::parse("sobel(2)").unwrap_err();
        assert!(e.expected.contains("no arguments"));
        assert!(Pipeline::parse("").is_err());
    }
}
