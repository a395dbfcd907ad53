//! Out-of-plane precision against the Cramér–Rao bound:
//!
//! ```sh
//! cargo bench -p vernier --bench pose_3d [-- --draws N]
//! ```
//!
//! For a periodic grid (field fit on), an HP code and a stamp, orthographic views (the
//! microscope's optics: area-sampled renders, blur 0.5 px, grey levels 0.05/0.95, 1 % noise,
//! 12-bit) at eight tilts `(±0.1 | ±0.3, ±0.1 | ±0.3)` rad and `N` noise draws each (default
//! 24), prints per view:
//!
//! * the RMS error of `beta` and `gamma` (the nearer of the two mirror solutions, which no
//!   orthographic image tells apart) over the draws;
//! * the Cramér–Rao bound of each: `√(F⁻¹)` with `F = JᵀJ/σ²` over the pose's unknowns
//!   `(x, y, alpha, pixel size, beta, gamma)`, `J` the clean render's derivatives (central
//!   differences of the exact area coverage) and `σ` the noise; the dot shape, grey levels and
//!   blur are taken as known, so the figure bounds every unbiased estimator;
//! * RMS error over the bound, and the published σ over the observed spread.
//!
//! Then the same under a pinhole camera (focal 8000 px, point-sampled renders blurred 0.7 px,
//! `--focal-length-px`): the right mirror's rate and the depth's error in its own σ.
//! Not run in CI (minutes); `vernier/tests/marker_pose_3d.rs` and `periodic_pose_3d.rs` hold
//! the fixed-seed checks.

#[path = "../tests/common/mod.rs"]
mod common;

use nalgebra::{DMatrix, SMatrix};
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::layout::{BitmapLayout, HpCodeLayout, Layout, PeriodicLayout};
use vernier::render::{render, RenderOptions};
use vernier::{Detector, GreyImage, Pose};

/// Physical period of every marker, pattern units.
const PERIOD: f64 = 10.0;
/// Noise of the views, fraction of full scale.
const NOISE: f64 = 0.01;
/// Focal length of the pinhole views, pixels.
const FOCAL: f64 = 8000.0;

/// One marker family's set-up.
struct Case {
    name: &'static str,
    layout: Box<dyn Layout>,
    settings: DetectorSettings,
    pixel_size: f64,
    size: usize,
}

fn cases() -> Vec<Case> {
    let base = DetectorSettings {
        period: Some(PERIOD),
        pose_3d: true,
        ..Default::default()
    };
    let stamp = common::data_dir().join("layouts/stamp69x69.png");
    vec![
        Case {
            name: "periodic",
            layout: Box::new(PeriodicLayout::new(PERIOD, 101, 101).expect("layout")),
            settings: DetectorSettings {
                pattern_type: MarkerKind::Periodic,
                field_fit: Some(true),
                ..base.clone()
            },
            pixel_size: 1.1,
            size: 256,
        },
        Case {
            name: "HP code",
            layout: Box::new(
                HpCodeLayout::from_code_size(PERIOD, 33)
                    .and_then(|l| l.with_id(361))
                    .expect("layout"),
            ),
            settings: DetectorSettings {
                pattern_type: MarkerKind::HpCode,
                code_size: Some(33),
                ..base.clone()
            },
            pixel_size: 0.9,
            size: 384,
        },
        Case {
            name: "stamp",
            layout: Box::new(BitmapLayout::from_image_file(PERIOD, &stamp).expect("stamp")),
            settings: DetectorSettings {
                pattern_type: MarkerKind::Stamp,
                bitmaps: vec![stamp],
                ..base
            },
            pixel_size: 1.5,
            size: 420,
        },
    ]
}

/// The clean orthographic render of `layout` at `pose` (grey levels 0.05/0.95, blur 0.5 px).
fn clean(layout: &dyn Layout, pose: &Pose, size: usize) -> GreyImage {
    let mut options = RenderOptions::new(size, size);
    options.blur_sigma = 0.5;
    options.background = 0.05;
    options.foreground = 0.95;
    render(layout, pose, &options).expect("render")
}

