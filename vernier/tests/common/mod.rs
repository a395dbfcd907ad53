//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};
use std::path::PathBuf;
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::layout::Layout;
use vernier::{Detector, GreyImage, Pose};

/// Folder of the real test images: `$VERNIER_DATA_DIR`, else `../shared/data` beside the
/// workspace. Panics (test failure, not skip) when it is missing.
pub fn data_dir() -> PathBuf {
    let dir = std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    assert!(
        dir.is_dir(),
        "test data folder {} is missing: set VERNIER_DATA_DIR to the shared/data folder",
        dir.display()
    );
    dir
}

/// Error of a periodic-grid measurement against the truth, invariant under the grid's
/// symmetries: `(translation error in pixels, angle error in radians)`.
///
/// Both poses describe a square lattice of period `period` (pattern units); the translation
/// error is the distance from the measured node to the nearest true node, in pixels.
pub fn lattice_error(
    measured: &Pose,
    truth: &Pose,
    period: f64,
    image_center: (f64, f64),
) -> (f64, f64) {
    let node = |p: &Pose| {
        let o = p.origin_in_image();
        (image_center.0 + o.x, image_center.1 + o.y)
    };
    let (m, t) = (node(measured), node(truth));
    let pitch_px = period / truth.pixel_size;
    let (s, c) = truth.alpha.sin_cos();
    let (dx, dy) = (m.0 - t.0, m.1 - t.1);
    // Offset in lattice units along the true grid axes, reduced to the nearest node.
    let u = (c * dx + s * dy) / pitch_px;
    let v = (-s * dx + c * dy) / pitch_px;
    let (eu, ev) = ((u - u.round()) * pitch_px, (v - v.round()) * pitch_px);
    let mut da = (measured.alpha - truth.alpha).rem_euclid(FRAC_PI_2);
    if da > FRAC_PI_4 {
        da -= FRAC_PI_2;
    }
    (eu.hypot(ev), da.abs())
}

/// `image` written as an 8-bit JPEG of `quality` (1–100) and read back, as a camera or a
/// user's re-encoding would leave it.
pub fn jpeg(image: &GreyImage, quality: u8) -> GreyImage {
    use image::codecs::jpeg::JpegEncoder;
    let bytes: Vec<u8> = image.quantized(8).iter().map(|&v| v as u8).collect();
    let mut encoded = Vec::new();
    JpegEncoder::new_with_quality(&mut encoded, quality)
        .encode(
            &bytes,
            image.width() as u32,
            image.height() as u32,
            image::ExtendedColorType::L8,
        )
        .expect("JPEG encoding");
    let decoded = image::load_from_memory(&encoded).expect("JPEG decoding");
    GreyImage::from_dynamic(&decoded).expect("grey image")
}

/// The HP code detector a user gets from `--hpcode --period PERIOD --code-size W` and nothing
/// else (polarity and window automatic).
pub fn hp_detector(period: f64, code_size: usize) -> Detector {
    let settings = DetectorSettings {
        pattern_type: MarkerKind::HpCode,
        period: Some(period),
        code_size: Some(code_size),
        ..Default::default()
    };
    Detector::new(settings.to_config().expect("HP settings")).expect("HP detector")
}

/// `image` with every level mapped through `f` (`[0, 1]` scale: gamma, contrast, inversion).
pub fn map_levels(image: &GreyImage, mut f: impl FnMut(f32) -> f32) -> GreyImage {
    let pixels = image.pixels().iter().map(|&v| f(v)).collect();
    GreyImage::new(image.width(), image.height(), pixels).expect("mapped image")
}

/// `image` times a gain field `gain(x, y)` of the pixel's fractional position in the image
/// (`[0, 1]²`): illumination gradients, vignetting.
pub fn illuminated(image: &GreyImage, gain: impl Fn(f64, f64) -> f64) -> GreyImage {
    let (w, h) = (image.width(), image.height());
    let pixels = image
        .pixels()
        .iter()
        .enumerate()
        .map(|(i, &v)| v * gain((i % w) as f64 / w as f64, (i / w) as f64 / h as f64) as f32)
        .collect();
    GreyImage::new(w, h, pixels).expect("illuminated image")
}

