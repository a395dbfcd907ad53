//! `render_test_frames`: writes synthetic mono8 frames of dot markers at known poses, for
//! feeding the node from another process (interoperability test, benchmark, dry runs).
//!
//! ```text
//! render_test_frames --out DIR [--kind periodic|hpcode|megarena] [--count N] [--size 1024]
//!                    [--period 10] [--pixel-size 0.8] [--seed 1]
//!                    [--code-size 33] [--ids 37,300]          (hpcode only)
//!                    [--height H] [--motion PX]              (hpcode only)
//! ```
//!
//! `--kind periodic` (default): one periodic dot grid per frame (reported as ID 0).
//! `--kind megarena`: a 12-bit Megarena pattern per frame (reported as ID 0), each frame at a
//! random absolute position of its field (within ±2 mm of a point 51 mm × 43 mm into it) and
//! random orientation, with 1 % noise (the library's `megarena` bench scene).
//! `--kind hpcode`: two HP code markers per frame, `--code-size` half-period cells wide
//! (`W ≡ 1 mod 4`, node parameter `code_size`), with the two distinct IDs of `--ids` (first =
//! `a`, second = `b`), each at its own random position (fully inside the image, apart from the
//! other) and random full-turn orientation; both share the frame's pixel size (one camera).
//! `--height` makes the frames `size × H` (e.g. `--size 2456 --height 2054`, a 5 MP camera).
//! `--motion PX` makes them a smooth sequence instead: after frame 0 each marker drifts `PX`
//! pixels per frame along its own random direction (bouncing off the borders) and turns by
//! 1 mrad per frame, as a servo loop sees it (for tracking).
//!
//! Writes `DIR/frame_<i>.gray` (raw row-major mono8, `size × size`) and `DIR/truth.json`:
//! `{"kind", "size", "period", "pixel_size", "unit": "um", "frames": [{"file", "markers": [{"id",
//! "x", "y", "alpha", "pixel_size", "position_m": [x, y, z]}]}]}` where `x, y, pixel_size` are
//! pattern units (µm), `alpha` radians, and `position_m` is the expected `PoseStamped` position
//! (camera frame: origin at the centre pixel, x right, y down; metres), i.e. the translation of
//! `Pose::scaled(1e-6).camera_from_pattern()` exactly as the node converts a
//! `vernier::MarkerPose`. HP code frames add `"code_size"` and `"ids": [a, b]` at the top level,
//! per marker `"origin_px": [col, row]` (marker centre, image pixels), and per frame
//! `"relative": {"a", "b", "position_m": [x, y, z], "yaw"}`: the pose of marker `b` in marker
//! `a`'s frame (metres, radians about `a`'s z axis), computed as the node does
//! (`Pose::relative` of the SI-scaled poses, published on `~/relative/marker_<a>_<b>/pose`).
//! Periodic poses lie in the detector's canonical range (`|x|, |y| < P/2`, `α ∈ [0, π/2)`);
//! HP code poses have `α ∈ [−π, π)`. Images are blurred (σ = 0.5 px, before pixel
//! integration) and quantised to 8 bits.

use nalgebra::Vector2;
use std::f64::consts::PI;
use std::path::PathBuf;
use std::process::ExitCode;
use vernier::layout::{HpCodeLayout, Layout, PeriodicLayout};
use vernier::render::{render, render_scene, RenderOptions};
use vernier::Pose;

/// Metres per pattern unit (µm).
const METRES_PER_UM: f64 = 1e-6;

/// What the frames show.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    /// One periodic dot grid.
    Periodic,
    /// Two HP code markers with distinct IDs.
    HpCode,
    /// A 12-bit Megarena pattern (absolute position).
    Megarena,
}

