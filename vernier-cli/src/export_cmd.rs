//! `vernier export`: writes a pattern file's layout as PNG, SVG, GDSII or OASIS.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use vernier::export::ExportFormat;
use vernier::layout::Rect;
use vernier::pattern_file::Pattern;

/// Arguments of `vernier export`.
#[derive(Parser)]
pub struct ExportArgs {
    /// JSON pattern file (PeriodicPattern, HPCodePattern, BitmapPattern (stamps),
    /// FingerprintPattern, MegarenaPattern, CustomPattern).
    #[arg(long)]
    pattern: PathBuf,
    /// Output format: png, svg, gds or oas (default: from the output file's extension).
    #[arg(long)]
    format: Option<String>,
    /// Marker ID written in an HP code's top dot row (HPCodePattern only).
    #[arg(long)]
    id: Option<u64>,
    /// Megarena region of interest `x,y,w,h` in layout coordinates, pattern units (µm):
    /// replaces the file's `regionOfInterest` (MegarenaPattern only).
    #[arg(long, allow_hyphen_values = true)]
    roi: Option<String>,
    /// Write the file even when its estimated size is above the export limit (512 MiB).
    #[arg(long)]
    force: bool,
    /// Output file; the format's extension (.png, .svg, .gds, .oas) is appended when the
    /// name has none.
    output: PathBuf,
}

/// Exports drawing more rectangles than this show a progress bar.
const PROGRESS_MIN_RECTS: f64 = 1e6;

/// `bytes` for messages: `1.9 GB`, `512 MiB`-style binary units.
fn human_bytes(bytes: f64) -> String {
    let units = ["bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"];
    let mut value = bytes;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < units.len() {
        value /= 1024.0;
        unit += 1;
    }
    if value.is_finite() {
        format!("{value:.1} {}", units[unit]).replace(".0 ", " ")
    } else {
        "an unbounded size".into()
    }
}

/// Chooses the format and the final file name: `--format` wins, else the extension; an
/// extension naming another format is an error rather than a mislabelled file.
fn format_and_path(format: Option<&str>, output: &Path) -> Result<(ExportFormat, PathBuf), String> {
    let from_extension = ExportFormat::from_path(output);
    let format = match format {
        Some(name) => name.parse::<ExportFormat>().map_err(|e| e.to_string())?,
        None => from_extension.ok_or_else(|| {
            format!(
                "cannot tell the format of `{}`: give --format png|svg|gds|oas or a file \
                 ending in .png, .svg, .gds or .oas",
                output.display()
            )
        })?,
    };
    match from_extension {
        Some(f) if f == format => Ok((format, output.to_path_buf())),
        Some(f) => Err(format!(
            "`{}` has the extension of {} files but --format is {}",
            output.display(),
            f.extension(),
            format.extension()
        )),
        None => {
            let mut name = output.as_os_str().to_owned();
            name.push(".");
            name.push(format.extension());
            Ok((format, PathBuf::from(name)))
        }
    }
}

/// Runs `vernier export`.
pub fn run(args: &ExportArgs) -> Result<ExitCode, String> {
    let (format, path) = format_and_path(args.format.as_deref(), &args.output)?;
    let mut pattern = Pattern::from_file(&args.pattern).map_err(|e| e.to_string())?;
    if let Some(id) = args.id {
        pattern = match pattern {
            Pattern::HpCode(l) => Pattern::HpCode(l.with_id(id).map_err(|e| e.to_string())?),
            other => {
                return Err(format!(
                    "--id applies to HPCodePattern files, `{}` holds a {}",
                    args.pattern.display(),
                    other.class_name()
                ))
            }
        };
    }
    if let Some(text) = &args.roi {
        let v = crate::parse_numbers(text, "roi", ',', 4)?;
        pattern = match pattern {
            Pattern::Megarena(l) => Pattern::Megarena(
                l.with_region_of_interest(Rect::new(v[0], v[1], v[2], v[3]))
                    .map_err(|e| e.to_string())?,
            ),
            other => {
                return Err(format!(
                    "--roi applies to MegarenaPattern files, `{}` holds a {}",
                    args.pattern.display(),
                    other.class_name()
                ))
            }
        };
    }
    // Estimate first (from the frame alone): a huge region is refused before any work.
    let estimate = vernier::export::estimate_bytes(&pattern, format);
    let limit = vernier::limits::DEFAULT_MAX_EXPORT_BYTES;
    if estimate > limit as f64 && !args.force {
        return Err(format!(
            "the {} export would be about {}, above the export limit of {}: give --force to \
             write it anyway (or a smaller --roi)",
            format.extension(),
            human_bytes(estimate),
            human_bytes(limit as f64)
        ));
    }
    let path_error = |e: std::io::Error| format!("{}: {e}", path.display());
    if format == ExportFormat::Svg {
        // Streamed to the file with a progress bar (bytes written vs the estimate).
        let file = std::fs::File::create(&path).map_err(path_error)?;
        let mut out = std::io::BufWriter::new(file);
        let rects = vernier::export::estimate_rects(&pattern);
        let progress = if rects > PROGRESS_MIN_RECTS {
            crate::batch::progress_bar(rects as u64, "rectangles")
        } else {
            indicatif::ProgressBar::hidden()
        };
        vernier::export::write_svg_to(&pattern, &mut out, &mut |n| progress.set_position(n))
            .map_err(path_error)?;
        progress.finish_and_clear();
        let file = out.into_inner().map_err(|e| path_error(e.into_error()))?;
        vernier::output::sync(&file).map_err(path_error)?;
    } else {
        // GDSII/OASIS: a progress bar over the two passes that build the drawing.
        let rects = vernier::export::estimate_rects(&pattern);
        let progress = if rects > PROGRESS_MIN_RECTS && format != ExportFormat::Png {
            crate::batch::progress_bar(2 * rects as u64, "rectangles")
        } else {
            indicatif::ProgressBar::hidden()
        };
        let bytes = vernier::export::export_bytes_with_progress(&pattern, format, &mut |n| {
            progress.set_position(n)
        })
        .map_err(|e| e.to_string())?;
        progress.finish_and_clear();
        vernier::output::write_file(&path, &bytes).map_err(path_error)?;
    }
    println!("{}", path.display());
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_comes_from_flag_or_extension() {
        let p = Path::new;
        assert_eq!(
            format_and_path(None, p("a/m.OAS")).unwrap(),
            (ExportFormat::Oasis, p("a/m.OAS").to_path_buf())
        );
        assert_eq!(
            format_and_path(Some("gds"), p("m")).unwrap(),
            (ExportFormat::Gds, p("m.gds").to_path_buf())
        );
        assert_eq!(
            format_and_path(Some("svg"), p("m.v2")).unwrap().1,
            p("m.v2.svg")
        );
        assert!(format_and_path(Some("gds"), p("m.oas")).is_err());
        assert!(format_and_path(None, p("m")).is_err());
        assert!(format_and_path(Some("dxf"), p("m")).is_err());
    }
}