/// `image` plus white Gaussian noise of standard deviation `sigma` (`[0, 1]` scale), seeded.
pub fn noisy(image: &GreyImage, sigma: f64, seed: u64) -> GreyImage {
    use rand::{rngs::SmallRng, Rng, SeedableRng};
    let mut rng = SmallRng::seed_from_u64(seed);
    map_levels(image, |v| {
        v + (sigma * rng.sample::<f64, _>(rand_distr::StandardNormal)) as f32
    })
}

/// `clean` with Gaussian noise of standard deviation `noise` (fraction of full scale) added,
/// clipped to `[0, 1]` and quantised to 12 bits, as `vernier::render::render` does: one clean render serves
/// every noise draw.
pub fn noisy_12_bit(clean: &GreyImage, noise: f64, seed: u64) -> GreyImage {
    use rand::{rngs::SmallRng, SeedableRng};
    use rand_distr::{Distribution, Normal};
    let mut rng = SmallRng::seed_from_u64(seed);
    let normal = Normal::new(0.0, noise).unwrap();
    let levels = 4095.0;
    let pixels = clean
        .pixels()
        .iter()
        .map(|&v| ((v as f64 + normal.sample(&mut rng)).clamp(0.0, 1.0) * levels).round() / levels)
        .map(|v| v as f32)
        .collect();
    GreyImage::new(clean.width(), clean.height(), pixels).unwrap()
}

/// `image` under a Gaussian blur of standard deviation `sigma` pixels (separable, ±3σ, edges
/// replicated).
pub fn blurred(image: &GreyImage, sigma: f64) -> GreyImage {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp() as f32)
        .collect();
    let total: f32 = kernel.iter().sum();
    let (w, h) = (image.width() as isize, image.height() as isize);
    let pass = |src: &[f32], along_rows: bool| -> Vec<f32> {
        let mut out = vec![0.0f32; src.len()];
        for r in 0..h {
            for c in 0..w {
                let mut acc = 0.0;
                for (j, &k) in kernel.iter().enumerate() {
                    let d = j as isize - radius;
                    let (rr, cc) = if along_rows { (r, c + d) } else { (r + d, c) };
                    let (rr, cc) = (rr.clamp(0, h - 1), cc.clamp(0, w - 1));
                    acc += k * src[(rr * w + cc) as usize];
                }
                out[(r * w + c) as usize] = acc / total;
            }
        }
        out
    };
    let once = pass(image.pixels(), true);
    GreyImage::new(image.width(), image.height(), pass(&once, false)).expect("blurred image")
}

/// `image` turned by `degrees` (counter-clockwise on screen) about its centre, bilinear, on a
/// canvas that holds all of it, filled with the image's median level.
pub fn turned(image: &GreyImage, degrees: f64) -> GreyImage {
    let (s, c) = degrees.to_radians().sin_cos();
    let (w, h) = (image.width() as f64, image.height() as f64);
    let (ow, oh) = (
        (w * c.abs() + h * s.abs()).ceil() as usize,
        (w * s.abs() + h * c.abs()).ceil() as usize,
    );
    warped(image, ow, oh, |col, r| {
        let (x, y) = (col - ow as f64 / 2.0, r - oh as f64 / 2.0);
        // Inverse rotation (y down: counter-clockwise on screen is a negative angle).
        (c * x - s * y + w / 2.0, s * x + c * y + h / 2.0)
    })
}

/// `image` seen from a camera tilted by `degrees` about an axis at `axis_degrees` from the
/// image's x axis (a microscope's near-telecentric view: foreshortened by `cos(degrees)`
/// across that axis, no perspective), about the image centre. A tilt about an oblique axis
/// shears the marker: its right angles open or close (by ~5° at 25° about a diagonal).
pub fn tilted(image: &GreyImage, degrees: f64, axis_degrees: f64) -> GreyImage {
    let k = degrees.to_radians().cos();
    let (s, c) = axis_degrees.to_radians().sin_cos();
    let (w, h) = (image.width() as f64, image.height() as f64);
    warped(image, image.width(), image.height(), |col, r| {
        // Output to input: undo the foreshortening across the axis (along its normal).
        let (x, y) = (col - w / 2.0, r - h / 2.0);
        let (along, across) = (c * x + s * y, -s * x + c * y);
        let across = across / k;
        (
            c * along - s * across + w / 2.0,
            s * along + c * across + h / 2.0,
        )
    })
}

