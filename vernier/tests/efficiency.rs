//! Statistical efficiency and honest uncertainty on renders (issue 12, parts 2 and 3;
//! docs/design.md#uncertainty).
//!
//! For a periodic grid, an HP code and a stamp, each rendered at a known pose (area sampling,
//! 0.5 px optical blur, grey levels 0.2/0.8 so that the noise never clips):
//!
//! * **Cramér–Rao bound.** The Fisher information of `(x, y, alpha, pixel_size)` under white
//!   Gaussian noise is `F = JᵀJ/σ²`, `J` the renderer's derivatives by central differences;
//!   the bound is `diag(F⁻¹)` (pixel size a nuisance parameter, hence the full inverse). `σ²`
//!   includes the 12-bit quantisation (`Δ²/12`). The RMS error of the detector over 200 noisy
//!   renders (1 % of full scale, quantised to 12 bits) is compared with it.
//! * **Honest uncertainty.** On the same renders, and at 5 % noise, the σ that
//!   [`vernier::MarkerPose::covariance`] predicts (what the ROS node publishes: camera-frame x,
//!   y and yaw) is compared with the spread of the measurements: the ratio must lie in
//!   [0.75, 1.33].
//!
//! The noise is added here with a seeded generator (Gaussian, then rounding to 12 bits: what
//! `RenderOptions::noise_std` and `bit_depth` do) so that one clean render serves every draw.
//!
//! `cargo test --release -p vernier --test efficiency -- --nocapture` prints every ratio.

mod common;

use nalgebra::{Matrix4, Vector2};
use rand::{rngs::SmallRng, SeedableRng};
use rand_distr::{Distribution, Normal};
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::hpcode::{HpCodeDetector, HpCodeParams};
use vernier::layout::{BitmapLayout, HpCodeLayout, Layout, PeriodicLayout};
use vernier::phase::wrap_to_pi;
use vernier::render::{render, RenderOptions};
use vernier::stamp::{StampDetector, StampParams};
use vernier::{Detector, GreyImage, Pose};

/// Physical period of every marker, pattern units.
const PERIOD: f64 = 10.0;
/// Quantisation of the noisy renders.
const BITS: u32 = 12;
/// Noisy renders per noise level.
const RENDERS: usize = 200;
/// Accepted range of predicted σ / empirical σ.
const HONEST: std::ops::RangeInclusive<f64> = 0.75..=1.33;

/// One rendered marker and the detector a user would run on it.
struct Case {
    name: &'static str,
    layout: Box<dyn Layout>,
    truth: Pose,
    options: RenderOptions,
    settings: DetectorSettings,
    /// The `window_px` the node passes to `covariance`: `window_size`, else the image's shorter
    /// side.
    window_px: f64,
    /// The analysed window `(centre col, centre row, side)`, for the bound restricted to it.
    window: (i64, i64, usize),
    /// `x, y` known modulo one period (periodic grid).
    modulo: bool,
}

fn options(size: usize, blur: f64) -> RenderOptions {
    RenderOptions {
        blur_sigma: blur,
        background: 0.2,
        foreground: 0.8,
        ..RenderOptions::new(size, size)
    }
}

/// 128² image of a grid at 8.33 px per period.
fn periodic_case() -> Case {
    let size = 128;
    Case {
        name: "periodic",
        layout: Box::new(PeriodicLayout::new(PERIOD, 61, 61).unwrap()),
        truth: Pose::planar(1.3, -2.1, 0.3, 1.2),
        options: options(size, 0.5),
        settings: DetectorSettings {
            pattern_type: MarkerKind::Periodic,
            period: Some(PERIOD),
            // The whole-image fit is opt-in for periodic grids (its cost).
            field_fit: Some(true),
            ..Default::default()
        },
        window_px: size as f64,
        window: ((size / 2) as i64, (size / 2) as i64, size),
        modulo: true,
    }
}

