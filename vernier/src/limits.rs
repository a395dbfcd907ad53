//! Resource limits and the physical range of every user setting, in one place.
//!
//! Every entry point (CLI flags, pattern files, `vernier bag --params`, the ROS node's `-p`,
//! parameter files and `set_parameters`) validates with these functions, so a value is
//! accepted or rejected the same way everywhere, with a message naming the setting.
//!
//! Lengths are in pattern units (the unit of the period, µm by convention), image sizes in
//! pixels, rates in Hz.

use crate::error::{Error, Result};

/// Default largest image accepted by any decoder or buffer conversion, pixels (100 MP).
/// CLI `--max-pixels`, node parameter `max_image_pixels`.
pub const DEFAULT_MAX_PIXELS: u64 = 100_000_000;

/// Bytes per pixel the decoders may allocate at most (16-bit RGBA), used with the pixel limit
/// to bound a decode's allocation.
pub const MAX_DECODED_BYTES_PER_PIXEL: u64 = 8;

/// Largest image file read into memory beyond `max_pixels · 8` bytes (headers, metadata,
/// badly compressed data), bytes.
pub const FILE_SIZE_SLACK: u64 = 64 << 20;

/// Smallest period accepted anywhere, pattern units (1e-6 µm = 1 fm: below it, the pixel size
/// underflows to denormals and poses lose all meaning).
pub const MIN_PERIOD: f64 = 1e-6;
/// Largest period accepted anywhere, pattern units (1e6 µm = 1 m).
pub const MAX_PERIOD: f64 = 1e6;

/// Smallest pixel size (pattern units per pixel) accepted by `render`.
pub const MIN_PIXEL_SIZE: f64 = 1e-9;
/// Largest pixel size (pattern units per pixel) accepted by `render`.
pub const MAX_PIXEL_SIZE: f64 = 1e9;
/// Smallest rendered period, pixels: finer grids only alias, and their dot count explodes.
pub const MIN_RENDER_PERIOD_PX: f64 = 0.5;

/// Smallest HP code width, half-period cells (9 dots per side: three finders and one ID bit).
pub const MIN_CODE_SIZE: usize = 17;
/// Largest HP code width, half-period cells.
pub const MAX_CODE_SIZE: usize = 1001;

/// Smallest Megarena LFSR code depth, bits.
pub const MIN_CODE_DEPTH: u32 = crate::megarena_sequence::MIN_CODE_DEPTH;
/// Largest Megarena LFSR code depth, bits.
pub const MAX_CODE_DEPTH: u32 = crate::megarena_sequence::MAX_CODE_DEPTH;

/// Smallest analysis window side, pixels (the detectors add their own, stricter minimum).
pub const MIN_WINDOW_SIZE: usize = 8;
/// Largest analysis window side, pixels.
pub const MAX_WINDOW_SIZE: usize = 32_768;

/// Largest rendered image, pixels (as the decode limit).
pub const MAX_RENDER_PIXELS: u64 = DEFAULT_MAX_PIXELS;
/// Largest render side, pixels.
pub const MAX_RENDER_SIDE: usize = 65_535;
/// Largest optical blur σ of `render`, pixels.
pub const MAX_BLUR_SIGMA: f64 = 100.0;
/// Largest additive noise σ of `render`, fraction of full scale.
pub const MAX_NOISE_STD: f64 = 10.0;

/// Largest processing rate cap of the node, Hz.
pub const MAX_RATE: f64 = 1e6;

/// Default largest export written without `--force`, bytes (estimated before writing).
pub const DEFAULT_MAX_EXPORT_BYTES: u64 = 512 << 20;

/// Largest parameter file (YAML) read, bytes.
pub const MAX_PARAM_FILE_BYTES: u64 = 1 << 20;
/// Largest YAML document after alias expansion, nodes (scalars, sequences and maps).
pub const MAX_YAML_NODES: u64 = 100_000;
/// Deepest YAML nesting.
pub const MAX_YAML_DEPTH: usize = 64;
/// Largest pattern file (JSON) read, bytes.
pub const MAX_PATTERN_FILE_BYTES: u64 = 64 << 20;

/// A number as users read it: plain (`15.5`), in exponent form when tiny or huge (`5e-324`).
fn show(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

fn range_error(name: &'static str, value: impl std::fmt::Display, range: String) -> Error {
    Error::parameter(name, format!("must be {range}, got {value}"))
}

/// Checks a period, pattern units: finite, in [`MIN_PERIOD`]`..=`[`MAX_PERIOD`].
pub fn check_period(value: f64) -> Result<f64> {
    if value.is_finite() && (MIN_PERIOD..=MAX_PERIOD).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            "period",
            show(value),
            format!("a length in [{MIN_PERIOD:e}, {MAX_PERIOD:e}] pattern units"),
        ))
    }
}