/// An `ow × oh` image whose pixel `(col, row)` is `image` at `source(col, row)` (bilinear),
/// the image's median level where that falls outside it.
fn warped(
    image: &GreyImage,
    ow: usize,
    oh: usize,
    source: impl Fn(f64, f64) -> (f64, f64),
) -> GreyImage {
    let mut sorted = image.pixels().to_vec();
    sorted.sort_by(f32::total_cmp);
    let fill = sorted[sorted.len() / 2];
    let mut pixels = Vec::with_capacity(ow * oh);
    for r in 0..oh {
        for col in 0..ow {
            let (x, y) = source(col as f64, r as f64);
            pixels.push(image.bilinear(x, y).unwrap_or(fill));
        }
    }
    GreyImage::new(ow, oh, pixels).expect("warped image")
}

/// `image` seen in perspective: its top edge shrunk by `fraction` of the width at each end
/// (keystone, a camera looking down at the part from below its top edge), bilinear, the
/// uncovered corners filled with the median level. A marker half the image high then has its
/// far edge about `fraction` narrower than its near edge.
pub fn keystone(image: &GreyImage, fraction: f64) -> GreyImage {
    let (w, h) = (image.width() as f64, image.height() as f64);
    let k = fraction * w;
    // The homography from output to input pixels: output corners `to` show input corners
    // `from` (eight equations for its eight unknowns).
    let to = [(k, 0.0), (w - k, 0.0), (w, h), (0.0, h)];
    let from = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)];
    let mut a = nalgebra::SMatrix::<f64, 8, 8>::zeros();
    let mut b = nalgebra::SVector::<f64, 8>::zeros();
    for (i, (&(x, y), &(u, v))) in to.iter().zip(&from).enumerate() {
        let rows = [
            [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y],
            [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y],
        ];
        for (j, row) in rows.iter().enumerate() {
            for (col, &value) in row.iter().enumerate() {
                a[(2 * i + j, col)] = value;
            }
        }
        (b[2 * i], b[2 * i + 1]) = (u, v);
    }
    let m = a.lu().solve(&b).expect("keystone homography");
    warped(image, image.width(), image.height(), |x, y| {
        let d = m[6] * x + m[7] * y + 1.0;
        (
            (m[0] * x + m[1] * y + m[2]) / d,
            (m[3] * x + m[4] * y + m[5]) / d,
        )
    })
}

/// `image` scaled by `factor` ≤ 1 (a lower magnification): box-averaged over each output
/// pixel's footprint, as a sensor with larger pixels would integrate it.
pub fn scaled_down(image: &GreyImage, factor: f64) -> GreyImage {
    let (w, h) = (image.width(), image.height());
    let (ow, oh) = (
        ((w as f64 * factor) as usize).max(1),
        ((h as f64 * factor) as usize).max(1),
    );
    let span = |i: usize, n: usize| {
        let a = (i as f64 / factor).floor() as usize;
        a.min(n - 1)..(((i + 1) as f64 / factor).floor() as usize).clamp(a + 1, n)
    };
    let src = image.pixels();
    let mut pixels = Vec::with_capacity(ow * oh);
    for r in 0..oh {
        for c in 0..ow {
            let (rows, cols) = (span(r, h), span(c, w));
            let n = (rows.len() * cols.len()) as f32;
            let sum: f32 = rows
                .flat_map(|y| cols.clone().map(move |x| src[y * w + x]))
                .sum();
            pixels.push(sum / n);
        }
    }
    GreyImage::new(ow, oh, pixels).expect("scaled image")
}

