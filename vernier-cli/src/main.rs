//! `vernier`: detect markers in image files, render synthetic images, export layouts.
//!
//! Every failure prints one line `vernier: <what went wrong>` on stderr and exits non-zero.

mod bag;
mod batch;
mod calibrate;
mod detector_flags;
mod export_cmd;
mod inputs;
#[cfg(feature = "opencv")]
mod live;
mod plot;
mod pose_table;
mod rerun_log;
mod stats;

use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use vernier::pattern_file::Pattern;
use vernier::render::{render, RenderOptions, Sampling};
use vernier::Pose;

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
    /// Pixel size with its uncertainty, and its variation across the field, from images of
    /// markers (give it back with `detect --pixel-size`).
    Calibrate(calibrate::CalibrateArgs),
    /// Detect markers live in frames from a camera, V4L2 device, GStreamer pipeline or video
    /// file (OpenCV; cargo feature `opencv`).
    #[cfg(feature = "opencv")]
    Live(live::LiveArgs),
}

#[derive(Parser)]
struct DetectArgs {
    /// Marker type, pattern file and detector settings (shared with `vernier live`).
    #[command(flatten)]
    detector: detector_flags::DetectorFlags,
    /// Largest image read, pixels (`100M`, `2.5G`, `4000000`): a larger image (by its
    /// header, before decoding) is an error naming this limit. Default 100M.
    #[arg(long, value_parser = parse_max_pixels, default_value = "100M")]
    max_pixels: u64,
    /// Output format: `json` (one object per image), or `csv` / `jsonl` (one row per image
    /// and marker, time-series columns of vernier-cli/src/pose_table.rs).
    #[arg(long, value_enum, default_value = "json")]
    format: pose_table::TableFormat,
    /// Also log every frame to rerun (needs the `rerun` cargo feature): `spawn` a viewer,
    /// `connect` to a running one (or give its `rerun+http://HOST:PORT/proxy` URL), or write a
    /// `FILE.rrd`. Logs the image, markers and their axes, the spectrum with its lobes, the
    /// wrapped phase and the pose time series.
    #[arg(long, value_name = "TARGET")]
    rerun: Option<rerun_log::RerunTarget>,
    /// Images detected at once, each on its own core, when they are independent (no
    /// `--track`, no `--rerun`): 0 = one per core. Each image's markers are then measured on
    /// its one thread; the output keeps the images' order.
    #[arg(long, default_value_t = 0)]
    jobs: usize,
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

/// Restores SIGPIPE's default action (Rust ignores it): a closed pipe downstream
/// (`vernier stats … | head`) then ends the program quietly, as it ends other Unix tools,
/// instead of a panic in `println!`.
fn exit_quietly_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: called first in `main`, before any other thread exists; SIG_DFL is a valid
    // disposition for SIGPIPE.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> ExitCode {
    exit_quietly_on_closed_pipe();
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
        // `vernier live` exists only with the `opencv` feature: say how to get it.
        #[cfg(not(feature = "opencv"))]
        Err(e)
            if e.kind() == clap::error::ErrorKind::InvalidSubcommand
                && std::env::args().nth(1).as_deref() == Some("live") =>
        {
            eprintln!(
                "vernier: this `vernier` was built without `live` (OpenCV); rebuild it with \
                 `cargo install --path vernier-cli --features opencv` (needs libopencv-dev, \
                 clang and libclang-dev)"
            );
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
        Command::Calibrate(args) => calibrate::run(&args),
        #[cfg(feature = "opencv")]
        Command::Live(args) => live::run(&args),
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
    let images = inputs::expand_inputs(&args.images)?;
    let tracking = args.detector.tracking();
    let jobs = match args.jobs {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    let jobs = if tracking.is_some() || args.rerun.is_some() {
        1
    } else {
        jobs.min(images.len()).max(1)
    };
    let mut detectors = if jobs == 1 {
        vec![args.detector.detector()?]
    } else {
        // One detector (plans, buffers) per image thread, its markers on that thread.
        let settings = args.detector.settings();
        let config = settings.to_config().map_err(|e| e.to_string())?;
        (0..jobs)
            .map(|_| {
                vernier::Detector::new(config.clone().with_marker_threads(1))
                    .map(|d| d.with_pixel_size(settings.pixel_size))
                    .map_err(|e| e.to_string())
            })
            .collect::<Result<Vec<_>, String>>()?
    };
    let mut rerun = match &args.rerun {
        Some(target) => Some(rerun_log::RerunLog::open(
            target,
            args.detector.display_polarity(),
        )?),
        None => None,
    };
    let limits = vernier::DecodeLimits::with_max_pixels(args.max_pixels);
    let failures = batch::detect_files(
        &mut detectors,
        &images,
        &limits,
        args.format,
        tracking,
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
