//! HP codes with a fibre or a blob over their ID row or left column: a marker should be found
//! with its ID or refused, never reported with another ID. Occluders as dark as the dots of a
//! dark-dot marker (or as bright as those of a bright-dot one) can fill an empty ID position;
//! occluders at the background's level can hide a present one. The stress suite keeps its
//! dust and hair off the ID strips so that its found rate measures detection; this test
//! measures what happens when they are not, and prints its table
//! (`cargo test --release -p vernier --test hpcode_id_occluders -- --nocapture`).

mod common;

use nalgebra::Vector2;
use rand::{rngs::SmallRng, Rng, SeedableRng};
use std::f64::consts::PI;
use vernier::layout::HpCodeLayout;
use vernier::render::{render, RenderOptions};
use vernier::{GreyImage, Pose};

/// Physical period of the rendered markers, µm.
const PERIOD: f64 = 10.0;
/// Random markers per kind of occluder.
const CASES: usize = 60;
/// Blob radius, periods, below which (with the blur) a blob centred on an ID position reaches
/// none of the samples of a neighbouring dot.
const CONFINED_RADIUS: f64 = 0.85;
/// Wrong IDs of occluders that reach beyond their position, measured (listed at the assert).
const KNOWN_UNCAUGHT: usize = 1;

/// What lies over the ID strip.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Occluder {
    /// A straight fibre 0.05–0.6 period wide.
    Fibre,
    /// A round blob 0.3–1.2 period in radius.
    Blob,
}

/// `image` with `occluder` through (fibre) or around (blob) pixel `at`, blended `strength` of
/// the way towards `level`, antialiased over one pixel. `size` is the fibre's width or the
/// blob's radius, pixels; `angle` the fibre's direction, radians.
fn occluded(
    image: &GreyImage,
    occluder: Occluder,
    at: Vector2<f64>,
    (size, angle): (f64, f64),
    (level, strength): (f32, f32),
) -> GreyImage {
    let w = image.width();
    let along = Vector2::new(angle.cos(), angle.sin());
    let mut pixels = image.pixels().to_vec();
    for (i, v) in pixels.iter_mut().enumerate() {
        let d = Vector2::new((i % w) as f64, (i / w) as f64) - at;
        let inside = match occluder {
            Occluder::Fibre => 0.5 * size - (d.x * along.y - d.y * along.x).abs(),
            Occluder::Blob => size - d.norm(),
        };
        let cover = (inside + 0.5).clamp(0.0, 1.0) as f32;
        *v += strength * cover * (level - *v);
    }
    GreyImage::new(w, image.height(), pixels).expect("occluded image")
}

/// Outcome counts of one kind of occluder: found with its ID, refused, reported with another
/// ID (occluders that reach beyond their position, and those confined to it).
#[derive(Default, Debug)]
struct Outcomes {
    found: usize,
    refused: usize,
    wrong: Vec<String>,
    wrong_confined: Vec<String>,
}

