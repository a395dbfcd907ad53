//! SVG export (docs/design.md#export-svg): one black `rect` per fabricated rectangle.

use std::fmt::Write as _;

use super::geometry::ExportFrame;
use crate::pattern_file::Pattern;

/// A number with at most 15 significant digits, shortest form (`7`, `0.25`, `3013.5`).
pub(crate) fn fmt15(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return "0".into();
    }
    // Round to 15 significant digits, then print the shortest representation of that value.
    let rounded: f64 = format!("{v:.14e}").parse().unwrap_or(v);
    format!("{rounded}")
}

/// Escapes the XML special characters of a text node or attribute value.
fn xml_escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for ch in text.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            // XML 1.0 forbids most control characters.
            c if c.is_control() && c != '\n' && c != '\t' => {}
            c => out.push(c),
        }
    }
    out
}

/// The SVG document of `pattern`.
///
/// * `viewBox` = the export canvas (frame + margins) in **pattern units** (µm), y down, so the
///   rectangles keep their layout positions plus margins; for a whole layout it is
///   `0 0 W H` as in the original. For a Megarena region of interest it starts at the
///   region's first dot cell, so dots keep their absolute positions.
/// * `width`/`height` give the physical size in mm (pattern unit taken as µm), so drawing
///   tools open the file at scale (the original wrote unitless numbers).
/// * `title` = description; `desc` lists class, description, date, author, unit, width,
///   height, originX, originY and the four margins, one `key: value` per line.
/// * one `<rect x y width height fill="black"/>` per rectangle, 15 significant digits.
pub fn write_svg(pattern: &Pattern) -> String {
    let mut out = Vec::new();
    // Writing into a Vec cannot fail, and the text is UTF-8 by construction.
    let _ = write_svg_to(pattern, &mut out, &mut |_| {});
    String::from_utf8(out).unwrap_or_default()
}

/// Streams the document of [`write_svg`] into `sink` (no copy of the whole file in memory),
/// calling `progress` with the number of rectangles written so far every 65536 rectangles.
/// The first write error stops the output and is returned.
pub fn write_svg_to(
    pattern: &Pattern,
    sink: &mut dyn std::io::Write,
    progress: &mut dyn FnMut(u64),
) -> std::io::Result<()> {
    let layout = pattern.layout();
    let frame = ExportFrame::of(pattern);
    let meta = layout.metadata();
    let c = frame.canvas;
    let mut out = String::new();
    // `write!` into a String cannot fail.
    let _ = writeln!(
        out,
        "<?xml version=\"1.0\" encoding=\"UTF-8\" standalone=\"no\"?>\n\
         <!-- Created with the Vernier library -->\n\
         <svg xmlns=\"http://www.w3.org/2000/svg\" version=\"1.1\" x=\"0\" y=\"0\" \
         width=\"{}mm\" height=\"{}mm\" viewBox=\"{} {} {} {}\">",
        fmt15(c.width / 1000.0),
        fmt15(c.height / 1000.0),
        fmt15(c.x),
        fmt15(c.y),
        fmt15(c.width),
        fmt15(c.height),
    );
    let _ = writeln!(out, "<title>{}</title>", xml_escape(&meta.description));
    let m = meta.margins;
    let b = layout.bounds();
    let fields = [
        ("class", layout.class_name().to_string()),
        ("description", meta.description.clone()),
        ("date", meta.date.clone()),
        ("author", meta.author.clone()),
        ("unit", meta.unit.clone()),
        ("width", fmt15(b.width)),
        ("height", fmt15(b.height)),
        ("originX", fmt15(frame.origin.0)),
        ("originY", fmt15(frame.origin.1)),
        ("leftMargin", fmt15(m.left)),
        ("rightMargin", fmt15(m.right)),
        ("topMargin", fmt15(m.top)),
        ("bottomMargin", fmt15(m.bottom)),
    ];
    out.push_str("<desc>\n");
    for (key, value) in fields {
        let _ = writeln!(out, "{key}: {}", xml_escape(&value));
    }
    out.push_str("</desc>\n");
    sink.write_all(out.as_bytes())?;
    let mut result = Ok(());
    let mut count = 0u64;
    let mut line = String::new();
    frame.visit_rects(layout, &mut |r| {
        if result.is_err() {
            return;
        }
        line.clear();
        let _ = writeln!(
            line,
            "<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"black\" />",
            fmt15(r.x),
            fmt15(r.y),
            fmt15(r.width),
            fmt15(r.height)
        );
        result = sink.write_all(line.as_bytes());
        count += 1;
        if count % 65536 == 0 {
            progress(count);
        }
    });
    result?;
    progress(count);
    sink.write_all(b"</svg>\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_have_15_significant_digits() {
        assert_eq!(fmt15(7.0), "7");
        assert_eq!(fmt15(0.1 + 0.2), "0.3");
        assert_eq!(fmt15(-2.5), "-2.5");
        assert_eq!(fmt15(123_456.789_012_345_67), "123456.789012346");
        assert_eq!(fmt15(f64::NAN), "0");
    }

    #[test]
    fn escapes_markup() {
        assert_eq!(xml_escape("a<b & \"c\">"), "a&lt;b &amp; &quot;c&quot;&gt;");
    }
}
