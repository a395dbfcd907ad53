//! `render_test_frames`: writes synthetic mono8 frames of a periodic dot grid at known poses,
//! for feeding the node from another process (interoperability test, benchmark, dry runs).
//!
//! ```text
//! render_test_frames --out DIR [--count N] [--size 1024] [--period 10] [--pixel-size 0.8]
//!                    [--seed 1]
//! ```
//!
//! Writes `DIR/frame_<i>.gray` (raw row-major mono8, `size × size`) and `DIR/truth.json`:
//! `{"size", "period", "pixel_size", "unit": "um", "frames": [{"file", "markers": [{"id",
//! "x", "y", "alpha", "pixel_size", "position_m": [x, y, z]}]}]}` where `x, y` are pattern
//! units (µm) and `position_m` is the expected `PoseStamped` position (camera frame, metres).
//! Poses lie in the periodic detector's canonical range (`|x|, |y| < P/2`, `α ∈ [0, π/2)`),
//! images are blurred (σ = 0.5 px) and quantised to 8 bits.

use std::path::PathBuf;
use std::process::ExitCode;
use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions};
use vernier::Pose;

struct Args {
    out: PathBuf,
    count: usize,
    size: usize,
    period: f64,
    pixel_size: f64,
    seed: u64,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        out: PathBuf::new(),
        count: 4,
        size: 1024,
        period: 10.0,
        pixel_size: 0.8,
        seed: 1,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or_else(|| format!("`{flag}` needs a value"));
        let number = |text: String| {
            text.parse::<f64>()
                .map_err(|_| format!("`{flag}`: `{text}` is not a number"))
        };
        match flag.as_str() {
            "--out" => args.out = PathBuf::from(value()?),
            "--count" => args.count = number(value()?)? as usize,
            "--size" => args.size = number(value()?)? as usize,
            "--period" => args.period = number(value()?)?,
            "--pixel-size" => args.pixel_size = number(value()?)?,
            "--seed" => args.seed = number(value()?)? as u64,
            other => {
                return Err(format!(
                    "unknown argument `{other}` (see the source header)"
                ))
            }
        }
    }
    if args.out.as_os_str().is_empty() {
        return Err("--out DIR is required".into());
    }
    if !(args.size >= 16 && args.period > 0.0 && args.pixel_size > 0.0) {
        return Err("need --size ≥ 16, --period > 0, --pixel-size > 0".into());
    }
    Ok(args)
}

/// A small deterministic generator (SplitMix64) for the poses: no extra dependency.
struct SplitMix(u64);

impl SplitMix {
    fn next_unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_unit()
    }
}

fn run(args: &Args) -> Result<(), String> {
    std::fs::create_dir_all(&args.out)
        .map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let diagonal = args.size as f64 * args.pixel_size * 1.5;
    let dots = ((diagonal / args.period) as usize + 4) | 1;
    let layout = PeriodicLayout::new(args.period, dots, dots).map_err(|e| e.to_string())?;
    let mut options = RenderOptions::new(args.size, args.size);
    options.blur_sigma = 0.5;
    options.bit_depth = Some(8);
    let mut rng = SplitMix(args.seed);
    let mut frames = Vec::new();
    for i in 0..args.count {
        let p = args.period;
        let pose = Pose::planar(
            rng.range(-0.4 * p, 0.4 * p),
            rng.range(-0.4 * p, 0.4 * p),
            rng.range(0.05, 1.5),
            args.pixel_size,
        );
        let image = render(&layout, &pose, &options).map_err(|e| e.to_string())?;
        let bytes: Vec<u8> = image
            .pixels()
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        let file = format!("frame_{i:04}.gray");
        std::fs::write(args.out.join(&file), &bytes)
            .map_err(|e| format!("cannot write {file}: {e}"))?;
        let position = pose.scaled(1e-6).camera_from_pattern().translation.vector;
        frames.push(serde_json::json!({
            "file": file,
            "markers": [{
                "id": 0,
                "x": pose.x, "y": pose.y, "alpha": pose.alpha, "pixel_size": pose.pixel_size,
                "position_m": [position.x, position.y, position.z],
            }],
        }));
    }
    let truth = serde_json::json!({
        "size": args.size,
        "period": args.period,
        "pixel_size": args.pixel_size,
        "unit": "um",
        "frames": frames,
    });
    let text = serde_json::to_string_pretty(&truth).map_err(|e| e.to_string())?;
    std::fs::write(args.out.join("truth.json"), text)
        .map_err(|e| format!("cannot write truth.json: {e}"))
}

fn main() -> ExitCode {
    match parse_args().and_then(|args| run(&args)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("render_test_frames: {message}");
            ExitCode::FAILURE
        }
    }
}
