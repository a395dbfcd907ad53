//! Layout export for fabrication and documentation (docs/design.md#export): PNG, SVG, GDSII, OASIS.
//!
//! Every format draws the rectangles of the pattern's **export frame** (the whole layout, or
//! the dot cells of a Megarena's region of interest, [`ExportFrame`]) with the margins of
//! its metadata added (`u' = u + left`, `v' = v + top`). Lengths are in the pattern unit,
//! taken as µm where a physical unit is needed (SVG size in mm, GDSII/OASIS database unit
//! 1 nm, user unit 1 µm, y axis negated, dots on layer 1 / datatype 1).
//!
//! GDSII and OASIS are written by this module (no toolkit): regular dot grids become arrays
//! (GDSII AREF of a one-dot cell, OASIS repetitions), so a 10⁵-dot Megarena region is a
//! few hundred records and exports in milliseconds ([`geometry::dot_arrays`]).
//!
//! Differences from the original, on purpose: no progress printing (its `i mod (count/100)`
//! divided by zero below 100 rectangles), the GDSII default extension is `.gds` (not
//! `.oas`), the HP-code finders are complete in every format, the label is written as text
//! elements (not stroke-font polygons), and the OASIS file is not deflate-compressed.

mod gds;
pub mod geometry;
mod oasis;
mod png;
mod svg;

use std::path::Path;

pub use geometry::{dot_arrays, DbRect, DotArray, ExportFrame, DB_PER_UNIT};
pub use png::{layout_image, write_png, MAX_PNG_PIXELS};
pub use svg::{write_svg, write_svg_to};

use crate::error::{Error, Result};
use crate::layout::Layout;
use crate::pattern_file::Pattern;

/// Layer and datatype of the fabricated dots in GDSII and OASIS (docs/design.md#export-gds-oasis).
pub const DOT_LAYER: (i16, i16) = (1, 1);
/// Layer and text type of the descriptive label in GDSII and OASIS.
pub const LABEL_LAYER: (i16, i16) = (2, 0);

/// An export file format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ExportFormat {
    /// 8-bit grey PNG, one pixel per half-period cell, white = dot (docs/design.md#export-png).
    Png,
    /// SVG, one black rectangle per dot, viewBox in pattern units (docs/design.md#export-svg).
    Svg,
    /// GDSII stream (docs/design.md#export-gds-oasis).
    Gds,
    /// OASIS (docs/design.md#export-gds-oasis).
    Oasis,
}

impl ExportFormat {
    /// All formats.
    pub const ALL: [ExportFormat; 4] = [
        ExportFormat::Png,
        ExportFormat::Svg,
        ExportFormat::Gds,
        ExportFormat::Oasis,
    ];

    /// Usual file extension, without the dot: `png`, `svg`, `gds`, `oas`.
    pub fn extension(self) -> &'static str {
        match self {
            ExportFormat::Png => "png",
            ExportFormat::Svg => "svg",
            ExportFormat::Gds => "gds",
            ExportFormat::Oasis => "oas",
        }
    }

    /// Format of a file extension or format name (case-insensitive): `png`, `svg`,
    /// `gds`/`gds2`/`gdsii`, `oas`/`oasis`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "png" => Some(ExportFormat::Png),
            "svg" => Some(ExportFormat::Svg),
            "gds" | "gds2" | "gdsii" => Some(ExportFormat::Gds),
            "oas" | "oasis" => Some(ExportFormat::Oasis),
            _ => None,
        }
    }

    /// Format given by the extension of `path`, if known.
    pub fn from_path(path: &Path) -> Option<Self> {
        path.extension()
            .and_then(|e| e.to_str())
            .and_then(Self::from_name)
    }
}

impl std::str::FromStr for ExportFormat {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Self::from_name(s).ok_or_else(|| {
            Error::parameter(
                "format",
                format!("unknown export format `{s}`; expected png, svg, gds or oas"),
            )
        })
    }
}

/// The descriptive text of a GDSII/OASIS export, in database units (y up).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Label {
    /// Printable-ASCII lines, top to bottom.
    pub lines: Vec<String>,
    /// Anchor of the first line.
    pub x: i64,
    /// Anchor of the first line (y up).
    pub y: i64,
    /// Text height; lines are 1.5 heights apart.
    pub height: i64,
    /// (layer, text type).
    pub layer: (i16, i16),
}

/// Everything the GDSII and OASIS writers need.
pub(crate) struct Drawing<'a> {
    /// Library and top-cell name: the class name.
    pub name: &'a str,
    pub arrays: &'a [DotArray],
    pub dot_layer: (i16, i16),
    pub label: Label,
    /// Year, month, day, hour, minute, second written as the GDSII library dates.
    pub timestamp: [i16; 6],
}

