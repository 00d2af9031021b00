//! How the store records a brick's range of values (`_brickyard/stats`,
//! docs/FORMAT.md "Statistics"), for its writers and every reader.

/// The range of the values other than NaN that a store brick's statistics
/// `(min, max)` record, `None` for a brick of NaN alone.
///
/// A brick whose values other than NaN are all equal to `v` but which also
/// holds NaN is recorded as `(v, NaN)`: as `(v, v)` it would read as
/// constant, and a reader that maps a constant brick without loading it
/// would draw its NaN voxels (transparent everywhere else) as `v`.
pub fn finite_range(mn: f64, mx: f64) -> Option<(f64, f64)> {
    match (mn.is_nan(), mx.is_nan()) {
        (true, _) => None,
        (false, true) => Some((mn, mn)),
        (false, false) => Some((mn, mx)),
    }
}

/// The statistics the store records for a brick whose values other than
/// NaN span `(mn, mx)` (NaN, NaN when there are none) and which holds NaN
/// or not (see [`finite_range`]).
pub fn recorded(mn: f64, mx: f64, has_nan: bool) -> (f64, f64) {
    if has_nan && mn == mx {
        (mn, f64::NAN)
    } else {
        (mn, mx)
    }
}