/// Cramér–Rao bound of `(beta, gamma)`, radians, of an orthographic view of `layout` at `pose`
/// under white noise `noise`: `F = JᵀJ/σ²` over `(x, y, alpha, pixel size, beta, gamma)`.
fn bound(layout: &dyn Layout, pose: &Pose, size: usize, noise: f64) -> [f64; 2] {
    // Steps moving the marker's edge by ~0.01 px.
    let steps = [
        0.01 * pose.pixel_size,
        0.01 * pose.pixel_size,
        1e-4,
        1e-4 * pose.pixel_size,
        1e-3,
        1e-3,
    ];
    let moved = |k: usize, h: f64| {
        let mut p = *pose;
        match k {
            0 => p.x += h,
            1 => p.y += h,
            2 => p.alpha += h,
            3 => p.pixel_size += h,
            4 => p.beta += h,
            _ => p.gamma += h,
        }
        clean(layout, &p, size)
    };
    let columns: Vec<Vec<f64>> = (0..6)
        .map(|k| {
            let (plus, minus) = (moved(k, steps[k]), moved(k, -steps[k]));
            plus.pixels()
                .iter()
                .zip(minus.pixels())
                .map(|(a, b)| (*a as f64 - *b as f64) / (2.0 * steps[k]))
                .collect()
        })
        .collect();
    let mut fisher = SMatrix::<f64, 6, 6>::zeros();
    for i in 0..6 {
        for j in i..6 {
            let dot: f64 = columns[i].iter().zip(&columns[j]).map(|(a, b)| a * b).sum();
            fisher[(i, j)] = dot / (noise * noise);
            fisher[(j, i)] = fisher[(i, j)];
        }
    }
    let inverse = DMatrix::from_iterator(6, 6, fisher.iter().copied())
        .try_inverse()
        .expect("the Fisher information is singular");
    [inverse[(4, 4)].sqrt(), inverse[(5, 5)].sqrt()]
}

/// The eight tilts of the sweep.
fn tilts() -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for b in [-0.3, -0.1, 0.1, 0.3] {
        for g in [-0.3, 0.1] {
            out.push((b, g));
        }
    }
    out
}

/// The view of `case` tilted by `(beta, gamma)`, the `i`-th of the sweep.
fn view(case: &Case, i: usize, beta: f64, gamma: f64) -> Pose {
    let offset = if case.name == "periodic" { 0.0 } else { 20.0 };
    Pose {
        x: (0.2 * i as f64 - offset) * case.pixel_size,
        y: 0.5 * offset * case.pixel_size,
        z: 0.0,
        alpha: 0.2 + 0.04 * i as f64,
        beta,
        gamma,
        pixel_size: case.pixel_size,
    }
}

fn main() {
    let draws: u64 = std::env::args()
        .skip_while(|a| a != "--draws")
        .nth(1)
        .and_then(|v| v.parse().ok())
        .unwrap_or(24);
    println!("orthographic views, {NOISE} noise, {draws} draws per view");
    println!(
        "{:<9} {:>6} {:>6} {:>10} {:>10} {:>10} {:>10} {:>7} {:>7} {:>7} {:>7}",
        "marker",
        "beta",
        "gamma",
        "rms beta",
        "crb beta",
        "rms gamma",
        "crb gamma",
        "β/crb",
        "γ/crb",
        "σβ pred",
        "σγ pred"
    );
    for case in cases() {
        orthographic_rows(&case, draws);
    }
    println!();
    println!("pinhole views (focal {FOCAL} px), {NOISE} noise, {draws} draws per view");
    println!(
        "{:<9} {:>6} {:>6} {:>12} {:>12} {:>12}",
        "marker", "beta", "gamma", "right mirror", "depth bias σ", "depth worst σ"
    );
    for case in cases().into_iter().filter(|c| c.name != "periodic") {
        pinhole_rows(&case, draws);
    }
}

