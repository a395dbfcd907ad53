//! Out-of-plane pose of HP codes and stamps (`pose_3d`, docs/design.md#pose-3d-markers): the
//! right mirror solution and the depth under a pinhole camera, one of the two mirror solutions
//! under orthographic optics, and the honesty of the published σ of the angles and the depth
//! over noisy renders. The larger sweep with the Cramér–Rao bound: `cargo bench -p vernier
//! --bench pose_3d`.

mod common;

use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::layout::{BitmapLayout, HpCodeLayout, Layout};
use vernier::marker_tilt::CLEAR_CUE;
use vernier::phase::wrap_to_pi;
use vernier::render::render;
use vernier::{Detector, MarkerPose, Pose};

/// Physical period of the test markers, pattern units.
const PERIOD: f64 = 10.0;
/// Focal length of the pinhole renders, pixels (the marker ~7000 units away).
const FOCAL: f64 = 8000.0;

/// The two marker families measured here.
#[derive(Clone, Copy, Debug)]
enum Family {
    HpCode,
    Stamp,
}

impl Family {
    fn detector(self, focal: Option<f64>) -> Detector {
        let settings = DetectorSettings {
            period: Some(PERIOD),
            pose_3d: true,
            focal_length_px: focal,
            ..match self {
                Family::HpCode => DetectorSettings {
                    pattern_type: MarkerKind::HpCode,
                    code_size: Some(33),
                    ..Default::default()
                },
                Family::Stamp => DetectorSettings {
                    pattern_type: MarkerKind::Stamp,
                    bitmaps: vec![stamp_file()],
                    ..Default::default()
                },
            }
        };
        Detector::new(settings.to_config().unwrap()).unwrap()
    }

    /// A 33-cell HP code carrying ID 361, or the data set's 69 × 69 stamp.
    fn layout(self) -> Box<dyn Layout> {
        match self {
            Family::HpCode => Box::new(
                HpCodeLayout::from_code_size(PERIOD, 33)
                    .unwrap()
                    .with_id(361)
                    .unwrap(),
            ),
            Family::Stamp => Box::new(BitmapLayout::from_image_file(PERIOD, stamp_file()).unwrap()),
        }
    }

    /// View `i` of the marker tilted by `(beta, gamma)`: its origin 10–40 px off the image
    /// centre (off the optical axis), turned by 0.3–2 rad.
    fn view(self, i: usize, beta: f64, gamma: f64) -> (Pose, usize) {
        let (pixel_size, size) = match self {
            Family::HpCode => (0.9, 384),
            Family::Stamp => (1.5, 420),
        };
        let pose = Pose {
            x: (-30.0 + i as f64) * pixel_size,
            y: 20.0 * pixel_size,
            z: 0.0,
            alpha: 0.3 + 0.05 * i as f64,
            beta,
            gamma,
            pixel_size,
        };
        (pose, size)
    }
}

fn stamp_file() -> std::path::PathBuf {
    common::data_dir().join("layouts/stamp69x69.png")
}

/// The one marker found in `image`.
fn only_marker(detector: &mut Detector, image: &vernier::GreyImage, what: &str) -> MarkerPose {
    let found = detector.detect(image).unwrap();
    assert_eq!(found.len(), 1, "{what}: {found:?}");
    found.into_iter().next().unwrap()
}