struct Args {
    out: PathBuf,
    kind: Kind,
    count: usize,
    /// Image side, pixels.
    size: usize,
    /// Dot period, µm.
    period: f64,
    /// µm per pixel.
    pixel_size: f64,
    seed: u64,
    /// HP code width in half-period cells.
    code_size: usize,
    /// HP code IDs `a`, `b`.
    ids: (u64, u64),
    /// Image height, pixels (HP code frames; default `size`).
    height: Option<usize>,
    /// Drift per frame, pixels (HP code frames; 0 = independent random poses).
    motion: f64,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        out: PathBuf::new(),
        kind: Kind::Periodic,
        count: 4,
        size: 1024,
        period: 10.0,
        pixel_size: 0.8,
        seed: 1,
        code_size: 33,
        ids: (37, 300),
        height: None,
        motion: 0.0,
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
            "--kind" => {
                args.kind = match value()?.as_str() {
                    "periodic" => Kind::Periodic,
                    "hpcode" => Kind::HpCode,
                    "megarena" => Kind::Megarena,
                    other => {
                        return Err(format!(
                            "`--kind`: expected periodic, hpcode or megarena, got `{other}`"
                        ))
                    }
                }
            }
            "--count" => args.count = number(value()?)? as usize,
            "--size" => args.size = number(value()?)? as usize,
            "--period" => args.period = number(value()?)?,
            "--pixel-size" => args.pixel_size = number(value()?)?,
            "--seed" => args.seed = number(value()?)? as u64,
            "--code-size" => args.code_size = number(value()?)? as usize,
            "--height" => args.height = Some(number(value()?)? as usize),
            "--motion" => args.motion = number(value()?)?,
            "--ids" => {
                let text = value()?;
                let parsed: Result<Vec<u64>, _> =
                    text.split(',').map(|t| t.trim().parse::<u64>()).collect();
                args.ids = match parsed.as_deref() {
                    Ok(&[a, b]) if a != b => (a, b),
                    _ => {
                        return Err(format!(
                            "`--ids`: expected two distinct ids `a,b`, got `{text}`"
                        ))
                    }
                };
            }
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

/// Render settings shared by both kinds: σ = 0.5 px optical blur, 8-bit quantisation.
fn render_options(size: usize) -> RenderOptions {
    let mut options = RenderOptions::new(size, size);
    options.blur_sigma = 0.5;
    options.bit_depth = Some(8);
    options
}

/// Writes `image` (grey levels in `[0, 1]`) as raw mono8 `DIR/frame_<i>.gray`; returns the
/// file name.
fn write_frame(args: &Args, i: usize, image: &vernier::GreyImage) -> Result<String, String> {
    let bytes: Vec<u8> = image
        .pixels()
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let file = format!("frame_{i:04}.gray");
    std::fs::write(args.out.join(&file), &bytes)
        .map_err(|e| format!("cannot write {file}: {e}"))?;
    Ok(file)
}

/// The truth of one marker: pattern-unit pose and the node's `PoseStamped` position (metres).
fn marker_truth(id: u64, pose: &Pose) -> serde_json::Value {
    let position = pose
        .scaled(METRES_PER_UM)
        .camera_from_pattern()
        .translation
        .vector;
    serde_json::json!({
        "id": id,
        "x": pose.x, "y": pose.y, "alpha": pose.alpha, "pixel_size": pose.pixel_size,
        "position_m": [position.x, position.y, position.z],
    })
}

/// Frames of one pattern (reported as ID 0), each at the pose `pose_of` draws; the noise of
/// frame `i` is seeded with `seed + i`.
fn single_pattern_frames(
    args: &Args,
    layout: &dyn Layout,
    mut options: RenderOptions,
    mut pose_of: impl FnMut(&mut SplitMix) -> Pose,
) -> Result<Vec<serde_json::Value>, String> {
    let mut rng = SplitMix(args.seed);
    let mut frames = Vec::new();
    for i in 0..args.count {
        let pose = pose_of(&mut rng);
        options.seed = args.seed.wrapping_add(i as u64);
        let image = render(layout, &pose, &options).map_err(|e| e.to_string())?;
        let file = write_frame(args, i, &image)?;
        frames.push(serde_json::json!({
            "file": file,
            "markers": [marker_truth(0, &pose)],
        }));
    }
    Ok(frames)
}

fn periodic_frames(args: &Args) -> Result<Vec<serde_json::Value>, String> {
    let diagonal = args.size as f64 * args.pixel_size * 1.5;
    let dots = ((diagonal / args.period) as usize + 4) | 1;
    let layout = PeriodicLayout::new(args.period, dots, dots).map_err(|e| e.to_string())?;
    let p = args.period;
    single_pattern_frames(args, &layout, render_options(args.size), |rng| {
        Pose::planar(
            rng.range(-0.4 * p, 0.4 * p),
            rng.range(-0.4 * p, 0.4 * p),
            rng.range(0.05, 1.5),
            args.pixel_size,
        )
    })
}

/// Code depth of the Megarena frames (node parameter `code_depth`).
const MEGARENA_CODE_DEPTH: u32 = 12;

fn megarena_frames(args: &Args) -> Result<Vec<serde_json::Value>, String> {
    let layout = vernier::layout::MegarenaLayout::new(args.period, MEGARENA_CODE_DEPTH)
        .map_err(|e| e.to_string())?;
    let mut options = render_options(args.size);
    options.noise_std = 0.01;
    single_pattern_frames(args, &layout, options, |rng| {
        Pose::planar(
            -51_234.5 + rng.range(-2_000.0, 2_000.0),
            -43_210.9 + rng.range(-2_000.0, 2_000.0),
            rng.range(-PI, PI),
            args.pixel_size,
        )
    })
}

/// Two HP code markers per frame at random, non-overlapping poses (both fully inside the
/// image, with a gap of at least two periods between their bounding circles).
fn hpcode_frames(args: &Args) -> Result<Vec<serde_json::Value>, String> {
    let (id_a, id_b) = args.ids;
    let layouts = [hpcode_layout(args, id_a)?, hpcode_layout(args, id_b)?];
    // Bounding circle of a marker at any angle, pixels, plus a margin for the blur.
    let radius_px = layouts[0].width() / args.pixel_size / std::f64::consts::SQRT_2 + 4.0;
    let gap_px = 2.0 * args.period / args.pixel_size;
    let (width, height) = (args.size, args.height.unwrap_or(args.size));
    let size = width.min(height) as f64;
    if 2.0 * radius_px >= size {
        return Err(format!(
            "a {}-cell HP code at {} px per period does not fit a {}-pixel frame",
            args.code_size,
            args.period / args.pixel_size,
            args.size
        ));
    }
    let mut options = render_options(width);
    options.height = height;
    let center = Vector2::new((width / 2) as f64, (height / 2) as f64);
    let area = HpCodeArea {
        lo: Vector2::new(radius_px, radius_px),
        hi: Vector2::new(width as f64 - radius_px, height as f64 - radius_px),
        min_distance_px: 2.0 * radius_px + gap_px,
    };
    let mut placer = HpCodePlacer::new(args.seed);
    let mut frames = Vec::new();
    for i in 0..args.count {
        let (origins, alphas) = placer.next(args, &area)?;
        let poses = [0, 1]
            .map(|k| Pose::from_origin_in_image(origins[k] - center, alphas[k], args.pixel_size));
        let items: Vec<(&dyn Layout, Pose)> = layouts
            .iter()
            .zip(poses)
            .map(|(l, p)| (l as &dyn Layout, p))
            .collect();
        let image = render_scene(&items, &options).map_err(|e| e.to_string())?;
        let file = write_frame(args, i, &image)?;
        frames.push(two_marker_truth(file, [id_a, id_b], &poses, origins));
    }
    Ok(frames)
}

/// The HP code layout of marker `id` (`--period`, `--code-size`).
fn hpcode_layout(args: &Args, id: u64) -> Result<HpCodeLayout, String> {
    HpCodeLayout::from_code_size(args.period, args.code_size)
        .and_then(|l| l.with_id(id))
        .map_err(|e| format!("HP code (--code-size {}, id {id}): {e}", args.code_size))
}

/// Where the two markers' origins may go: inside `lo..hi` (pixels), at least
/// `min_distance_px` apart.
struct HpCodeArea {
    lo: Vector2<f64>,
    hi: Vector2<f64>,
    min_distance_px: f64,
}

impl HpCodeArea {
    /// A random origin in the area, pixels.
    fn place(&self, rng: &mut SplitMix) -> Vector2<f64> {
        Vector2::new(
            rng.range(self.lo.x, self.hi.x),
            rng.range(self.lo.y, self.hi.y),
        )
    }
}

/// Origins (pixels) and angles (rad) of the two markers of a frame.
type TwoMarkers = ([Vector2<f64>; 2], [f64; 2]);

/// The two markers' origins and angles, frame after frame: at random, or with `--motion`
/// drifting from the last frame's, bouncing off the area's edges.
struct HpCodePlacer {
    rng: SplitMix,
    /// Each marker's drift direction (unit vectors), with `--motion`.
    directions: [Vector2<f64>; 2],
    /// The last frame's markers.
    last: Option<TwoMarkers>,
}

impl HpCodePlacer {
    fn new(seed: u64) -> HpCodePlacer {
        // Drawn from their own generator, so that the poses without --motion stay as they were.
        let mut drift = SplitMix(seed ^ 0x5eed_d41f);
        let directions =
            [drift.range(-PI, PI), drift.range(-PI, PI)].map(|a| Vector2::new(a.cos(), a.sin()));
        HpCodePlacer {
            rng: SplitMix(seed),
            directions,
            last: None,
        }
    }

