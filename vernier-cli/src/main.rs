//! `vernier`: detect markers in image files, render synthetic images, export layouts.
//!
//! Every failure prints one line `vernier: <what went wrong>` on stderr and exits non-zero.

mod bag;
mod batch;
mod export_cmd;
mod inputs;
mod plot;
mod pose_table;
mod rerun_log;
mod stats;

use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::pattern_file::Pattern;
use vernier::render::{render, RenderOptions, Sampling};
use vernier::{Detector, Polarity, Pose};

#[derive(Parser)]
#[command(
    name = "vernier",
    version,
    about = "Sub-pixel pose of periodic dot markers in microscope images",
    arg_required_else_help = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Detect markers in image files and print their poses.
    Detect(DetectArgs),
    /// Render a synthetic image of a pattern at a known pose.
    Render(RenderArgs),
    /// Export a pattern file's layout for fabrication or documentation (PNG, SVG, GDSII, OASIS).
    Export(export_cmd::ExportArgs),
    /// Plot a pose table (from `detect` or `bag`): pose over time and Allan deviation.
    Plot(plot::PlotArgs),
    /// Replay a rosbag2 MCAP recording through the detector (poses to MCAP, CSV or JSON Lines).
    Bag(bag::BagArgs),
    /// Noise of a pose table per marker and relative pair (robust second differences).
    Stats(stats::StatsArgs),
}

#[derive(Parser)]
struct DetectArgs {
    /// JSON pattern file describing the marker (PeriodicPattern, HPCodePattern, ...).
    #[arg(long)]
    pattern: Option<PathBuf>,
    /// Marker type when no pattern file is given: periodic, hpcode, stamp or megarena.
    #[arg(long = "type", default_value = "periodic")]
    marker_type: MarkerKind,
    /// Shorthand for `--type hpcode`.
    #[arg(long)]
    hpcode: bool,
    /// Shorthand for `--type megarena`.
    #[arg(long)]
    megarena: bool,
    /// Shorthand for `--type stamp`.
    #[arg(long)]
    stamp: bool,
    /// Physical period of the dot grid, pattern units (µm by convention).
    #[arg(long, allow_hyphen_values = true)]
    period: Option<f64>,
    /// HP code width in half-period cells (33, 37, ...).
    #[arg(long)]
    code_size: Option<usize>,
    /// Megarena LFSR bit depth (4–12).
    #[arg(long)]
    code_depth: Option<u32>,
    /// Side of the window analysed around each marker, pixels (8–32768, at most the
    /// image's larger side).
    #[arg(long)]
    window_size: Option<usize>,
    /// Largest image read, pixels (`100M`, `2.5G`, `4000000`): a larger image (by its
    /// header, before decoding) is an error naming this limit. Default 100M.
    #[arg(long, value_parser = parse_max_pixels, default_value = "100M")]
    max_pixels: u64,
    /// Stamp bitmap PNG files (1 = dot), in ID order; repeat the flag for several.
    #[arg(long)]
    bitmap: Vec<PathBuf>,
    /// Output format: `json` (one object per image), or `csv` / `jsonl` (one row per image
    /// and marker, time-series columns of vernier-cli/src/pose_table.rs).
    #[arg(long, value_enum, default_value = "json")]
    format: pose_table::TableFormat,
    /// Also measure the out-of-plane angles `beta` (about the pattern's y axis) and `gamma`
    /// (about its x axis), radians: 6-DoF pose, orthographic model, `z` stays 0. Megarena
    /// only (ignored for other marker types). Of the two mirror solutions `(beta, gamma)` and
    /// `(-beta, -gamma)` the perspective cue's choice is printed, its strength (0-1) in the
    /// JSON as `pose_3d_cue_strength`.
    #[arg(long = "pose-3d")]
    pose_3d: bool,
    /// HP codes: keep the analysis window's planes instead of refining each decoded marker on
    /// its whole regular dot field (docs/design.md#field-fit): faster, less precise.
    #[arg(long = "no-field-fit")]
    no_field_fit: bool,
    /// Treat the images as one sequence, in order, and track the markers from frame to frame
    /// (HP codes: the finder search runs on the first frame, on loss and every
    /// `--reacquire-every` frames; same poses as without it while markers move less than half
    /// a period per frame).
    #[arg(long)]
    track: bool,
    /// With `--track`, run the full search every this many frames (new markers are found
    /// then); 0 = only when a marker is lost.
    #[arg(long, value_name = "FRAMES", default_value_t = 30)]
    reacquire_every: usize,
    /// Dot polarity: `auto` (default: found per marker for HP codes and stamps, bright for
    /// periodic and Megarena), `bright` dots on a dark background or `dark` dots on a bright one.
    #[arg(long, default_value = "auto")]
    polarity: PolarityArg,
    /// Also log every frame to rerun (needs the `rerun` cargo feature): `spawn` a viewer,
    /// `connect` to a running one (or give its `rerun+http://HOST:PORT/proxy` URL), or write a
    /// `FILE.rrd`. Logs the image, markers and their axes, the spectrum with its lobes, the
    /// wrapped phase and the pose time series.
    #[arg(long, value_name = "TARGET")]
    rerun: Option<rerun_log::RerunTarget>,
    /// Image files (PNG, JPEG, TIFF, PNM; 8/16-bit grey or colour), folders (their image
    /// files) or quoted glob patterns (`'run1/*.png'`, `'**/*.tif'`), in natural order.
    #[arg(required = true)]
    images: Vec<PathBuf>,
}