/// Checks a pixel size, pattern units per pixel: finite, in
/// [`MIN_PIXEL_SIZE`]`..=`[`MAX_PIXEL_SIZE`].
pub fn check_pixel_size(value: f64) -> Result<f64> {
    if value.is_finite() && (MIN_PIXEL_SIZE..=MAX_PIXEL_SIZE).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            "pixel_size",
            show(value),
            format!("in [{MIN_PIXEL_SIZE:e}, {MAX_PIXEL_SIZE:e}] pattern units per pixel"),
        ))
    }
}

/// Checks an HP code width `W`, half-period cells: `≡ 1 (mod 4)`, in
/// [`MIN_CODE_SIZE`]`..=`[`MAX_CODE_SIZE`].
pub fn check_code_size(value: usize) -> Result<usize> {
    if value % 4 == 1 && (MIN_CODE_SIZE..=MAX_CODE_SIZE).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            "code_size",
            value,
            format!(
                "an HP code width in half periods ≡ 1 (mod 4) in {MIN_CODE_SIZE}..={MAX_CODE_SIZE} (33, 37, ...)"
            ),
        ))
    }
}

/// Checks a Megarena code depth, bits: [`MIN_CODE_DEPTH`]`..=`[`MAX_CODE_DEPTH`].
pub fn check_code_depth(value: u32) -> Result<u32> {
    if (MIN_CODE_DEPTH..=MAX_CODE_DEPTH).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            "code_depth",
            value,
            format!("in {MIN_CODE_DEPTH}..={MAX_CODE_DEPTH} bits"),
        ))
    }
}

/// Checks an analysis window side, pixels: [`MIN_WINDOW_SIZE`]`..=`[`MAX_WINDOW_SIZE`].
pub fn check_window_size(value: usize) -> Result<usize> {
    if (MIN_WINDOW_SIZE..=MAX_WINDOW_SIZE).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            "window_size",
            value,
            format!("in {MIN_WINDOW_SIZE}..={MAX_WINDOW_SIZE} pixels"),
        ))
    }
}

/// Checks that a window of `window` pixels fits an image of `width × height` pixels along at
/// least one side, and covers at most [`MAX_WINDOW_AREA_RATIO`] times the image's pixels (a
/// larger window holds no more of the image, only fill, and its memory is unbounded by the
/// image's).
pub fn check_window_fits(window: usize, width: usize, height: usize) -> Result<()> {
    let area = (window as u64).saturating_mul(window as u64);
    let pixels = (width as u64).saturating_mul(height as u64);
    if window > width.max(height) || area > pixels.saturating_mul(MAX_WINDOW_AREA_RATIO) {
        return Err(Error::parameter(
            "window_size",
            format!(
                "{window} pixels is larger than the {width}×{height} image (at most its larger \
                 side and {MAX_WINDOW_AREA_RATIO} times its area)"
            ),
        ));
    }
    Ok(())
}

/// Largest window area, in multiples of the image's pixel count.
pub const MAX_WINDOW_AREA_RATIO: u64 = 4;

/// Checks a quality threshold (`name`): in `[0, 1]`.
pub fn check_quality(name: &'static str, value: f64) -> Result<f64> {
    if (0.0..=1.0).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(name, show(value), "in [0, 1]".into()))
    }
}

/// Checks a processing-rate cap, Hz: `0` (no limit) to [`MAX_RATE`].
pub fn check_rate(name: &'static str, value: f64) -> Result<f64> {
    if (0.0..=MAX_RATE).contains(&value) {
        Ok(value)
    } else {
        Err(range_error(
            name,
            show(value),
            format!("in [0, {MAX_RATE:e}] Hz (0 = no limit)"),
        ))
    }
}

/// Checks a pixel limit setting (`--max-pixels`, `max_image_pixels`): at least 1.
pub fn check_max_pixels(value: u64) -> Result<u64> {
    if value >= 1 {
        Ok(value)
    } else {
        Err(range_error("max_image_pixels", value, "≥ 1 pixel".into()))
    }
}

/// `n` pixels in megapixels for messages (`"10000 MP"`, `"0.25 MP"`).
pub fn megapixels(n: u64) -> String {
    let mp = n as f64 / 1e6;
    if mp >= 10.0 {
        format!("{mp:.0} MP")
    } else {
        format!("{} MP", (mp * 1e3).round() / 1e3)
    }
}