/// A degradation of a real image (the view a lab might get of the same marker), and whether
/// every marker the image must give is asserted to be found under it.
pub struct Degradation {
    /// What was done, for the table.
    pub name: &'static str,
    /// Every required marker must still be found.
    pub asserted: bool,
    /// The degraded view.
    pub apply: fn(&GreyImage) -> GreyImage,
}

/// The degradations of the real-image tests (`real_hpcode_views.rs`, `stamp.rs`): the mild ones (one
/// pixel of blur, noise and JPEG at camera levels, illumination, a quarter of the contrast,
/// inversion, any turn, lower magnifications, perspective up to a 9 % keystone, overexposure)
/// must keep every marker; the harsh ones (gamma or strong overexposure, blur at a quarter period
/// and beyond, heavy noise, a third of the magnification) are counted only. None may give an ID that is not in the image.
pub const DEGRADATIONS: &[Degradation] = &[
    mild("blur 1 px", |i| blurred(i, 1.0)),
    mild("noise 2 %", |i| noisy(i, 0.02, 1)),
    mild("JPEG q60", |i| jpeg(i, 60)),
    mild("JPEG q30", |i| jpeg(i, 30)),
    mild("contrast ×0.25", |i| {
        map_levels(i, |v| 0.5 + 0.25 * (v - 0.5))
    }),
    mild("inverted", |i| map_levels(i, |v| 1.0 - v)),
    mild("gradient 0.35–1", |i| {
        illuminated(i, |x, _| 0.35 + 0.65 * x)
    }),
    // Low contrast under a steep gradient: the level moves by more than the dots' contrast
    // across a marker (finders and dots read against the light where they are,
    // docs/design.md#level-surfaces).
    mild("contrast ×0.3 under a gradient 0.3–1", |i| {
        illuminated(&map_levels(i, |v| 0.5 + 0.3 * (v - 0.5)), |x, _| {
            0.3 + 0.7 * x
        })
    }),
    mild("vignetting", |i| {
        illuminated(i, |x, y| {
            (1.0 - 0.8 * ((x - 0.3).powi(2) + (y - 0.4).powi(2))).max(0.15)
        })
    }),
    mild("turned 7°", |i| turned(i, 7.0)),
    mild("turned 23°", |i| turned(i, 23.0)),
    mild("turned 45°", |i| turned(i, 45.0)),
    mild("scaled ×0.75", |i| scaled_down(i, 0.75)),
    mild("scaled ×0.5", |i| scaled_down(i, 0.5)),
    mild("keystone 3 %", |i| keystone(i, 0.03)),
    // A tilt about an oblique axis shears the right angle of a marker's finders, and the
    // finders of two markers side by side then fit a marker better than its own (all triples
    // are tried, docs/design.md#hp-grouping).
    mild("tilted 25° about 30°", |i| tilted(i, 25.0, 30.0)),
    mild("tilted 25° about 135°", |i| tilted(i, 25.0, 135.0)),
    // Strong perspective on markers half the image wide: the window's planes do not hold to the
    // far corner (grids drifting off a far edge read another row as the ID without the check
    // of the field's edges: `HPCodeImage_20um.png` and `code21.jpg` at 5 and 6.5 %). HP codes
    // are read on the grid fitted to their own dots (docs/design.md#hp-dot-homography); before
    // it, 15, 16 and 11 of their 16 markers were found at 5, 6.5 and 9 %.
    mild("keystone 5 %", |i| keystone(i, 0.05)),
    mild("keystone 6.5 %", |i| keystone(i, 0.065)),
    mild("keystone 9 %", |i| keystone(i, 0.09)),
    // Overexposed: substrate, gaps and finder centres saturate alike (finders read from their
    // gap and ring).
    mild("levels ×1.8, clipped", |i| {
        map_levels(i, |v| (1.8 * v).min(1.0))
    }),
    harsh("levels ×2.5, clipped", |i| {
        map_levels(i, |v| (2.5 * v).min(1.0))
    }),
    // Squared levels open the dim rings of `code18_90.jpg`'s finders at every threshold level
    // (a finder needs a closed gap inside its ring).
    harsh("gamma 2", |i| map_levels(i, |v| v * v)),
    // Square-rooted levels leave the bright residue over `code17.jpg`'s ID row too close to
    // its dots: that marker is refused (an undecidable ID dot).
    harsh("gamma 0.5", |i| map_levels(i, f32::sqrt)),
    harsh("blur 2 px", |i| blurred(i, 2.0)),
    harsh("noise 5 %", |i| noisy(i, 0.05, 2)),
    harsh("scaled ×0.35", |i| scaled_down(i, 0.35)),
];