/// A 33-cell HP code (137 px wide at 8.33 px per period) near the centre of a 256² image.
///
/// The node passes `window_size` (else the image side) as the analysed window to
/// `covariance`; HP codes and stamps size their window automatically inside the marker, so the
/// detector is given that size explicitly (the same window: only a larger one is apodised).
fn hpcode_case() -> Case {
    let truth = Pose::from_origin_in_image(Vector2::new(1.7, -2.3), 0.4, 1.2);
    let layout = HpCodeLayout::new(PERIOD, 17).unwrap().with_id(5).unwrap();
    let options = options(256, 0.5);
    let image = render(&layout, &truth, &options).unwrap();
    let found = HpCodeDetector::new(HpCodeParams::new(PERIOD, 33))
        .unwrap()
        .detect(&image)
        .unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    let ((cx, cy), side) = found[0].window;
    Case {
        name: "HP code",
        layout: Box::new(layout),
        truth,
        options,
        settings: DetectorSettings {
            pattern_type: MarkerKind::HpCode,
            period: Some(PERIOD),
            code_size: Some(33),
            window_size: Some(side),
            ..Default::default()
        },
        window_px: side as f64,
        window: (cx, cy, side),
        modulo: false,
    }
}

fn stamp_bitmap() -> std::path::PathBuf {
    common::data_dir().join("layouts/stampD.png")
}

/// The data set's 69-cell stamp "D" (242 px wide at 7 px per period) in a 320² image.
fn stamp_case() -> Case {
    let truth = Pose::from_origin_in_image(Vector2::new(-1.4, 2.6), 0.3, PERIOD / 7.0);
    stamp_case_at(truth, options(320, 0.5))
}

/// The same stamp along the pixel axes (turned 1.5 mrad: the lab's usual mounting) at 16 px
/// per period in a 600² image: the whole-field fit bins it 2 × 2 through the anti-aliasing
/// filter (docs/design.md#anti-aliased-binning), where a box average folded its harmonics onto
/// each other.
fn binned_stamp_case() -> Case {
    let truth = Pose::from_origin_in_image(Vector2::new(-1.4, 2.6), 0.0015, PERIOD / 16.0);
    stamp_case_at(truth, options(600, 0.5))
}

/// Stamp "D" rendered at `truth` with `options`, measured in the window its detection takes.
fn stamp_case_at(truth: Pose, options: RenderOptions) -> Case {
    let bitmap = BitmapLayout::from_image_file(PERIOD, stamp_bitmap()).unwrap();
    let image = render(&bitmap, &truth, &options).unwrap();
    let found = StampDetector::new(StampParams::new(PERIOD, vec![bitmap.clone()]))
        .unwrap()
        .detect(&image)
        .unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    let ((cx, cy), side) = (found[0].window_center, found[0].window_size);
    Case {
        name: "stamp",
        layout: Box::new(bitmap),
        truth,
        options,
        settings: DetectorSettings {
            pattern_type: MarkerKind::Stamp,
            period: Some(PERIOD),
            window_size: Some(side),
            bitmaps: vec![stamp_bitmap()],
            ..Default::default()
        },
        window_px: side as f64,
        window: (cx, cy, side),
        modulo: false,
    }
}

/// White-noise σ of a render with noise `noise` and 12-bit rounding.
fn noise_sigma(noise: f64) -> f64 {
    let step = 1.0 / ((1u32 << BITS) - 1) as f64;
    (noise * noise + step * step / 12.0).sqrt()
}

/// Cramér–Rao bounds of `(x, y, alpha, pixel_size)` (variances, pattern units and radians) for
/// white noise of unit σ (they scale as σ²): from every pixel, and from the pixels of `region`
/// (`(first col, first row, side)`) only.
fn crlb(case: &Case, region: (i64, i64, usize)) -> ([f64; 4], [f64; 4]) {
    let t = case.truth;
    // Steps moving the image by ~0.005 px (at the border for alpha and the scale).
    let half = case.options.width.max(case.options.height) as f64 / 2.0;
    let h = [
        0.005 * t.pixel_size,
        0.005 * t.pixel_size,
        0.005 / half,
        0.005 / half * t.pixel_size,
    ];
    let moved = |k: usize, sign: f64| {
        let mut p = t;
        let v = [&mut p.x, &mut p.y, &mut p.alpha, &mut p.pixel_size];
        *v[k] += sign * h[k];
        render(case.layout.as_ref(), &p, &case.options).unwrap()
    };
    let jacobian: Vec<Vec<f64>> = (0..4)
        .map(|k| {
            let (plus, minus) = (moved(k, 1.0), moved(k, -1.0));
            plus.pixels()
                .iter()
                .zip(minus.pixels())
                .map(|(&p, &m)| (p as f64 - m as f64) / (2.0 * h[k]))
                .collect()
        })
        .collect();
    let w = case.options.width;
    let (c0, r0, side) = region;
    let inside = |i: usize| {
        let (c, r) = ((i % w) as i64, (i / w) as i64);
        (c0..c0 + side as i64).contains(&c) && (r0..r0 + side as i64).contains(&r)
    };
    let (mut full, mut windowed) = (Matrix4::<f64>::zeros(), Matrix4::<f64>::zeros());
    for i in 0..4 {
        for j in 0..4 {
            for (n, (a, b)) in jacobian[i].iter().zip(&jacobian[j]).enumerate() {
                full[(i, j)] += a * b;
                if inside(n) {
                    windowed[(i, j)] += a * b;
                }
            }
        }
    }
    let diagonal = |fisher: Matrix4<f64>| {
        let bound = fisher
            .try_inverse()
            .expect("Fisher information is invertible");
        [0, 1, 2, 3].map(|k| bound[(k, k)])
    };
    (diagonal(full), diagonal(windowed))
}

