//! The measured spectra Tessera ships, compiled in from `crates/render/data/spectra` (sources and
//! licences in its SOURCES.md): CIE 1931 2 degree colour matching functions, illuminants D65 and
//! A, the 24 ColorChecker reflectances, metal n and k, and the Cornell box spectra. Parsed once.

use super::Spectrum;
use std::sync::OnceLock;

const CMF_CSV: &str = include_str!("../../data/spectra/cie1931_2deg_cmf.csv");
const D65_CSV: &str = include_str!("../../data/spectra/cie_d65.csv");
const A_CSV: &str = include_str!("../../data/spectra/cie_a.csv");
const CHECKER_CSV: &str = include_str!("../../data/spectra/colorchecker_reflectance.csv");
const METAL_CSV: &str = include_str!("../../data/spectra/metal_eta_k.csv");
const CORNELL_CSV: &str = include_str!("../../data/spectra/cornell_box_spectra.csv");

/// Rows of numbers after the header; the shipped files are known good, so a bad cell is a bug.
fn rows(csv: &str) -> impl Iterator<Item = Vec<&str>> {
    csv.lines().skip(1).filter(|l| !l.trim().is_empty()).map(|l| l.split(',').map(str::trim).collect())
}

fn num(cell: &str) -> f64 {
    cell.parse().unwrap_or_else(|_| panic!("shipped spectral table has a bad number '{cell}'"))
}

/// Column `c` of a wide table against its first column.
fn column(csv: &str, c: usize) -> Spectrum {
    Spectrum::new(rows(csv).map(|r| (num(r[0]), num(r[c]))).collect())
}

/// x̄, ȳ, z̄ of the CIE 1931 2 degree observer, 360-830 nm at 1 nm.
pub fn cmf() -> &'static [Spectrum; 3] {
    static CMF: OnceLock<[Spectrum; 3]> = OnceLock::new();
    CMF.get_or_init(|| [column(CMF_CSV, 1), column(CMF_CSV, 2), column(CMF_CSV, 3)])
}

/// CIE D65, relative spectral power (100 at 560 nm), 300-830 nm.
pub fn d65() -> &'static Spectrum {
    static D65: OnceLock<Spectrum> = OnceLock::new();
    D65.get_or_init(|| column(D65_CSV, 1))
}

/// CIE illuminant A (2856 K Planckian), relative spectral power, 300-830 nm.
pub fn illuminant_a() -> &'static Spectrum {
    static A: OnceLock<Spectrum> = OnceLock::new();
    A.get_or_init(|| column(A_CSV, 1))
}

/// The 24 ColorChecker patches in chart order (row-major from dark skin to black), with names.
pub fn colorchecker() -> &'static [(String, Spectrum)] {
    static CHECKER: OnceLock<Vec<(String, Spectrum)>> = OnceLock::new();
    CHECKER.get_or_init(|| {
        let header: Vec<&str> = CHECKER_CSV.lines().next().unwrap_or_default().split(',').collect();
        (1..header.len()).map(|c| (header[c].trim().to_string(), column(CHECKER_CSV, c))).collect()
    })
}

/// Named metals with measured complex index of refraction n + ik (pbrt-v4's tables).
pub const METALS: [&str; 4] = ["Au", "Ag", "Cu", "Al"];

/// (n, k) of a named metal (`Au`, `Ag`, `Cu`, `Al`; case-insensitive).
pub fn metal(name: &str) -> Option<&'static (Spectrum, Spectrum)> {
    static TABLE: OnceLock<Vec<(&'static str, (Spectrum, Spectrum))>> = OnceLock::new();
    let table = TABLE.get_or_init(|| {
        METALS
            .iter()
            .map(|m| {
                let pick = |col: usize| {
                    Spectrum::new(rows(METAL_CSV).filter(|r| r[0] == *m).map(|r| (num(r[1]), num(r[col]))).collect())
                };
                (*m, (pick(2), pick(3)))
            })
            .collect()
    });
    table.iter().find(|(m, _)| m.eq_ignore_ascii_case(name)).map(|(_, nk)| nk)
}

/// The Cornell box's measured spectra: `white`, `green`, `red` reflectances (400-700 nm) and the
/// `light`'s relative emission (four points, 400-700 nm).
pub fn cornell(name: &str) -> Option<&'static Spectrum> {
    static TABLE: OnceLock<Vec<(&'static str, Spectrum)>> = OnceLock::new();
    let table = TABLE.get_or_init(|| {
        ["white", "green", "red", "light"]
            .iter()
            .map(|s| {
                (*s, Spectrum::new(rows(CORNELL_CSV).filter(|r| r[0] == *s).map(|r| (num(r[1]), num(r[2]))).collect()))
            })
            .collect()
    });
    table.iter().find(|(s, _)| *s == name).map(|(_, sp)| sp)
}