/// A degradation whose views must keep every required marker.
const fn mild(name: &'static str, apply: fn(&GreyImage) -> GreyImage) -> Degradation {
    Degradation {
        name,
        asserted: true,
        apply,
    }
}

/// A degradation whose views are counted only.
const fn harsh(name: &'static str, apply: fn(&GreyImage) -> GreyImage) -> Degradation {
    Degradation {
        name,
        asserted: false,
        apply,
    }
}

/// A real image of the data set: its file, the IDs of its markers, and how many of them every
/// view must give.
#[derive(Clone, Copy)]
pub struct RealImage {
    /// File name (for messages).
    pub file: &'static str,
    /// IDs of its markers.
    pub ids: &'static [u64],
    /// Markers every view must give (fewer than `ids` where one is physically damaged).
    pub required: usize,
}

/// Runs `detect` (image index, view → IDs found) on every [`DEGRADATIONS`] view of `images`
/// and prints a table per degradation: required markers found, IDs not in the image (or more
/// markers than it holds). Returns the failures: any wrong or extra ID, and a required marker
/// missed under an asserted degradation.
pub fn degraded_views(
    images: &[(RealImage, GreyImage)],
    detect: impl Fn(usize, &GreyImage) -> Vec<u64>,
) -> Vec<String> {
    let mut failures = Vec::new();
    let (mut found_all, mut required_all) = (0, 0);
    println!("| degradation | required markers found | wrong or extra IDs | short of markers |");
    println!("|---|---:|---:|---|");
    for degradation in DEGRADATIONS {
        let (mut found, mut required, mut wrong) = (0, 0, 0);
        let mut short = Vec::new();
        for (i, (real, image)) in images.iter().enumerate() {
            let ids = detect(i, &(degradation.apply)(image));
            let stray = ids.iter().filter(|id| !real.ids.contains(id)).count()
                + ids.len().saturating_sub(real.ids.len());
            let kept = (ids.len() - stray.min(ids.len())).min(real.required);
            wrong += stray;
            found += kept;
            required += real.required;
            if kept < real.required {
                short.push(real.file);
            }
            if stray > 0 || (degradation.asserted && kept < real.required) {
                failures.push(format!(
                    "{} {}: IDs {ids:?}, expected {:?} (at least {})",
                    real.file, degradation.name, real.ids, real.required
                ));
            }
        }
        println!(
            "| {} | {found} / {required} | {wrong} | {} |",
            degradation.name,
            short.join(", ")
        );
        found_all += found;
        required_all += required;
    }
    println!("all: {found_all} / {required_all} required markers found");
    failures
}

/// Pinhole render of `layout` at `pose` with focal length `focal` pixels: pixel rays are
/// intersected with the pattern plane placed at depth `z = pixel_size·focal` (magnification
/// `1/pixel_size` at the centre), the layout's intensity point-sampled 2×2 per pixel.
pub fn render_perspective(layout: &dyn Layout, pose: &Pose, focal: f64, size: usize) -> GreyImage {
    let depth = pose.pixel_size * focal;
    let rotation = pose.rotation();
    let normal = rotation * nalgebra::Vector3::z();
    let mut pixels = vec![0.0f32; size * size];
    let c = (size / 2) as f64;
    for row in 0..size {
        for col in 0..size {
            let mut sum = 0.0;
            for (dx, dy) in [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)] {
                let ray = nalgebra::Vector3::new(col as f64 + dx - c, row as f64 + dy - c, focal);
                let t = depth * normal.z / normal.dot(&ray);
                let hit = ray * t - nalgebra::Vector3::new(0.0, 0.0, depth);
                let p = rotation.transpose() * hit;
                sum += layout.intensity(p.x - pose.x, p.y - pose.y);
            }
            pixels[row * size + col] = (sum / 4.0) as f32;
        }
    }
    GreyImage::new(size, size, pixels).unwrap()
}