/// One random marker (W 33 or 37, random ID, angle, period 7–14 px, polarity, blur, noise)
/// with a random occluder of `kind` over a random point of its ID row or left column, at the
/// dots' level (`like_dots`) or the background's.
fn run_case(rng: &mut SmallRng, kind: Occluder, like_dots: bool, outcomes: &mut Outcomes) {
    let code_size: usize = if rng.random_bool(0.5) { 33 } else { 37 };
    let dots = code_size.div_ceil(2);
    let id = rng.random_range(0..1u64 << ((code_size - 15) / 2));
    let period_px = rng.random_range(7.0..14.0);
    let alpha = rng.random_range(-PI..PI);
    let side = (dots as f64 * period_px * 1.6) as usize + 40;
    let (bright, dark) = (rng.random_range(0.7..0.95), rng.random_range(0.05..0.3));
    let dark_dots = rng.random_bool(0.5);
    let (background, foreground) = if dark_dots {
        (bright, dark)
    } else {
        (dark, bright)
    };
    let layout = HpCodeLayout::from_code_size(PERIOD, code_size)
        .expect("layout")
        .with_id(id)
        .expect("ID");
    let offset = Vector2::new(rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0));
    let pose = Pose::from_origin_in_image(offset, alpha, PERIOD / period_px);
    let options = RenderOptions {
        background,
        foreground,
        ..RenderOptions::new(side, side)
    };
    let image = render(&layout, &pose, &options).expect("render");
    // Dot (r, c) of the marker is at centre + step_x·(c − h) + step_y·(r − h).
    let centre = Vector2::new((side / 2) as f64, (side / 2) as f64) + offset;
    let step_x = Vector2::new(alpha.cos(), alpha.sin()) * period_px;
    let step_y = Vector2::new(-alpha.sin(), alpha.cos()) * period_px;
    let h = (dots - 1) as f64 / 2.0;
    let along = rng.random_range(4.0..(dots - 5) as f64 + 0.01).round();
    let across = rng.random_range(-0.3..0.3);
    let (r, c) = if rng.random_bool(0.5) {
        (across, along)
    } else {
        (along, across)
    };
    let at = centre + step_x * (c - h) + step_y * (r - h);
    let size = match kind {
        Occluder::Fibre => rng.random_range(0.05..0.6),
        Occluder::Blob => rng.random_range(0.3..1.2),
    } * period_px;
    let level = if like_dots { foreground } else { background };
    let strength = rng.random_range(0.5..1.0);
    let spoiled = occluded(
        &image,
        kind,
        at,
        (size, rng.random_range(0.0..PI)),
        (level, strength),
    );
    let blur = rng.random_range(0.3..1.5);
    let noise = rng.random_range(0.0..0.03);
    let seed = rng.random();
    let seen = common::noisy(&common::blurred(&spoiled, blur), noise, seed);
    let found = common::hp_detector(PERIOD, code_size)
        .detect(&seen)
        .expect("detection");
    let case = format!(
        "ID {id} W {code_size}, period {period_px:.1} px, {} dots, {kind:?} {:.2} period at \
         ({r:.1}, {c:.1}), level of the {}, strength {strength:.2}, blur {blur:.2} px, noise \
         {noise:.3}",
        if dark_dots { "dark" } else { "bright" },
        size / period_px,
        if like_dots { "dots" } else { "background" },
    );
    // A blob that cannot reach a neighbouring dot's samples (0.85 period from the position)
    // leaves the image of another marker: no reader can tell them apart (HP codes carry no
    // check bits), so its wrong IDs are counted apart.
    let confined = kind == Occluder::Blob && size + blur < CONFINED_RADIUS * period_px;
    match found.as_slice() {
        [] => outcomes.refused += 1,
        [m] if m.id == id && (m.origin_px - centre).norm() < 1.0 => outcomes.found += 1,
        other => {
            let read: Vec<u64> = other.iter().map(|m| m.id).collect();
            let wrong = match confined {
                true => &mut outcomes.wrong_confined,
                false => &mut outcomes.wrong,
            };
            wrong.push(format!("{case}: read {read:?}"));
            // For a look at it: `VERNIER_OCCLUDER_DUMP=folder` writes the image of each.
            if let Some(dir) = std::env::var_os("VERNIER_OCCLUDER_DUMP") {
                let path = std::path::Path::new(&dir).join(format!("id{id}_w{code_size}.png"));
                seen.save_png(path, 16).expect("dump");
            }
        }
    }
}

#[test]
fn occluders_over_the_id_strips_are_refused_rather_than_misread() {
    // Other seeds: `VERNIER_OCCLUDER_SEED=12 cargo test …` (the bound below is seed 11's).
    let seed = std::env::var("VERNIER_OCCLUDER_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(11);
    let mut rng = SmallRng::seed_from_u64(seed);
    let (mut wrong, mut confined) = (Vec::new(), Vec::new());
    println!(
        "| occluder over an ID strip | found with its ID | refused | wrong ID \
         | of which confined to one position |"
    );
    println!("|---|---:|---:|---:|---:|");
    for kind in [Occluder::Fibre, Occluder::Blob] {
        for like_dots in [true, false] {
            let mut outcomes = Outcomes::default();
            for _ in 0..CASES {
                run_case(&mut rng, kind, like_dots, &mut outcomes);
            }
            let level = if like_dots { "dots" } else { "background" };
            let confined_count = outcomes.wrong_confined.len();
            println!(
                "| {kind:?}, level of the {level} | {} | {} | {} | {confined_count} |",
                outcomes.found,
                outcomes.refused,
                outcomes.wrong.len() + confined_count,
            );
            wrong.extend(outcomes.wrong);
            confined.extend(outcomes.wrong_confined);
        }
    }
    println!("confined to one ID position (indistinguishable from another marker):");
    confined.iter().for_each(|c| println!("  {c}"));
    println!("reaching beyond one position:");
    wrong.iter().for_each(|c| println!("  {c}"));
    // Known gap, measured: one wide, weak fibre crossing the row obliquely (ID 1355: 0.53
    // period, 65 %), whose sides inside the dot field fall on dots, so that no line through
    // the position stands out of both its sides. This seed is the one the present-dot checks
    // were built with; seeds 12–14 (on which the hidden-side check was built) leave 1, 1 and
    // 0 such cases (docs/design.md#hp-id-occluders).
    assert!(
        wrong.len() <= KNOWN_UNCAUGHT,
        "{} wrong:\n{}",
        wrong.len(),
        wrong.join("\n")
    );
}