/// Printable ASCII only (OASIS a-strings, GDSII strings): `µ` becomes `u`, others `?`.
fn ascii(text: &str) -> String {
    text.chars()
        .map(|c| match c {
            ' '..='~' => c,
            'µ' | 'μ' => 'u',
            _ => '?',
        })
        .collect()
}

/// Human-readable summary of a pattern (the label of GDSII/OASIS exports), one item a line.
pub fn describe(pattern: &Pattern) -> Vec<String> {
    let layout = pattern.layout();
    let meta = layout.metadata();
    let unit = if meta.unit.is_empty() {
        "um"
    } else {
        meta.unit.as_str()
    };
    let num = svg::fmt15;
    let mut lines = Vec::new();
    match pattern {
        Pattern::Periodic(l) => {
            lines.push(format!(
                "PeriodicPattern {} x {} dots",
                l.n_rows(),
                l.n_cols()
            ));
            lines.push(format!("dot size: {} {unit}", num(l.dot_size())));
        }
        Pattern::HpCode(l) => {
            lines.push(format!(
                "HPCodePattern {} x {} dots ({} half-periods)",
                l.size(),
                l.size(),
                l.code_size()
            ));
            lines.push(format!("id: {}", l.id()));
        }
        Pattern::Bitmap(l) => lines.push(format!(
            "BitmapPattern {} x {} cells",
            l.cell_rows(),
            l.cell_cols()
        )),
        Pattern::Fingerprint(l) => lines.push(format!(
            "FingerprintPattern {} x {} dots",
            l.n_rows(),
            l.n_cols()
        )),
        Pattern::Megarena(l) => {
            lines.push(format!("{}-bit MegarenaPattern", l.code_depth()));
            let r = l.region_of_interest();
            lines.push(format!(
                "region of interest: {}, {}, {}, {} {unit}",
                num(r.x),
                num(r.y),
                num(r.width),
                num(r.height)
            ));
        }
        Pattern::Custom(l) => lines.push(format!("CustomPattern {} rectangles", l.dots().len())),
    }
    if layout.period() > 0.0 {
        lines.insert(1, format!("period: {} {unit}", num(layout.period())));
    }
    if !meta.description.is_empty() {
        lines.push(meta.description.clone());
    }
    lines.iter().map(|l| ascii(l)).collect()
}

/// Parses `YYYY-MM-DD[ HH:MM:SS]` (the metadata date) into GDSII date fields; `None` when the
/// text has another form.
fn parse_date(text: &str) -> Option<[i16; 6]> {
    let numbers: Vec<i16> = text
        .split(|c: char| !c.is_ascii_digit())
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().ok())
        .collect::<Option<_>>()?;
    let mut out = [0i16; 6];
    if !(3..=6).contains(&numbers.len()) {
        return None;
    }
    out[..numbers.len()].copy_from_slice(&numbers);
    let valid = (1..=9999).contains(&out[0])
        && (1..=12).contains(&out[1])
        && (1..=31).contains(&out[2])
        && out[3] < 24
        && out[4] < 60
        && out[5] < 61;
    valid.then_some(out)
}