/// Render options of the synthetic-view tests: blur 0.5 px; with `noise > 0`, Gaussian noise
/// of that fraction of full scale, 12-bit, grey levels 0.05/0.95, seeded.
pub fn render_options(size: usize, noise: f64, seed: u64) -> vernier::render::RenderOptions {
    let mut opts = vernier::render::RenderOptions::new(size, size);
    opts.blur_sigma = 0.5;
    if noise > 0.0 {
        opts.noise_std = noise;
        opts.bit_depth = Some(12);
        opts.background = 0.05;
        opts.foreground = 0.95;
        opts.seed = seed;
    }
    opts
}

/// The out-of-plane tilts of the 6-DoF tests: every sign and size combination of
/// `beta, gamma ∈ {±0.1, ±0.2, ±0.3}` rad.
pub fn tilts() -> Vec<(f64, f64)> {
    let values = [-0.3, -0.2, -0.1, 0.1, 0.2, 0.3];
    values
        .iter()
        .flat_map(|&b| values.iter().map(move |&g| (b, g)))
        .collect()
}

/// Checks marker `m` of a perspective render tilted by `(beta, gamma)` rad with the
/// out-of-plane pose on: both angles within `tolerance` rad, a perspective cue above 0.5, and
/// in its covariance `cov` real (small) roll and pitch variances and an unobserved `z`.
/// Returns the larger angle error and the cue strength.
pub fn check_perspective_tilt(
    m: &vernier::MarkerPose,
    (beta, gamma): (f64, f64),
    tolerance: f64,
    cov: &[[f64; 6]; 6],
) -> (f64, f64) {
    let error = (m.pose.beta - beta).abs().max((m.pose.gamma - gamma).abs());
    let cue = m.pose_3d_cue_strength.unwrap_or(0.0);
    assert!(
        error < tolerance,
        "truth ({beta}, {gamma}), got ({}, {}), cue {cue}",
        m.pose.beta,
        m.pose.gamma
    );
    assert!(cue > 0.5, "truth ({beta}, {gamma}): cue {cue}");
    // roll = γ, pitch = β get real variances; z stays unknown.
    assert!(cov[3][3] > 0.0 && cov[3][3] < 1e-4, "{cov:?}");
    assert!(cov[4][4] > 0.0 && cov[4][4] < 1e-4, "{cov:?}");
    assert_eq!(cov[2][2], 1e6);
    (error, cue)
}

/// Predicted against observed σ of `(beta, gamma, alpha)` over noise draws of one tilted view
/// ([`TiltSpread::add`] each draw's marker, then [`TiltSpread::ratios`]).
#[derive(Default)]
pub struct TiltSpread {
    samples: [Vec<f64>; 3],
    variance_sum: [f64; 3],
}

impl TiltSpread {
    /// Adds one draw's marker `m` (both mirror solutions folded onto the truth's, whose beta
    /// is `truth_beta`) and its covariance `cov` (pitch = β, roll = γ, yaw = α).
    pub fn add(&mut self, m: &vernier::MarkerPose, truth_beta: f64, cov: &[[f64; 6]; 6]) {
        let sign = if m.pose.beta * truth_beta >= 0.0 {
            1.0
        } else {
            -1.0
        };
        let values = [sign * m.pose.beta, sign * m.pose.gamma, m.pose.alpha];
        for (k, (i, v)) in [4, 3, 5].into_iter().zip(values).enumerate() {
            self.samples[k].push(v);
            self.variance_sum[k] += cov[i][i];
        }
    }

    /// Each angle's RMS predicted σ over its sample standard deviation.
    pub fn ratios(&self) -> [f64; 3] {
        [0, 1, 2].map(|k| {
            let v = &self.samples[k];
            let n = v.len() as f64;
            let mean = v.iter().sum::<f64>() / n;
            let spread = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            (self.variance_sum[k] / n).sqrt() / spread
        })
    }
}
