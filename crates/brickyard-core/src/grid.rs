//! Voxel grids in world space: units of length, and whether two volumes
//! lie on the same grid (a label image over its image).

/// Units accepted by OME-NGFF for space axes (UDUNITS-2 names).
pub const SPACE_UNITS: &[&str] = &[
    "angstrom",
    "attometer",
    "centimeter",
    "decimeter",
    "exameter",
    "femtometer",
    "foot",
    "gigameter",
    "hectometer",
    "inch",
    "kilometer",
    "megameter",
    "meter",
    "micrometer",
    "mile",
    "millimeter",
    "nanometer",
    "parsec",
    "petameter",
    "picometer",
    "terameter",
    "yard",
    "yoctometer",
    "yottameter",
    "zeptometer",
    "zettameter",
];

/// The length of one `unit` (an OME-NGFF space unit name, or a spelling
/// [`normalize_unit`] knows) in meters; `None` for a name it does not know.
pub fn unit_in_meters(unit: &str) -> Option<f64> {
    Some(match normalize_unit(unit)?.as_str() {
        "angstrom" => 1e-10,
        "attometer" => 1e-18,
        "centimeter" => 1e-2,
        "decimeter" => 1e-1,
        "exameter" => 1e18,
        "femtometer" => 1e-15,
        "foot" => 0.3048,
        "gigameter" => 1e9,
        "hectometer" => 1e2,
        "inch" => 0.0254,
        "kilometer" => 1e3,
        "megameter" => 1e6,
        "meter" => 1.0,
        "micrometer" => 1e-6,
        "mile" => 1609.344,
        "millimeter" => 1e-3,
        "nanometer" => 1e-9,
        "parsec" => 3.085_677_581_491_367e16,
        "petameter" => 1e15,
        "picometer" => 1e-12,
        "terameter" => 1e12,
        "yard" => 0.9144,
        "yoctometer" => 1e-24,
        "yottameter" => 1e24,
        "zeptometer" => 1e-21,
        "zettameter" => 1e21,
        _ => return None,
    })
}

/// Normalize common unit spellings to OME-NGFF names.
pub fn normalize_unit(u: &str) -> Option<String> {
    let t = u.trim().to_ascii_lowercase();
    let n = match t.as_str() {
        "mm" => "millimeter",
        "um" | "µm" | "μm" | "micron" | "microns" => "micrometer",
        "nm" => "nanometer",
        "m" => "meter",
        "cm" => "centimeter",
        "pm" => "picometer",
        "a" | "å" => "angstrom",
        _ => t.as_str(),
    };
    SPACE_UNITS.contains(&n).then(|| n.to_string())
}

/// A unit a user names (a flag, a sidecar, a Python keyword): its OME-NGFF
/// name, or the message saying what was expected. Units read from an
/// input's header go through [`normalize_unit`] instead, which drops one it
/// does not know.
pub fn known_unit(u: &str) -> Result<String, String> {
    normalize_unit(u).ok_or_else(|| {
        format!(
            "unknown unit {u:?}; expected one of OME-Zarr's space units ({}) or mm, um, nm, cm, m",
            SPACE_UNITS.join(", ")
        )
    })
}

/// A volume's grid: voxels, spacing and origin `[z, y, x]` (the centre of
/// voxel 0), and the unit of both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid<'a> {
    pub dims: [u64; 3],
    pub spacing: [f64; 3],
    pub origin: [f64; 3],
    pub unit: Option<&'a str>,
}

impl Grid<'_> {
    /// Whether `other` lies on this grid: the same voxels, spacing (within
    /// a millionth) and origin (within a millionth of a voxel), compared in
    /// this grid's unit where both units are known (numbers as they are
    /// otherwise). `Err`: how the two differ, `other` first, for a message.
    pub fn same_as(&self, other: &Grid) -> Result<(), String> {
        let meters = |g: &Grid| g.unit.and_then(unit_in_meters);
        let scale = match (meters(self), meters(other)) {
            (Some(a), Some(b)) => b / a,
            _ => 1.0,
        };
        let (sa, oa) = (self.spacing, self.origin);
        let (sb, ob) = (
            other.spacing.map(|v| v * scale),
            other.origin.map(|v| v * scale),
        );
        let close = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol;
        let same_spacing = (0..3).all(|i| close(sa[i], sb[i], 1e-6 * sa[i].abs().max(sb[i].abs())));
        let same_origin = (0..3).all(|i| close(oa[i], ob[i], 1e-6 * sa[i].abs()));
        if self.dims == other.dims && same_spacing && same_origin {
            return Ok(());
        }
        let describe = |g: &Grid| {
            format!(
                "{:?} voxels of {:?} at {:?}{} (z, y, x)",
                g.dims,
                g.spacing,
                g.origin,
                g.unit.map(|u| format!(" {u}")).unwrap_or_default()
            )
        };
        Err(format!("{}, against {}", describe(other), describe(self)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(spacing: [f64; 3], origin: [f64; 3], unit: Option<&str>) -> Grid<'_> {
        Grid {
            dims: [10, 20, 30],
            spacing,
            origin,
            unit,
        }
    }

    #[test]
    fn units_and_grids() {
        assert_eq!(unit_in_meters("µm"), Some(1e-6));
        assert_eq!(unit_in_meters("millimeter"), Some(1e-3));
        assert_eq!(unit_in_meters("parsnip"), None);
        assert_eq!(known_unit(" UM ").as_deref(), Ok("micrometer"));
        let e = known_unit("parsnip").unwrap_err();
        assert!(e.contains("\"parsnip\"") && e.contains("millimeter"), "{e}");
        let um = grid([0.5, 0.26, 0.26], [0.25, 0.13, 0.13], Some("micrometer"));
        // The same grid in nanometers, and without units.
        assert!(um
            .same_as(&grid(
                [500.0, 260.0, 260.0],
                [250.0, 130.0, 130.0],
                Some("nanometer")
            ))
            .is_ok());
        assert!(um
            .same_as(&grid([0.5, 0.26, 0.26], [0.25, 0.13, 0.13], None))
            .is_ok());
        // The same numbers in millimeters: a grid 1000 times larger.
        let e = um
            .same_as(&grid(
                [0.5, 0.26, 0.26],
                [0.25, 0.13, 0.13],
                Some("millimeter"),
            ))
            .unwrap_err();
        assert!(e.contains("millimeter") && e.contains("micrometer"), "{e}");
        // Shifted by 50 voxels in x; by a hundred-millionth of one (same).
        assert!(um
            .same_as(&grid(
                [0.5, 0.26, 0.26],
                [0.25, 0.13, 13.13],
                Some("micrometer")
            ))
            .is_err());
        assert!(um
            .same_as(&grid(
                [0.5, 0.26, 0.26],
                [0.25, 0.13, 0.13 + 2.6e-9],
                Some("micrometer")
            ))
            .is_ok());
        // Other voxels.
        let mut other = um;
        other.dims = [10, 20, 31];
        assert!(um.same_as(&other).is_err());
    }
}