#[derive(Parser)]
struct RenderArgs {
    /// JSON pattern file.
    #[arg(long)]
    pattern: PathBuf,
    /// Pose `x,y,alpha`: pattern units and radians (frames: docs/design.md#frames).
    #[arg(long, allow_hyphen_values = true)]
    pose: String,
    /// Pattern units per pixel.
    #[arg(long, allow_hyphen_values = true)]
    pixel_size: f64,
    /// Image size `WIDTHxHEIGHT` in pixels.
    #[arg(long)]
    size: String,
    /// Gaussian optical blur σ, pixels (applied before pixel integration).
    #[arg(long, default_value_t = 0.0)]
    blur: f64,
    /// Additive Gaussian noise σ, fraction of full scale (0.01 = 1 %).
    #[arg(long, default_value_t = 0.0)]
    noise: f64,
    /// Output bit depth: 8, 12 or 16 (12-bit is stored in a 16-bit PNG).
    #[arg(long, default_value_t = 8)]
    bits: u32,
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Point-sample the analytic intensity (original renderer) instead of area-sampling dots.
    #[arg(long)]
    point: bool,
    /// Output PNG file.
    output: PathBuf,
}

fn main() -> ExitCode {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        // --help and --version are not errors: clap prints them as usual.
        Err(e) if !e.use_stderr() => {
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        // Bare `vernier` (or a subcommand's bare group): the help, not an error line.
        Err(e) if e.kind() == clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            let _ = e.print();
            return ExitCode::from(2);
        }
        // Usage errors: one line, like every other failure, naming what is wrong.
        Err(e) => {
            eprintln!("vernier: {}", usage_error_line(&e));
            return ExitCode::from(2);
        }
    };
    let result = match cli.command {
        Command::Detect(args) => detect(&args),
        Command::Render(args) => render_image(&args),
        Command::Export(args) => export_cmd::run(&args),
        Command::Plot(args) => plot::run(&args),
        Command::Bag(args) => bag::run(&args),
        Command::Stats(args) => stats::run(&args),
    };
    match result {
        Ok(code) => code,
        Err(message) => {
            eprintln!("vernier: {message}");
            ExitCode::FAILURE
        }
    }
}

/// A clap usage error on one line: its text up to the usage block (clap lists the missing or
/// bad arguments on the lines after the first), and where to read more.
fn usage_error_line(e: &clap::Error) -> String {
    let rendered = e.render().to_string();
    let mut lines = rendered
        .lines()
        .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
        .map(str::trim)
        .filter(|l| !l.is_empty());
    let first = lines
        .next()
        .unwrap_or("invalid arguments")
        .trim_start_matches("error: ")
        .to_string();
    let rest: Vec<&str> = lines.collect();
    let what = if rest.is_empty() {
        first
    } else {
        format!("{} {}", first, rest.join(", "))
    };
    // `vernier detect --help` when the error is about a subcommand's arguments.
    let subcommand = std::env::args().nth(1).filter(|a| {
        <Cli as clap::CommandFactory>::command()
            .get_subcommands()
            .any(|c| c.get_name() == a)
    });
    match subcommand {
        Some(name) => format!("{what} (see `vernier {name} --help`)"),
        None => format!("{what} (see `vernier --help`)"),
    }
}

fn load_pattern(path: &Path) -> Result<Pattern, String> {
    Pattern::from_file(path).map_err(|e| e.to_string())
}

