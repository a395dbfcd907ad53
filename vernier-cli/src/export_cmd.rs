//! `vernier export`: writes a pattern file's layout as PNG, SVG, GDSII or OASIS.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use vernier::export::{export_bytes, ExportFormat};
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
    /// Output file; the format's extension (.png, .svg, .gds, .oas) is appended when the
    /// name has none.
    output: PathBuf,
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
    let bytes = export_bytes(&pattern, format).map_err(|e| e.to_string())?;
    std::fs::write(&path, &bytes).map_err(|e| format!("{}: {e}", path.display()))?;
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