#[test]
fn perspective_renders_give_the_right_mirror_and_the_depth() {
    // Pinhole renders (focal 8000 px), every tilt of ±0.1..0.3 rad: the cue is clear and
    // picks the right solution, the angles and the depth come back exactly (the perspective
    // solve takes the marker's distance from the optical axis). Measured worst: HP codes
    // 5e-6 rad, depth 1e-7 relative; stamps 3e-4 rad, 4e-5 relative (point-sampled renders).
    for family in [Family::HpCode, Family::Stamp] {
        let mut detector = family.detector(Some(FOCAL));
        let layout = family.layout();
        let (mut worst, mut worst_depth, mut weakest) = (0.0f64, 0.0f64, 1.0f64);
        for (i, (beta, gamma)) in common::tilts().into_iter().enumerate() {
            let (truth, size) = family.view(i, beta, gamma);
            let image = common::render_perspective(layout.as_ref(), &truth, FOCAL, size);
            let m = only_marker(&mut detector, &image, &format!("{family:?} {truth:?}"));
            let cue = m.pose_3d_cue_strength.unwrap_or(0.0);
            let error = (m.pose.beta - beta).abs().max((m.pose.gamma - gamma).abs());
            let depth = (m.pose.z / (truth.pixel_size * FOCAL) - 1.0).abs();
            let cov = m.covariance(PERIOD, m.window_px as f64);
            assert!(cue >= CLEAR_CUE, "{family:?} {truth:?}: cue {cue}");
            assert!(error < 1e-3, "{family:?} {truth:?}: got {:?}", m.pose);
            assert!(
                wrap_to_pi(m.pose.alpha - truth.alpha).abs() < 1e-3,
                "{:?}",
                m.pose
            );
            assert!(depth < 1e-3, "{family:?} {truth:?}: got {:?}", m.pose);
            for k in 2..5 {
                assert!(cov[k][k] > 0.0 && cov[k][k] < 1.0, "{family:?}: {cov:?}");
            }
            worst = worst.max(error);
            worst_depth = worst_depth.max(depth);
            weakest = weakest.min(cue);
        }
        eprintln!(
            "{family:?} perspective renders: worst angle error {worst:.1e} rad, depth \
             {worst_depth:.1e} relative, weakest cue {weakest:.6}"
        );
    }
}

#[test]
fn orthographic_renders_give_one_of_the_mirror_solutions() {
    // Orthographic, area-sampled renders: both mirror solutions explain the image; the nearer
    // one matches the truth, and where the cue calls itself clear it is the right one. The
    // depth is unobserved.
    for family in [Family::HpCode, Family::Stamp] {
        let mut detector = family.detector(None);
        let layout = family.layout();
        let (mut worst, mut clear) = (0.0f64, 0);
        for (i, (beta, gamma)) in common::tilts().into_iter().enumerate().step_by(3) {
            let (truth, size) = family.view(i, beta, gamma);
            let options = common::render_options(size, 0.0, 0);
            let image = render(layout.as_ref(), &truth, &options).unwrap();
            let m = only_marker(&mut detector, &image, &format!("{family:?} {truth:?}"));
            let direct = (m.pose.beta - beta).abs().max((m.pose.gamma - gamma).abs());
            let mirror = (m.pose.beta + beta).abs().max((m.pose.gamma + gamma).abs());
            assert!(
                direct.min(mirror) < 1e-3,
                "{family:?} {truth:?}: {:?}",
                m.pose
            );
            let cue = m.pose_3d_cue_strength.unwrap_or(1.0);
            if cue >= CLEAR_CUE {
                clear += 1;
                assert!(
                    direct < mirror,
                    "{family:?} {truth:?}: clear cue {cue}, mirror"
                );
            }
            assert_eq!(m.pose.z, 0.0);
            assert_eq!(m.covariance(PERIOD, m.window_px as f64)[2][2], 1e6);
            worst = worst.max(direct.min(mirror));
        }
        eprintln!(
            "{family:?} orthographic renders: worst angle error (nearer mirror) {worst:.1e} \
             rad, {clear} of 12 cues clear"
        );
    }
}

/// One noisy view's spread: predicted over observed standard deviation of `(beta, gamma,
/// alpha, depth)`, the mean depth error over the draws and the largest, in units of the
/// depth's σ (depth entries NaN under orthographic optics).
struct NoiseSpread {
    ratios: [f64; 4],
    depth_bias: f64,
    worst_depth: f64,
}