    /// The next frame's markers.
    fn next(&mut self, args: &Args, area: &HpCodeArea) -> Result<TwoMarkers, String> {
        if let (Some(last), true) = (self.last, args.motion > 0.0) {
            self.last = Some(self.drifted(last, args.motion, area));
        }
        let (first, mut second, angles) = match self.last {
            Some((o, a)) if args.motion > 0.0 => (o[0], o[1], Some(a)),
            _ => (area.place(&mut self.rng), area.place(&mut self.rng), None),
        };
        let mut attempts = 0;
        while angles.is_none() && (second - first).norm() < area.min_distance_px {
            attempts += 1;
            if attempts > 10_000 {
                return Err(format!(
                    "cannot place two {}-cell HP codes apart in a {}-pixel frame",
                    args.code_size, args.size
                ));
            }
            second = area.place(&mut self.rng);
        }
        let alphas = angles.unwrap_or_else(|| [self.rng.range(-PI, PI), self.rng.range(-PI, PI)]);
        self.last = Some(([first, second], alphas));
        Ok(([first, second], alphas))
    }

    /// `last` moved by `step` pixels along the drift directions (reversing a direction's
    /// component where the step would leave the area) and turned by ±1 mrad.
    fn drifted(
        &mut self,
        (origins, angles): TwoMarkers,
        step: f64,
        area: &HpCodeArea,
    ) -> TwoMarkers {
        let mut moved = origins;
        for k in 0..2 {
            let next = origins[k] + self.directions[k] * step;
            for axis in 0..2 {
                if next[axis] < area.lo[axis] || next[axis] > area.hi[axis] {
                    self.directions[k][axis] = -self.directions[k][axis];
                }
            }
            moved[k] = origins[k] + self.directions[k] * step;
        }
        (moved, [angles[0] + 1e-3, angles[1] - 1e-3])
    }
}

/// The truth of a two-marker frame: each marker's pose and origin (pixels), and marker
/// `ids[1]`'s pose in marker `ids[0]`'s frame.
fn two_marker_truth(
    file: String,
    ids: [u64; 2],
    poses: &[Pose; 2],
    origins: [Vector2<f64>; 2],
) -> serde_json::Value {
    let markers: Vec<serde_json::Value> = (0..2)
        .map(|k| {
            let mut m = marker_truth(ids[k], &poses[k]);
            m["origin_px"] = serde_json::json!([origins[k].x, origins[k].y]);
            m
        })
        .collect();
    // Exactly the node's convention (vernier-interface/src/processing.rs): aTb of the SI-scaled poses.
    let a_from_b = poses[0]
        .scaled(METRES_PER_UM)
        .relative(&poses[1].scaled(METRES_PER_UM));
    let t = a_from_b.translation.vector;
    let (_, _, yaw) = a_from_b.rotation.euler_angles();
    serde_json::json!({
        "file": file,
        "markers": markers,
        "relative": {
            "a": ids[0], "b": ids[1],
            "position_m": [t.x, t.y, t.z],
            "yaw": yaw,
        },
    })
}

fn run(args: &Args) -> Result<(), String> {
    std::fs::create_dir_all(&args.out)
        .map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let truth = match args.kind {
        Kind::Periodic => serde_json::json!({
            "kind": "periodic",
            "size": args.size,
            "period": args.period,
            "pixel_size": args.pixel_size,
            "unit": "um",
            "frames": periodic_frames(args)?,
        }),
        Kind::Megarena => serde_json::json!({
            "kind": "megarena",
            "size": args.size,
            "period": args.period,
            "pixel_size": args.pixel_size,
            "code_depth": MEGARENA_CODE_DEPTH,
            "unit": "um",
            "frames": megarena_frames(args)?,
        }),
        Kind::HpCode => serde_json::json!({
            "kind": "hpcode",
            "size": args.size,
            "height": args.height.unwrap_or(args.size),
            "period": args.period,
            "pixel_size": args.pixel_size,
            "code_size": args.code_size,
            "ids": [args.ids.0, args.ids.1],
            "unit": "um",
            "frames": hpcode_frames(args)?,
        }),
    };
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