/// Checks an image of `width × height` pixels against `max_pixels` (the
/// `--max-pixels` / `max_image_pixels` setting). The message names the setting:
/// `image is 100000×100000 = 10000 MP, above --max-pixels / max_image_pixels 100 MP`.
pub fn check_image_pixels(width: u64, height: u64, max_pixels: u64) -> Result<()> {
    let pixels = width.saturating_mul(height);
    if pixels > max_pixels {
        return Err(Error::InvalidImage(format!(
            "image is {width}×{height} = {}, above --max-pixels / max_image_pixels {}",
            megapixels(pixels),
            megapixels(max_pixels)
        )));
    }
    Ok(())
}

/// Parses a pixel count as typed on a command line: an integer, optionally with a `k`, `M`
/// or `G` suffix (`100M`, `2.5G`, `1000000`), an optional trailing `P`/`px`.
pub fn parse_pixel_count(text: &str) -> std::result::Result<u64, String> {
    let t = text.trim();
    let t = t
        .strip_suffix("px")
        .or_else(|| t.strip_suffix('P'))
        .or_else(|| t.strip_suffix('p'))
        .unwrap_or(t);
    let (number, scale) = match t.chars().last() {
        Some('k' | 'K') => (&t[..t.len() - 1], 1e3),
        Some('M' | 'm') => (&t[..t.len() - 1], 1e6),
        Some('G' | 'g') => (&t[..t.len() - 1], 1e9),
        _ => (t, 1.0),
    };
    let value: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("expected a pixel count like 100M or 1000000, got `{text}`"))?;
    let pixels = value * scale;
    if !(pixels.is_finite() && pixels >= 1.0 && pixels <= u64::MAX as f64) {
        return Err(format!("expected a pixel count ≥ 1, got `{text}`"));
    }
    Ok(pixels.round() as u64)
}

/// Parses a relative pair `"a:b"` of marker IDs (node parameter `relative_pairs`).
pub fn parse_relative_pair(text: &str) -> std::result::Result<(u64, u64), String> {
    let bad = || format!("`relative_pairs`: expected \"a:b\" with marker ids, got `{text}`");
    let (a, b) = text.split_once(':').ok_or_else(bad)?;
    let a: u64 = a.trim().parse().map_err(|_| bad())?;
    let b: u64 = b.trim().parse().map_err(|_| bad())?;
    if a == b {
        return Err(format!(
            "`relative_pairs`: `{text}` pairs a marker with itself"
        ));
    }
    Ok((a, b))
}

/// Reads a text file of at most `max_bytes` bytes (`what` names it in the message).
pub fn read_text_bounded(
    path: &std::path::Path,
    max_bytes: u64,
    what: &str,
) -> std::result::Result<String, String> {
    use std::io::Read;
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut text = String::new();
    file.take(max_bytes.saturating_add(1))
        .read_to_string(&mut text)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if text.len() as u64 > max_bytes {
        return Err(format!(
            "{}: {what} is larger than the limit of {max_bytes} bytes",
            path.display()
        ));
    }
    Ok(text)
}

#[cfg(feature = "yaml")]
pub use yaml::load_yaml;

#[cfg(feature = "yaml")]
mod yaml {
    use super::{MAX_PARAM_FILE_BYTES, MAX_YAML_DEPTH, MAX_YAML_NODES};
    use std::collections::HashMap;
    use yaml_rust2::parser::{Event, Parser};
    use yaml_rust2::{Yaml, YamlLoader};