/// [`NoiseSpread`] of `runs` draws of noise `noise` (fraction of full scale, grey levels
/// 0.05/0.95) on one view (β = 0.2, γ = −0.3 rad) through a pinhole (`pinhole`, blurred by
/// 0.7 px as optics do) or orthographic optics (area-sampled, blur 0.5 px).
fn spread_over_noise(family: Family, pinhole: bool, noise: f64, runs: u64) -> NoiseSpread {
    let mut detector = family.detector(pinhole.then_some(FOCAL));
    let (truth, size) = family.view(7, 0.2, -0.3);
    let layout = family.layout();
    let clean = if pinhole {
        let sharp = common::render_perspective(layout.as_ref(), &truth, FOCAL, size);
        common::blurred(&sharp, 0.7)
    } else {
        render(
            layout.as_ref(),
            &truth,
            &common::render_options(size, 0.0, 0),
        )
        .unwrap()
    };
    let clean = common::map_levels(&clean, |v| 0.05 + 0.9 * v);
    let placed = Pose {
        z: truth.pixel_size * FOCAL,
        ..truth
    };
    let true_depth = placed.camera_from_pattern().translation.z;
    let mut spread = common::TiltSpread::default();
    let (mut errors, mut depth_variance, mut worst) = (Vec::new(), 0.0, 0.0f64);
    for seed in 0..runs {
        let image = common::noisy_12_bit(&clean, noise, seed);
        let m = only_marker(&mut detector, &image, &format!("{family:?} draw {seed}"));
        let cov = m.covariance(PERIOD, m.window_px as f64);
        spread.add(&m, truth.beta, &cov);
        let error = m.pose.camera_from_pattern().translation.z - true_depth;
        worst = worst.max(error.abs() / cov[2][2].sqrt());
        errors.push(error);
        depth_variance += cov[2][2];
    }
    let n = errors.len() as f64;
    let mean = errors.iter().sum::<f64>() / n;
    let observed = (errors.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let predicted = (depth_variance / n).sqrt();
    let [b, g, a] = spread.ratios();
    let (depth_ratio, depth_bias, worst_depth) = if pinhole {
        (predicted / observed, mean / predicted, worst)
    } else {
        (f64::NAN, f64::NAN, f64::NAN)
    };
    NoiseSpread {
        ratios: [b, g, a, depth_ratio],
        depth_bias,
        worst_depth,
    }
}

#[test]
fn covariance_matches_the_spread_over_noisy_renders() {
    // One view under 48 draws of noise: each ratio carries a statistical error of
    // 1/√(2·47) = ±10 %. Measured predicted/observed σ of (beta, gamma, alpha, depth):
    // * orthographic, 1 %: HP code (1.24, 0.89, 1.10), stamp (0.98, 0.97, 1.01);
    // * pinhole, 0.5 %: HP code (1.18, 0.92, 1.05, 1.00), every depth within 2.7 σ;
    // * pinhole, 1 %: HP code (1.37, 0.94, 1.04, 1.02), its depth biased by +1.2 σ (largest
    //   3.8 σ); stamps over-predict every σ 1.6× (2.4× at 0.5 %): their fit's residual is
    //   2.6× the noise on pinhole renders, not on orthographic ones.
    // Asserted: honest under orthographic optics (the microscope's), never optimistic under a
    // pinhole, and the depth within 3 of its σ at 0.5 % noise.
    let mut results = Vec::new();
    for family in [Family::HpCode, Family::Stamp] {
        for (pinhole, noise) in [(false, 0.01), (true, 0.005), (true, 0.01)] {
            let spread = spread_over_noise(family, pinhole, noise, 48);
            eprintln!(
                "{family:?}, pinhole {pinhole}, noise {noise}: predicted/observed std of (beta, \
                 gamma, alpha, depth) {:.2?}, mean depth error {:+.2} σ, largest {:.2} σ",
                spread.ratios, spread.depth_bias, spread.worst_depth
            );
            results.push((family, pinhole, noise, spread));
        }
    }
    for (family, pinhole, noise, spread) in results {
        let what = format!(
            "{family:?}, pinhole {pinhole}, noise {noise}: {:?}",
            spread.ratios
        );
        let angles = &spread.ratios[..3];
        if pinhole {
            assert!(spread.ratios.iter().all(|&r| r >= 0.75), "{what}");
        } else {
            assert!(angles.iter().all(|r| (0.75..1.33).contains(r)), "{what}");
        }
        if pinhole && noise <= 0.005 {
            assert!(
                spread.worst_depth < 3.0,
                "{what}: depth {} σ",
                spread.worst_depth
            );
        }
    }
}