fn detect(args: &DetectArgs) -> Result<ExitCode, String> {
    let pattern_type = if args.hpcode {
        MarkerKind::HpCode
    } else if args.megarena {
        MarkerKind::Megarena
    } else if args.stamp {
        MarkerKind::Stamp
    } else {
        args.marker_type
    };
    let settings = DetectorSettings {
        pattern_type,
        pattern_file: args.pattern.clone(),
        period: args.period,
        code_size: args.code_size,
        code_depth: args.code_depth,
        window_size: args.window_size,
        polarity: args.polarity.0,
        bitmaps: args.bitmap.clone(),
        pose_3d: args.pose_3d,
        field_fit: Some(!args.no_field_fit),
    };
    let config = settings.to_config().map_err(|e| e.to_string())?;
    let mut detector = Detector::new(config).map_err(|e| e.to_string())?;
    let images = inputs::expand_inputs(&args.images)?;
    let mut rerun = match &args.rerun {
        Some(target) => Some(rerun_log::RerunLog::open(
            target,
            args.polarity.0.unwrap_or_default(),
        )?),
        None => None,
    };
    let limits = vernier::DecodeLimits::with_max_pixels(args.max_pixels);
    let failures = batch::detect_files(
        &mut detector,
        &images,
        &limits,
        args.format,
        args.track.then_some(args.reacquire_every),
        rerun.as_mut(),
    )?;
    if let Some(rerun) = rerun {
        rerun.finish()?;
    }
    Ok(if failures == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn parse_numbers(
    text: &str,
    what: &str,
    separator: char,
    count: usize,
) -> Result<Vec<f64>, String> {
    let values: Result<Vec<f64>, _> = text
        .split(separator)
        .map(|v| v.trim().parse::<f64>())
        .collect();
    match values {
        Ok(v) if v.len() == count && v.iter().all(|x| x.is_finite()) => Ok(v),
        _ => Err(format!(
            "--{what} expects {count} numbers separated by `{separator}`, got `{text}`"
        )),
    }
}

fn render_image(args: &RenderArgs) -> Result<ExitCode, String> {
    let pattern = load_pattern(&args.pattern)?;
    let pose = parse_numbers(&args.pose, "pose", ',', 3)?;
    let size = parse_numbers(&args.size, "size", 'x', 2)?;
    let max_side = vernier::limits::MAX_RENDER_SIDE as f64;
    if size.iter().any(|&v| v < 1.0 || v.fract() != 0.0) {
        return Err(format!(
            "--size expects positive integers WIDTHxHEIGHT, got `{}`",
            args.size
        ));
    }
    let pixels = size[0] * size[1];
    if size.iter().any(|&v| v > max_side) || pixels > vernier::limits::MAX_RENDER_PIXELS as f64 {
        return Err(format!(
            "--size {} is above the render limit of {max_side} pixels per side and {}",
            args.size,
            vernier::limits::megapixels(vernier::limits::MAX_RENDER_PIXELS)
        ));
    }
    vernier::limits::check_pixel_size(args.pixel_size).map_err(|e| e.to_string())?;
    if ![8, 12, 16].contains(&args.bits) {
        return Err(format!("--bits must be 8, 12 or 16, got {}", args.bits));
    }
    let mut options = RenderOptions::new(size[0] as usize, size[1] as usize);
    options.blur_sigma = args.blur;
    options.noise_std = args.noise;
    options.bit_depth = Some(args.bits);
    options.seed = args.seed;
    if args.point {
        options.sampling = Sampling::Point;
    }
    let pose = Pose::planar(pose[0], pose[1], pose[2], args.pixel_size);
    let image = render(pattern.layout(), &pose, &options).map_err(|e| e.to_string())?;
    image
        .save_png(&args.output, args.bits)
        .map_err(|e| e.to_string())?;
    Ok(ExitCode::SUCCESS)
}

/// `--max-pixels`: a pixel count (`100M`, `4000000`), at least 1.
fn parse_max_pixels(text: &str) -> Result<u64, String> {
    vernier::limits::parse_pixel_count(text)
}

/// `--polarity auto|bright|dark` (`auto` = `None`).
#[derive(Clone, Copy, Debug)]
struct PolarityArg(Option<Polarity>);

impl std::str::FromStr for PolarityArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        vernier::parse_polarity_setting(s)
            .map(PolarityArg)
            .map_err(|e| e.to_string())
    }
}
