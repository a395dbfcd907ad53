//! The original VERNIER program's result CSV as a pose table: semicolon separated, a header
//! `image;id;x;y;alpha;pixelSize;` with the five marker columns repeated per marker, then one
//! row per image. x, y are in pattern units (µm), alpha in rad, the pose convention as this
//! project's (origin at the image centre, x right, y down).

use std::path::Path;

use crate::pose_table::PoseRow;

/// Columns of one marker in the original's CSV.
const MARKER_COLUMNS: usize = 5;

/// True when `text` starts with the original's header (`image;` then marker columns).
pub fn is_reference_csv(text: &str) -> bool {
    let header = text
        .lines()
        .next()
        .unwrap_or("")
        .trim_start_matches('\u{feff}');
    let mut fields = header.split(';').map(str::trim);
    fields
        .next()
        .is_some_and(|f| f.eq_ignore_ascii_case("image"))
        && fields
            .next()
            .is_some_and(|f| f.eq_ignore_ascii_case("id") || f.eq_ignore_ascii_case("no"))
}

/// Parses the original's CSV `text` (read from `path`, named in errors) into pose rows: one
/// per image and marker, `frame` the row's index, `source` the image column. A row whose
/// markers repeat an ID (older files number every marker 0) takes the markers' order in the
/// row as IDs; the count of such rows is returned beside the rows.
pub fn parse_reference_csv(text: &str, path: &Path) -> Result<(Vec<PoseRow>, usize), String> {
    let mut rows = Vec::new();
    let mut renumbered = 0;
    let lines = text.lines().enumerate().skip(1);
    for (frame, (index, line)) in lines.filter(|(_, l)| !l.trim().is_empty()).enumerate() {
        let at = || format!("{} line {}", path.display(), index + 1);
        let mut fields: Vec<&str> = line.split(';').map(str::trim).collect();
        while fields.last() == Some(&"") {
            fields.pop();
        }
        let Some((image, markers)) = fields.split_first() else {
            continue;
        };
        if markers.len() % MARKER_COLUMNS != 0 {
            return Err(format!(
                "{}: {} fields after the image, not a multiple of {MARKER_COLUMNS} \
                 (id;x;y;alpha;pixelSize per marker)",
                at(),
                markers.len()
            ));
        }
        let number = |column: usize, value: &str| -> Result<f64, String> {
            value
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{}, field {}: `{value}` is not a number", at(), column + 2))
        };
        let mut parsed = Vec::new();
        for (m, group) in markers.chunks(MARKER_COLUMNS).enumerate() {
            let base = m * MARKER_COLUMNS;
            let id = group[0].parse::<u64>().map_err(|_| {
                format!(
                    "{}, field {}: `{}` is not a marker ID",
                    at(),
                    base + 2,
                    group[0]
                )
            })?;
            let value = |k: usize| number(base + k, group[k]);
            parsed.push((id, value(1)?, value(2)?, value(3)?, value(4)?));
        }
        let mut ids: Vec<u64> = parsed.iter().map(|p| p.0).collect();
        ids.sort_unstable();
        let repeated = ids.windows(2).any(|w| w[0] == w[1]);
        renumbered += usize::from(repeated);
        for (m, (id, x, y, alpha, pixel_size)) in parsed.into_iter().enumerate() {
            rows.push(PoseRow {
                frame: frame as u64,
                source: image.to_string(),
                id: Some(if repeated { m as u64 } else { id }),
                x: Some(x),
                y: Some(y),
                alpha: Some(alpha),
                pixel_size: Some(pixel_size),
                ..PoseRow::default()
            });
        }
    }
    if rows.is_empty() {
        return Err(format!(
            "{}: no marker row after the header",
            path.display()
        ));
    }
    Ok((rows, renumbered))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_originals_csv() {
        let text = "image;id;x;y;alpha;pixelSize;id;x;y;alpha;pixelSize;\n\
                    96;0;33.9;-618.4;-1.49;1.04;1;46.6;98.1;-1.55;1.04;\n\n\
                    97;0;34.1;-618.3;-1.48;1.04;1;47.1;98.2;-1.54;1.04;\n";
        assert!(is_reference_csv(text));
        let (rows, renumbered) = parse_reference_csv(text, Path::new("r.csv")).expect("valid");
        assert_eq!((rows.len(), renumbered), (4, 0));
        assert_eq!(
            (rows[3].frame, rows[3].id, rows[3].x),
            (1, Some(1), Some(47.1))
        );
        assert_eq!(rows[3].source, "97");
        // Every marker labelled 0: the order in the row gives the IDs.
        let old = "image;no;x;y;alpha;pixelSize;no;x;y;alpha;pixelSize;\n\
                   96;0;1;2;3;4;0;5;6;7;8;\n";
        let (rows, renumbered) = parse_reference_csv(old, Path::new("o.csv")).expect("valid");
        assert_eq!((rows[1].id, rows[1].x, renumbered), (Some(1), Some(5.0), 1));
    }

    #[test]
    fn bad_rows_are_named() {
        assert!(!is_reference_csv("frame,id,x\n"));
        let short = "image;id;x;y;alpha;pixelSize\n96;0;1;2;3\n";
        let e = parse_reference_csv(short, Path::new("r.csv")).expect_err("short row");
        assert!(e.contains("line 2") && e.contains("multiple of 5"), "{e}");
        let nan = "image;id;x;y;alpha;pixelSize\n96;0;1;x;3;4\n";
        let e = parse_reference_csv(nan, Path::new("r.csv")).expect_err("not a number");
        assert!(e.contains("field 4") && e.contains("`x`"), "{e}");
        let empty = "image;id;x;y;alpha;pixelSize\n";
        assert!(parse_reference_csv(empty, Path::new("r.csv")).is_err());
    }
}