/// `clean` plus Gaussian noise of σ `noise`, clamped to [0, 1] and rounded to 12 bits.
fn noisy(clean: &GreyImage, noise: f64, rng: &mut SmallRng) -> GreyImage {
    let normal = Normal::new(0.0, noise).unwrap();
    let levels = ((1u32 << BITS) - 1) as f64;
    let pixels = clean
        .pixels()
        .iter()
        .map(|&v| {
            let v = (v as f64 + normal.sample(rng)).clamp(0.0, 1.0);
            ((v * levels).round() / levels) as f32
        })
        .collect();
    GreyImage::new(clean.width(), clean.height(), pixels).unwrap()
}

fn spread(v: &[f64]) -> f64 {
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

/// Statistics of the detector over noisy renders of one case.
struct Measured {
    /// RMS error of the pose's x, y (pixels) and alpha (rad).
    rms: [f64; 3],
    /// Standard deviation of the camera-frame x, y (pixels), yaw (rad) and the measured pixel
    /// size (relative).
    empirical: [f64; 4],
    /// σ of the same from `MarkerPose::covariance` and `MarkerPose::pixel_size_std` (root of
    /// the mean variance).
    predicted: [f64; 4],
}

impl Measured {
    fn honesty(&self) -> [f64; 4] {
        [0, 1, 2, 3].map(|k| self.predicted[k] / self.empirical[k])
    }
}

fn measure(case: &Case, clean: &GreyImage, noise: f64, renders: usize, seed: u64) -> Measured {
    let mut detector = Detector::new(case.settings.to_config().unwrap()).unwrap();
    let t = case.truth;
    let px = t.pixel_size;
    let mut rng = SmallRng::seed_from_u64(seed);
    let (mut errors, mut camera, mut scale) = ([vec![], vec![], vec![]], [vec![], vec![]], vec![]);
    let mut variance = [0.0; 4];
    for _ in 0..renders {
        let found = detector.detect(&noisy(clean, noise, &mut rng)).unwrap();
        assert_eq!(found.len(), 1, "{}: {found:?}", case.name);
        let m = &found[0];
        let (mut dx, mut dy) = (m.pose.x - t.x, m.pose.y - t.y);
        if case.modulo {
            dx -= PERIOD * (dx / PERIOD).round();
            dy -= PERIOD * (dy / PERIOD).round();
        }
        errors[0].push(dx / px);
        errors[1].push(dy / px);
        errors[2].push(wrap_to_pi(m.pose.alpha - t.alpha));
        // Camera-frame translation of cTp (what the covariance describes), period shift undone.
        let unwrapped = Pose {
            x: t.x + dx,
            y: t.y + dy,
            ..m.pose
        };
        let translation = unwrapped.camera_from_pattern().translation.vector;
        camera[0].push(translation.x / px);
        camera[1].push(translation.y / px);
        let cov = m.covariance(PERIOD, case.window_px);
        variance[0] += cov[0][0] / (px * px);
        variance[1] += cov[1][1] / (px * px);
        variance[2] += cov[5][5];
        scale.push(m.measured_pixel_size / px);
        variance[3] += (m.pixel_size_std / px).powi(2);
    }
    Measured {
        rms: [0, 1, 2].map(|k| rms(&errors[k])),
        empirical: [
            spread(&camera[0]),
            spread(&camera[1]),
            spread(&errors[2]),
            spread(&scale),
        ],
        predicted: variance.map(|v| (v / renders as f64).sqrt()),
    }
}

/// Runs both checks on `case`. `crlb_limit`: the largest accepted RMS/CRLB per axis (x, y,
/// alpha).
fn check(case: Case, crlb_limit: [f64; 3]) {
    let clean = render(case.layout.as_ref(), &case.truth, &case.options).unwrap();
    let px = case.truth.pixel_size;
    // A noise-free render reports a small but positive uncertainty (the documented floor).
    let mut detector = Detector::new(case.settings.to_config().unwrap()).unwrap();
    let m = &detector.detect(&clean).unwrap()[0];
    let cov = m.covariance(PERIOD, case.window_px);
    assert!(
        m.phase_std.iter().all(|s| s.is_finite() && *s > 0.0),
        "{}: {:?}",
        case.name,
        m.phase_std
    );
    assert!([0, 1, 5].iter().all(|&k| cov[k][k] > 0.0), "{cov:?}");

    let (unit_bound, unit_windowed) = crlb(&case, case.window_corner());
    let mut failures = Vec::new();
    for (noise, seed) in [(0.01, 12), (0.05, 13)] {
        let sigma = noise_sigma(noise);
        let to_px =
            |v: [f64; 4]| [v[0].sqrt() / px, v[1].sqrt() / px, v[2].sqrt()].map(|s| s * sigma);
        let (bound, windowed) = (to_px(unit_bound), to_px(unit_windowed));
        let measured = measure(&case, &clean, noise, RENDERS, seed);
        let ratio = [0, 1, 2].map(|k| measured.rms[k] / bound[k]);
        let ratio_window = [0, 1, 2].map(|k| measured.rms[k] / windowed[k]);
        let honesty = measured.honesty();
        eprintln!(
            "{} noise {noise}: CRLB σ (x, y px, alpha rad) = ({:.2e}, {:.2e}, {:.2e}); RMS error \
             ({:.2e}, {:.2e}, {:.2e}); RMS/CRLB {ratio:.2?} (bound of the analysed window only: \
             {ratio_window:.2?}); predicted/empirical σ of (x, y, yaw, pixel size) \
             {honesty:.2?}",
            case.name,
            bound[0],
            bound[1],
            bound[2],
            measured.rms[0],
            measured.rms[1],
            measured.rms[2],
        );
        for k in 0..3 {
            // An (almost) unbiased estimator cannot beat the bound: checks the bound itself, up
            // to three standard errors of an RMS over the renders (1/√(2N) each).
            if ratio[k] < 1.0 - 3.0 / (2.0 * RENDERS as f64).sqrt() {
                failures.push(format!("noise {noise}: RMS/CRLB {ratio:?} below the bound"));
            }
            if noise == 0.01 && ratio[k] > crlb_limit[k] {
                failures.push(format!(
                    "noise {noise}: RMS/CRLB {ratio:?} above the limit {crlb_limit:?}"
                ));
            }
        }
        if !honesty.iter().all(|h| HONEST.contains(h)) {
            failures.push(format!(
                "noise {noise}: predicted/empirical {honesty:?} outside {HONEST:?}"
            ));
        }
    }
    assert!(failures.is_empty(), "{}: {failures:#?}", case.name);
}

impl Case {
    /// The analysed window as `(first col, first row, side)`.
    fn window_corner(&self) -> (i64, i64, usize) {
        let (cx, cy, side) = self.window;
        let half = (side / 2) as i64;
        (cx - half, cy - half, side)
    }
}

// Every family is measured on its whole dot field (docs/design.md#field-fit): all pixels of the
// periodic grid; every drawn dot of the HP code and the stamp, clear of finders, frames,
// glyphs and missing dots. The field model ties the dots' harmonics to their centres (point-
// symmetric dots), so the harmonics inform the offsets as well as the slopes. What is left
// between the estimator and the bound: the finders', frame's and glyph's own edges, and the
// pixels near them.

/// The target: RMS error within 1.3× the Cramér–Rao bound at 1 % noise.
const TARGET: [f64; 3] = [1.3, 1.3, 1.3];

#[test]
fn periodic_grid_efficiency_and_uncertainty() {
    // Measured RMS/CRLB at 1 %: (0.96, 0.87, 1.19); 800 renders give (0.96–1.02, 0.94–1.01,
    // 1.12–1.17): the position estimate is efficient, the 0.87 a draw of 200 renders.
    check(periodic_case(), TARGET);
}

#[test]
fn periodic_grid_engine_planes_uncertainty() {
    // The default for periodic grids (no whole-image fit): the engine's planes, alpha the
    // bisector of both lattice directions. A regression guard (measured (2.58, 2.48, 3.53);
    // alpha was 5.15 from plane 1 alone), not the target; the uncertainty must be honest all
    // the same.
    let mut case = periodic_case();
    case.settings.field_fit = None;
    check(case, [2.85, 2.75, 4.0]);
}

#[test]
fn hp_code_efficiency_and_uncertainty() {
    // Measured RMS/CRLB at 1 %: (1.28, 1.14, 1.25); (1.83, 1.79, 1.59) with free harmonic
    // phases and the regular dots only, (3.66, 4.11, 8.26) on the window alone.
    check(hpcode_case(), TARGET);
}

#[test]
fn binned_stamp_efficiency_and_uncertainty() {
    // Along the pixel axes, binned through the anti-aliasing filter: measured RMS/CRLB at 1 %
    // (1.76, 1.73, 4.29); a 2 × 2 box average gave (13.1, 27.6, 305) (its folded harmonics
    // coincide with the modelled ones), the field's own pixels unbinned (3.94, 3.35, 14.6).
    // The same stamp turned 0.3 rad gives (1.21, 1.20, 1.30). What is left along the axes is
    // a bias, not noise (at 5 % noise the ratios are 1.1–1.4), and not the filter's stop band
    // (a 90 dB filter: (1.59, 1.65, 3.53)): it goes with the sharpness of the dots, (1.20,
    // 1.22, 1.24) at 0.8 px of blur and (1.17, 1.18, 1.15) at 1 px, as content beyond the
    // sensor's own Nyquist frequency, folded by its pixels, would. A regression guard, not the
    // target; the uncertainty must be honest all the same.
    check(binned_stamp_case(), [2.0, 2.0, 4.7]);
}

#[test]
fn stamp_efficiency_and_uncertainty() {
    // Measured RMS/CRLB at 1 %: (1.03, 1.19, 1.12); (1.68, 1.73, 1.39) with free harmonic
    // phases and the regular dots only, (3.22, 3.03, 5.23) on the window alone.
    check(stamp_case(), TARGET);
}

#[test]
fn uncertainty_is_honest_from_4_to_40_px_periods_and_never_zero() {
    // Periodic grids, 256² images: sharp and blurred dots, 4 to 40 px per period. Clean renders
    // report a positive σ (the noise floor, docs/design.md#uncertainty); at 2 % noise the
    // predicted σ follows the spread (60 renders: ±9 % statistical error on each ratio).
    let mut failures = Vec::new();
    for (period_px, blur) in [
        (4.0, 0.0),
        (4.37, 0.0),
        (6.0, 1.0),
        (12.0, 1.5),
        (40.0, 0.0),
        (40.0, 1.5),
    ] {
        let mut case = periodic_case();
        case.truth.pixel_size = PERIOD / period_px;
        case.options = options(256, blur);
        case.window_px = 256.0;
        let clean = render(case.layout.as_ref(), &case.truth, &case.options).unwrap();
        let mut detector = Detector::new(case.settings.to_config().unwrap()).unwrap();
        let m = &detector.detect(&clean).unwrap()[0];
        let floor = m.phase_std;
        if !floor.iter().all(|s| s.is_finite() && *s > 0.0) {
            failures.push(format!(
                "{period_px} px, blur {blur}: clean phase_std {floor:?}"
            ));
        }
        let honesty = measure(&case, &clean, 0.02, 60, 21).honesty();
        eprintln!(
            "{period_px} px per period, blur {blur}: clean phase_std {:.1e} rad; at 2 % noise \
             predicted/empirical σ of (x, y, yaw, pixel size) {honesty:.2?}",
            floor[0]
        );
        if !honesty.iter().all(|h| HONEST.contains(h)) {
            failures.push(format!("{period_px} px, blur {blur}: {honesty:?}"));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Predicted over empirical position σ of `case` rendered noise-free at 10 % contrast, rounded
/// to 8 bits, at 60 random sub-pixel shifts of its pose.
fn rounding_honesty(case: &Case) -> f64 {
    let mut detector = Detector::new(case.settings.to_config().unwrap()).unwrap();
    let mut opts = case.options.clone();
    (opts.background, opts.foreground) = (0.45, 0.55);
    let mut rng = SmallRng::seed_from_u64(31);
    let (mut errors, mut variance) = (Vec::new(), 0.0);
    let px = case.truth.pixel_size;
    for _ in 0..60 {
        let mut truth = case.truth;
        truth.x += px * rand::Rng::random_range(&mut rng, -0.5..0.5);
        truth.y += px * rand::Rng::random_range(&mut rng, -0.5..0.5);
        let clean = render(case.layout.as_ref(), &truth, &opts).unwrap();
        let rounded: Vec<u8> = clean
            .pixels()
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        let image = GreyImage::from_u8(clean.width(), clean.height(), &rounded).unwrap();
        let found = detector.detect(&image).unwrap();
        assert_eq!(found.len(), 1, "{}: {found:?}", case.name);
        let m = &found[0];
        errors.push((m.pose.x - truth.x) / px);
        errors.push((m.pose.y - truth.y) / px);
        let cov = m.covariance(PERIOD, case.window_px);
        variance += (cov[0][0] + cov[1][1]) / (2.0 * px * px);
    }
    let predicted = (variance / 60.0).sqrt();
    let ratio = predicted / rms(&errors);
    eprintln!(
        "clean 8-bit {} at 10 % contrast: RMS position error {:.2e} px, predicted σ \
         {predicted:.2e} px, ratio {ratio:.2}",
        case.name,
        rms(&errors)
    );
    ratio
}

#[test]
fn uncertainty_counts_the_rounding_of_clean_8_bit_images() {
    // A noise-free HP code and stamp of low contrast (dots 10 % of full scale above the
    // background), rounded to 8 bits: the rounding (1/255, a tenth of the dot contrast per
    // step) is the only noise. Its variance Δ²/12 is a floor of the reported uncertainty
    // (docs/design.md#uncertainty): before it, second differences of the rounded values were
    // mostly exactly 0 and the predicted σ came out ~400 times below the error (stress suite,
    // low contrast). The floor is the rounding's white part: on a smooth image the rounding
    // error also runs in bands along the grey-level contours, correlated over neighbouring
    // pixels, which the fit averages less well, so the spread is up to ~2× the floor (HP 0.53,
    // stamp 1.18 measured here; the HP code's was 0.60 while its harmonics were always tied:
    // the correlated rounding makes some renders keep free phases). 60 renders at random sub-pixel poses: ±9 % statistical error
    // on each ratio. (The stamp's apodised window, which takes the floor from its source, is
    // checked on stress scene 55171: vernier-stress/tests/stress_small.rs.)
    let mut failures = Vec::new();
    for case in [hpcode_case(), stamp_case()] {
        let ratio = rounding_honesty(&case);
        if !(0.4..=*HONEST.end()).contains(&ratio) {
            failures.push(format!("{}: predicted/empirical σ {ratio:.3}", case.name));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Tracking (docs/design.md#tracked-field-fit): a sequence of noisy renders of the HP code
/// moving and turning (up to 4 px and 0.01 rad from its start, 1 % noise, fresh noise each
/// frame), detected frame by frame with `detect_next` (the whole-field fit warm-started from
/// the last frame's) and cold with `detect`. The tracked poses must reach the efficiency
/// target, be at least as precise as the cold ones (RMS error within the sampling spread of
/// two estimators that share their noise), and stay within each frame's predicted σ of the
/// cold fit of the same frame.
#[test]
fn tracked_hp_code_sequence_is_as_precise_as_cold_fits() {
    check_tracked(hpcode_case(), 200, 14);
}

/// [`tracked_hp_code_sequence_is_as_precise_as_cold_fits`] for the turned stamp (stamps are
/// tracked too; a stamp's field is about four times an HP code's, so fewer frames).
#[test]
fn tracked_stamp_sequence_is_as_precise_as_cold_fits() {
    check_tracked(stamp_case(), 60, 15);
}

/// The tracked-sequence checks on `frames` noisy renders of `case` in motion, noise seed
/// `seed`.
fn check_tracked(case: Case, frames: usize, seed: u64) {
    let px = case.truth.pixel_size;
    let base = case.truth.camera_from_pattern().translation.vector / px;
    let (unit_bound, _) = crlb(&case, case.window_corner());
    let sigma = noise_sigma(0.01);
    let bound = [
        unit_bound[0].sqrt() / px * sigma,
        unit_bound[1].sqrt() / px * sigma,
        unit_bound[2].sqrt() * sigma,
    ];
    let config = case.settings.to_config().unwrap();
    let (mut tracked, mut cold) = (
        Detector::new(config.clone()).unwrap(),
        Detector::new(config).unwrap(),
    );
    let mut rng = SmallRng::seed_from_u64(seed);
    let (mut errors, mut cold_errors) = ([vec![], vec![], vec![]], [vec![], vec![], vec![]]);
    let mut worst: f64 = 0.0;
    for k in 0..frames {
        let t = k as f64;
        let origin = Vector2::new(
            base.x + 4.0 * (t / 7.0).sin(),
            base.y + 3.0 * (t / 5.0).cos(),
        );
        let truth =
            Pose::from_origin_in_image(origin, case.truth.alpha + 0.01 * (t / 9.0).sin(), px);
        let clean = render(case.layout.as_ref(), &truth, &case.options).unwrap();
        let image = noisy(&clean, 0.01, &mut rng);
        let a = tracked.detect_next(&image, 0).unwrap();
        let b = cold.detect(&image).unwrap();
        assert!(a.len() == 1 && b.len() == 1, "frame {k}: {a:?} {b:?}");
        let (a, b) = (&a[0], &b[0]);
        for (m, e) in [(a, &mut errors), (b, &mut cold_errors)] {
            e[0].push((m.pose.x - truth.x) / px);
            e[1].push((m.pose.y - truth.y) / px);
            e[2].push(wrap_to_pi(m.pose.alpha - truth.alpha));
        }
        // Camera-frame differences against the tracked pose's own σ.
        let cov = a.covariance(PERIOD, case.window_px);
        let (ta, tb) = (
            a.pose.camera_from_pattern().translation.vector,
            b.pose.camera_from_pattern().translation.vector,
        );
        let off = [
            (ta.x - tb.x) / cov[0][0].sqrt(),
            (ta.y - tb.y) / cov[1][1].sqrt(),
            wrap_to_pi(a.pose.alpha - b.pose.alpha) / cov[5][5].sqrt(),
        ];
        worst = off.iter().fold(worst, |w, v| w.max(v.abs()));
    }
    let counts = tracked.tracking_counts();
    let (rms_tracked, rms_cold) = (
        [0, 1, 2].map(|k| rms(&errors[k])),
        [0, 1, 2].map(|k| rms(&cold_errors[k])),
    );
    let ratio = [0, 1, 2].map(|k| rms_tracked[k] / bound[k]);
    let against_cold = [0, 1, 2].map(|k| rms_tracked[k] / rms_cold[k]);
    eprintln!(
        "tracked {}, {frames} frames ({} tracked): RMS/CRLB (x, y, alpha) {ratio:.2?}, \
         tracked/cold RMS {against_cold:.3?}, largest |tracked − cold| {worst:.2} σ",
        case.name, counts.tracked
    );
    assert!(counts.tracked as usize >= frames - 1, "{counts:?}");
    assert!(
        ratio.iter().zip(TARGET).all(|(r, t)| *r <= t),
        "RMS/CRLB {ratio:?}"
    );
    // Two estimators of the same pixels: their errors differ by far less than the noise, so
    // the ratio of their RMS errors sits close to 1 (a few % here).
    assert!(
        against_cold.iter().all(|r| *r <= 1.05),
        "tracked/cold RMS {against_cold:?}"
    );
    assert!(
        worst <= 1.0,
        "a tracked pose {worst:.2} σ from the cold fit of its frame"
    );
}