    /// Parses YAML text (parameter files, `-p` values) within the limits: at most
    /// [`MAX_PARAM_FILE_BYTES`] of text, [`MAX_YAML_NODES`] nodes once aliases are expanded
    /// (a "billion laughs" file is refused before anything is expanded) and
    /// [`MAX_YAML_DEPTH`] levels of nesting.
    pub fn load_yaml(text: &str) -> Result<Vec<Yaml>, String> {
        if text.len() as u64 > MAX_PARAM_FILE_BYTES {
            return Err(format!(
                "YAML text of {} bytes is larger than the limit of {MAX_PARAM_FILE_BYTES} bytes",
                text.len()
            ));
        }
        // First pass: events only (linear in the text), counting expanded nodes.
        let mut parser = Parser::new_from_str(text);
        let mut anchors: HashMap<usize, u64> = HashMap::new();
        // Open collections: (anchor id, expanded node count so far).
        let mut stack: Vec<(usize, u64)> = Vec::new();
        let mut total: u64 = 0;
        loop {
            let (event, _) = parser.next_token().map_err(|e| e.to_string())?;
            let add = match event {
                Event::StreamEnd => break,
                Event::Scalar(_, _, anchor, _) => {
                    if anchor > 0 {
                        anchors.insert(anchor, 1);
                    }
                    Some(1)
                }
                Event::Alias(id) => Some(anchors.get(&id).copied().unwrap_or(1)),
                Event::SequenceStart(anchor, _) | Event::MappingStart(anchor, _) => {
                    if stack.len() >= MAX_YAML_DEPTH {
                        return Err(format!(
                            "YAML nesting deeper than the limit of {MAX_YAML_DEPTH} levels"
                        ));
                    }
                    stack.push((anchor, 1));
                    None
                }
                Event::SequenceEnd | Event::MappingEnd => {
                    let (anchor, count) = stack.pop().unwrap_or((0, 1));
                    if anchor > 0 {
                        anchors.insert(anchor, count);
                    }
                    Some(count)
                }
                _ => None,
            };
            if let Some(n) = add {
                match stack.last_mut() {
                    Some((_, count)) => *count = count.saturating_add(n),
                    None => total = total.saturating_add(n),
                }
                let open: u64 = stack.iter().fold(0u64, |s, (_, c)| s.saturating_add(*c));
                if total.saturating_add(open) > MAX_YAML_NODES {
                    return Err(format!(
                        "YAML expands to more than the limit of {MAX_YAML_NODES} nodes \
                         (aliases included)"
                    ));
                }
            }
        }
        YamlLoader::load_from_str(text).map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_name_the_setting() {
        let e = check_period(5e-324).unwrap_err().to_string();
        assert!(e.contains("period") && e.contains("5e-324"), "{e}");
        assert!(check_period(f64::NAN).is_err());
        assert!(check_period(15.5).is_ok());
        assert!(check_code_size(33).is_ok() && check_code_size(17).is_ok());
        for bad in [16, 35, 1_000_001, 0] {
            let e = check_code_size(bad).unwrap_err().to_string();
            assert!(e.contains("code_size"), "{e}");
        }
        assert!(check_window_size(4_294_967_295).is_err());
        assert!(check_window_size(32_768).is_ok());
        assert!(check_quality("min_quality", 2.0).is_err());
        assert!(check_rate("max_rate", -5.0).is_err());
        assert!(check_rate("max_rate", f64::NAN).is_err());
        let e = check_image_pixels(100_000, 100_000, DEFAULT_MAX_PIXELS)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("100000×100000 = 10000 MP")
                && e.contains("--max-pixels")
                && e.contains("100 MP"),
            "{e}"
        );
        assert!(check_window_fits(820, 1655, 762).is_ok());
        assert!(check_window_fits(2000, 1655, 762).is_err());
        // A long strip: the window fits its length but would be 11 times its area.
        assert!(check_window_fits(32_768, 32_768, 3_000).is_err());
    }

    #[test]
    fn pixel_counts() {
        assert_eq!(parse_pixel_count("100M"), Ok(100_000_000));
        assert_eq!(parse_pixel_count("2.5MP"), Ok(2_500_000));
        assert_eq!(parse_pixel_count("1000"), Ok(1000));
        assert!(parse_pixel_count("0").is_err());
        assert!(parse_pixel_count("lots").is_err());
        assert_eq!(parse_relative_pair(" 2 : 5"), Ok((2, 5)));
        assert!(parse_relative_pair("1:1").is_err());
        assert!(parse_relative_pair("1-2").is_err());
    }

    #[cfg(feature = "yaml")]
    #[test]
    fn yaml_bombs_are_refused() {
        let mut bomb = String::from("a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n");
        for i in 1..12 {
            let refs = vec![format!("*a{}", i - 1); 10].join(", ");
            bomb.push_str(&format!("a{i}: &a{i} [{refs}]\n"));
        }
        let e = load_yaml(&bomb).unwrap_err();
        assert!(e.contains("nodes"), "{e}");
        let deep = "[".repeat(1000) + &"]".repeat(1000);
        // The parser's own recursion limit or ours, whichever comes first.
        let e = load_yaml(&deep).unwrap_err();
        assert!(e.contains("nesting") || e.contains("recursion"), "{e}");
        let ok = load_yaml("a: &x 1\nb: *x\nc: [1, 2]\n").unwrap();
        assert_eq!(ok[0]["b"].as_i64(), Some(1));
    }
}