/// Current UTC time as GDSII date fields (civil date from the Unix day count).
fn now_utc() -> [i16; 6] {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Days since 1970-01-01 to a proleptic Gregorian date (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    [
        year as i16,
        month as i16,
        day as i16,
        (rem / 3600) as i16,
        (rem % 3600 / 60) as i16,
        (rem % 60) as i16,
    ]
}

/// Builds the GDSII/OASIS drawing of `pattern` and hands it to `write`; `progress` gets the
/// rectangles visited so far (see [`geometry::dot_arrays_with_progress`]).
fn with_drawing<T>(
    pattern: &Pattern,
    progress: &mut dyn FnMut(u64),
    write: impl FnOnce(&Drawing) -> Result<T>,
) -> Result<T> {
    let layout: &dyn Layout = pattern.layout();
    let frame = ExportFrame::of(pattern);
    let arrays = geometry::dot_arrays_with_progress(pattern, &frame, progress)?;
    // Label below the canvas, 8 × the first rectangle's height tall
    // (docs/design.md#export-gds-oasis).
    let height = arrays
        .first()
        .map_or((layout.period() * DB_PER_UNIT) as i64, |a| a.first.height)
        .max(1)
        * 8;
    let canvas = geometry::to_db(&frame.canvas)?;
    let label = Label {
        lines: describe(pattern),
        x: canvas.x,
        y: -(canvas.y + canvas.height + height),
        height,
        layer: LABEL_LAYER,
    };
    let drawing = Drawing {
        name: layout.class_name(),
        arrays: &arrays,
        dot_layer: DOT_LAYER,
        label,
        timestamp: parse_date(&layout.metadata().date).unwrap_or_else(now_utc),
    };
    write(&drawing)
}

/// Upper estimate of the number of rectangles an export of `pattern` draws: one per dot of the
/// exported frame for dot grids (periodic, Megarena), one per half-period cell for bitmaps,
/// fingerprints and HP codes, the rectangle count of custom patterns. Computed from the
/// frame alone (no rectangle is visited), so it is instant for any size.
pub fn estimate_rects(pattern: &Pattern) -> f64 {
    let frame = ExportFrame::of(pattern).frame;
    let p = pattern.layout().period();
    let cells = |pitch: f64| {
        if pitch > 0.0 {
            ((frame.width / pitch).ceil() + 1.0) * ((frame.height / pitch).ceil() + 1.0)
        } else {
            f64::INFINITY
        }
    };
    match pattern {
        Pattern::Periodic(_) | Pattern::Megarena(_) => cells(p),
        Pattern::Custom(l) => l.dots().len() as f64,
        Pattern::HpCode(_) | Pattern::Bitmap(_) | Pattern::Fingerprint(_) => cells(p / 2.0),
    }
}

/// Upper estimate of the size of the export of `pattern` in `format`, bytes, from
/// [`estimate_rects`] (SVG: about 80 bytes a rectangle; GDSII and OASIS: rows of dots become
/// arrays, counted as 2 bytes a rectangle; PNG: one byte a half-period cell).
pub fn estimate_bytes(pattern: &Pattern, format: ExportFormat) -> f64 {
    const HEADER: f64 = 4096.0;
    let rects = estimate_rects(pattern);
    HEADER
        + match format {
            ExportFormat::Svg => 80.0 * rects,
            ExportFormat::Gds | ExportFormat::Oasis => 2.0 * rects,
            ExportFormat::Png => {
                let frame = ExportFrame::of(pattern).canvas;
                let half = pattern.layout().period() / 2.0;
                if half > 0.0 {
                    (frame.width / half + 1.0) * (frame.height / half + 1.0)
                } else {
                    rects
                }
            }
        }
}

/// The file content of `pattern` in `format`.
///
/// Errors: PNG of a `CustomPattern` or of more than [`MAX_PNG_PIXELS`] pixels; GDSII/OASIS
/// coordinates beyond ±1 m (32-bit nm).
pub fn export_bytes(pattern: &Pattern, format: ExportFormat) -> Result<Vec<u8>> {
    export_bytes_with_progress(pattern, format, &mut |_| {})
}

/// [`export_bytes`], calling `progress` while a GDSII or OASIS drawing is built with the
/// rectangles visited so far, out of about twice [`estimate_rects`] (two passes; PNG and SVG
/// report nothing here: SVG streams with [`write_svg_to`]).
pub fn export_bytes_with_progress(
    pattern: &Pattern,
    format: ExportFormat,
    progress: &mut dyn FnMut(u64),
) -> Result<Vec<u8>> {
    match format {
        ExportFormat::Png => write_png(pattern),
        ExportFormat::Svg => Ok(write_svg(pattern).into_bytes()),
        ExportFormat::Gds => with_drawing(pattern, progress, gds::write_gds),
        ExportFormat::Oasis => with_drawing(pattern, progress, |d| Ok(oasis::write_oasis(d))),
    }
}

/// Writes `pattern` to `path` in `format` (the extension of `path` is not checked).
pub fn export_file(pattern: &Pattern, format: ExportFormat, path: impl AsRef<Path>) -> Result<()> {
    let path = path.as_ref();
    let bytes = export_bytes(pattern, format)?;
    crate::output::write_file(path, &bytes).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_and_extensions() {
        for f in ExportFormat::ALL {
            assert_eq!(ExportFormat::from_name(f.extension()), Some(f));
        }
        assert_eq!(
            ExportFormat::Gds.extension(),
            "gds",
            "not .oas as the original"
        );
        assert_eq!(
            ExportFormat::from_path(Path::new("a/b.GDS")),
            Some(ExportFormat::Gds)
        );
        assert!("dxf".parse::<ExportFormat>().is_err());
    }

    #[test]
    fn dates() {
        assert_eq!(
            parse_date("2025-03-17 08:40:25"),
            Some([2025, 3, 17, 8, 40, 25])
        );
        assert_eq!(parse_date("2022"), None);
        assert_eq!(parse_date("2022-13-01"), None);
        let now = now_utc();
        assert!(now[0] >= 2024 && (1..=12).contains(&now[1]) && (1..=31).contains(&now[2]));
    }

    #[test]
    fn labels_are_ascii() {
        let p = Pattern::from_json_str(
            r#"{"MegarenaPattern": {"unit": "µm", "codeDepth": 8, "period": 14.0,
                "description": "été"}}"#,
        )
        .unwrap();
        let lines = describe(&p);
        assert_eq!(lines[0], "8-bit MegarenaPattern");
        assert_eq!(lines[1], "period: 14 um");
        assert!(lines.iter().all(|l| l.is_ascii()), "{lines:?}");
    }
}