/// The orthographic sweep's rows of one marker family.
fn orthographic_rows(case: &Case, draws: u64) {
    let mut detector =
        Detector::new(case.settings.to_config().expect("settings")).expect("detector");
    let (mut worst_beta, mut worst_gamma) = (0.0f64, 0.0f64);
    for (i, (beta, gamma)) in tilts().into_iter().enumerate() {
        let truth = view(case, i, beta, gamma);
        let image = clean(case.layout.as_ref(), &truth, case.size);
        let crb = bound(case.layout.as_ref(), &truth, case.size, NOISE);
        let mut spread = common::TiltSpread::default();
        let (mut sum_b, mut sum_g, mut found) = (0.0, 0.0, 0);
        for seed in 0..draws {
            let noisy = common::noisy_12_bit(&image, NOISE, 1000 * i as u64 + seed);
            let Ok(markers) = detector.detect(&noisy) else {
                continue;
            };
            let Some(m) = markers.first() else {
                continue;
            };
            // The nearer mirror solution.
            let sign = if (m.pose.beta - beta).abs() <= (m.pose.beta + beta).abs() {
                1.0
            } else {
                -1.0
            };
            sum_b += (sign * m.pose.beta - beta).powi(2);
            sum_g += (sign * m.pose.gamma - gamma).powi(2);
            found += 1;
            spread.add(m, beta, &m.covariance(PERIOD, m.window_px as f64));
        }
        if found < 2 {
            println!(
                "{:<9} {beta:>6} {gamma:>6}   found in {found} of {draws} draws",
                case.name
            );
            continue;
        }
        let (rms_b, rms_g) = ((sum_b / found as f64).sqrt(), (sum_g / found as f64).sqrt());
        let ratios = spread.ratios();
        worst_beta = worst_beta.max(rms_b / crb[0]);
        worst_gamma = worst_gamma.max(rms_g / crb[1]);
        println!(
            "{:<9} {beta:>6} {gamma:>6} {rms_b:>10.2e} {:>10.2e} {rms_g:>10.2e} {:>10.2e} {:>7.2} \
             {:>7.2} {:>7.2} {:>7.2}",
            case.name,
            crb[0],
            crb[1],
            rms_b / crb[0],
            rms_g / crb[1],
            ratios[0],
            ratios[1]
        );
    }
    println!(
        "{:<9} worst RMS/bound: beta {worst_beta:.2}, gamma {worst_gamma:.2}",
        case.name
    );
}

/// The pinhole sweep's rows of one marker family (HP codes and stamps: their markers sit off
/// the optical axis).
fn pinhole_rows(case: &Case, draws: u64) {
    let settings = DetectorSettings {
        focal_length_px: Some(FOCAL),
        ..case.settings.clone()
    };
    let mut detector = Detector::new(settings.to_config().expect("settings")).expect("detector");
    for (i, (beta, gamma)) in tilts().into_iter().enumerate() {
        let truth = view(case, i, beta, gamma);
        let sharp = common::render_perspective(case.layout.as_ref(), &truth, FOCAL, case.size);
        let image = common::map_levels(&common::blurred(&sharp, 0.7), |v| 0.05 + 0.9 * v);
        let true_depth = Pose {
            z: truth.pixel_size * FOCAL,
            ..truth
        }
        .camera_from_pattern()
        .translation
        .z;
        let (mut right, mut found, mut sum, mut worst) = (0, 0, 0.0, 0.0f64);
        for seed in 0..draws {
            let noisy = common::noisy_12_bit(&image, NOISE, 1000 * i as u64 + seed);
            let Some(m) = detector
                .detect(&noisy)
                .ok()
                .and_then(|v| v.into_iter().next())
            else {
                continue;
            };
            found += 1;
            right += usize::from((m.pose.beta - beta).abs() < (m.pose.beta + beta).abs());
            let sigma = m.covariance(PERIOD, m.window_px as f64)[2][2].sqrt();
            let error = (m.pose.camera_from_pattern().translation.z - true_depth) / sigma;
            sum += error;
            worst = worst.max(error.abs());
        }
        println!(
            "{:<9} {beta:>6} {gamma:>6} {:>12} {:>12.2} {worst:>12.2}",
            case.name,
            format!("{right}/{found}"),
            sum / found.max(1) as f64
        );
    }
}
