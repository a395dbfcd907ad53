//! HP code detection (issue 3 acceptance): synthetic scenes with 1–6 markers at random poses,
//! IDs and scales; the original's real images (Image96–105, HPCodeImage_20um) against its
//! reference results; exact image rotations and flips; the unified detector and duplicates.

mod common;

use nalgebra::{Matrix2, Vector2};
use rand::{rngs::SmallRng, Rng, SeedableRng};
use std::f64::consts::{FRAC_PI_2, PI};
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::hpcode::{HpCodeDetector, HpCodeMarker, HpCodeParams};
use vernier::layout::{HpCodeLayout, Layout};
use vernier::phase::wrap_to_pi;
use vernier::render::{render_scene, RenderOptions};
use vernier::{Detector, GreyImage, MarkerPose, Polarity, Pose};

/// Physical period of every synthetic marker, µm.
const PERIOD: f64 = 10.0;

struct Truth {
    id: u64,
    pose: Pose,
    origin_px: Vector2<f64>,
}

/// `count` markers `code_size` cells wide at random poses, IDs and scales (period 7–11 px),
/// placed so that no marker enters another's analysis window.
fn random_scene(
    rng: &mut SmallRng,
    count: usize,
    code_size: usize,
    size: (usize, usize),
) -> (GreyImage, Vec<Truth>) {
    let bits = (code_size - 15) / 2;
    let center = Vector2::new((size.0 / 2) as f64, (size.1 / 2) as f64);
    let mut placed: Vec<(Truth, f64)> = Vec::new();
    let mut attempts = 0;
    while placed.len() < count {
        attempts += 1;
        assert!(attempts < 100_000, "cannot place {count} markers");
        let period_px: f64 = rng.random_range(7.0..11.0);
        let width_px = code_size as f64 * period_px / 2.0;
        let half_diag = width_px / std::f64::consts::SQRT_2 + 6.0;
        let pos = Vector2::new(
            rng.random_range(half_diag..size.0 as f64 - half_diag),
            rng.random_range(half_diag..size.1 as f64 - half_diag),
        );
        if placed
            .iter()
            .any(|(t, r)| (t.origin_px - pos).norm() < r + half_diag)
        {
            continue;
        }
        let pose =
            Pose::from_origin_in_image(pos - center, rng.random_range(-PI..PI), PERIOD / period_px);
        let truth = Truth {
            id: rng.random_range(0..1u64 << bits),
            pose,
            origin_px: pos,
        };
        placed.push((truth, half_diag));
    }
    let layouts: Vec<HpCodeLayout> = placed
        .iter()
        .map(|(t, _)| {
            HpCodeLayout::from_code_size(PERIOD, code_size)
                .unwrap()
                .with_id(t.id)
                .unwrap()
        })
        .collect();
    let items: Vec<(&dyn Layout, Pose)> = layouts
        .iter()
        .zip(&placed)
        .map(|(l, (t, _))| (l as &dyn Layout, t.pose))
        .collect();
    let mut opts = RenderOptions::new(size.0, size.1);
    opts.blur_sigma = 0.5;
    let image = render_scene(&items, &opts).unwrap();
    (image, placed.into_iter().map(|(t, _)| t).collect())
}

#[test]
fn synthetic_scenes_every_marker_found_with_its_id_and_pose() {
    let mut rng = SmallRng::seed_from_u64(3);
    let (mut worst_px, mut worst_rad, mut markers) = (0.0f64, 0.0f64, 0);
    let mut worst_scale = 0.0f64;
    for count in 1..=6 {
        let code_size = if count % 2 == 0 { 33 } else { 37 };
        let size = match count {
            1 | 2 => (640, 512),
            3 | 4 => (1024, 768),
            _ => (1280, 1024),
        };
        let (image, truths) = random_scene(&mut rng, count, code_size, size);
        let mut detector = HpCodeDetector::new(HpCodeParams::new(PERIOD, code_size)).unwrap();
        let found = detector.detect(&image).unwrap();
        assert_eq!(found.len(), truths.len(), "scene of {count}: {found:#?}");
        for t in &truths {
            let m = found
                .iter()
                .find(|m| (m.origin_px - t.origin_px).norm() < 2.0)
                .unwrap_or_else(|| panic!("scene of {count}: marker {} missing", t.id));
            assert_eq!(m.id, t.id, "scene of {count}");
            assert_eq!(m.code_size, code_size);
            assert_eq!(m.polarity, Polarity::BrightDots);
            assert!(!m.mirrored);
            assert!(m.id_confidence > 0.5, "{}", m.id_confidence);
            let err_px = (m.origin_px - t.origin_px).norm();
            let err_rad = wrap_to_pi(m.pose.alpha - t.pose.alpha).abs();
            // The pose itself (pattern units) agrees as well as the pixel position.
            let err_pose =
                Vector2::new(m.pose.x - t.pose.x, m.pose.y - t.pose.y).norm() / t.pose.pixel_size;
            worst_scale = worst_scale.max((m.pose.pixel_size / t.pose.pixel_size - 1.0).abs());
            assert!(
                (m.pose.pixel_size / t.pose.pixel_size - 1.0).abs() < 1e-5,
                "pixel size {} vs {}",
                m.pose.pixel_size,
                t.pose.pixel_size
            );
            worst_px = worst_px.max(err_px).max(err_pose);
            worst_rad = worst_rad.max(err_rad);
            markers += 1;
        }
    }
    println!(
        "{markers} markers: worst {worst_px:.2e} px, {worst_rad:.2e} rad, pixel size {worst_scale:.1e} (relative)"
    );
    assert!(worst_px < 2e-3, "position error {worst_px:.2e} px");
    // Noise-free renders of dots sharper than the pixel grid (0.5 px blur at 7–11 px
    // periods): harmonics beyond the fifth alias, and the whole-field fit, which models the
    // harmonics instead of windowing them away, keeps a bias of up to ~1.3e-5 rad there
    // (2e-8 rad at 1 px blur; docs/design.md#field-fit). Under 1 % noise it is 5× more
    // precise than the window (tests/efficiency.rs).
    assert!(worst_rad < 2e-5, "angle error {worst_rad:.2e} rad");
}

#[test]
fn thread_count_never_changes_the_result() {
    // Five markers measured on 1, 2 and 3 threads (each thread takes the next triple) give the
    // sequential result exactly.
    let mut rng = SmallRng::seed_from_u64(77);
    let (image, truth) = random_scene(&mut rng, 5, 33, (900, 700));
    let detect = |threads: usize| {
        let mut params = HpCodeParams::new(PERIOD, 33);
        params.threads = threads;
        HpCodeDetector::new(params).unwrap().detect(&image).unwrap()
    };
    let sequential = detect(1);
    assert_eq!(sequential.len(), truth.len());
    // Every field, floats bit for bit (Debug prints them exactly).
    let text = |m: &[HpCodeMarker]| format!("{m:?}");
    for threads in [2, 3, 0] {
        assert_eq!(
            text(&detect(threads)),
            text(&sequential),
            "{threads} threads"
        );
    }
}

#[test]
fn duplicate_ids_are_all_reported_and_flagged() {
    let layout = HpCodeLayout::from_code_size(PERIOD, 33)
        .unwrap()
        .with_id(5)
        .unwrap();
    let poses = [
        Pose::from_origin_in_image(Vector2::new(-160.0, 10.0), 0.3, 1.1),
        Pose::from_origin_in_image(Vector2::new(170.0, -20.0), -2.0, 1.2),
    ];
    let items: Vec<(&dyn Layout, Pose)> =
        poses.iter().map(|p| (&layout as &dyn Layout, *p)).collect();
    let mut opts = RenderOptions::new(720, 400);
    opts.blur_sigma = 0.5;
    let image = render_scene(&items, &opts).unwrap();
    let settings = DetectorSettings {
        pattern_type: MarkerKind::HpCode,
        period: Some(PERIOD),
        code_size: Some(33),
        ..Default::default()
    };
    let mut detector = Detector::new(settings.to_config().unwrap()).unwrap();
    let found = detector.detect(&image).unwrap();
    assert_eq!(found.len(), 2);
    assert!(found.iter().all(|m| m.id == 5 && m.duplicate_id));
    assert!(found.iter().all(|m| m.decode_confidence.unwrap() > 0.5));
}

#[test]
fn settings_and_errors() {
    // Code size from an HPCodePattern file; missing code size is a clear error.
    let dir = std::env::temp_dir().join(format!("vernier-hpcode-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("hp.json");
    std::fs::write(
        &file,
        r#"{"HPCodePattern": {"period": 15.5, "size": 19, "unit": "um"}}"#,
    )
    .unwrap();
    let from_file = DetectorSettings {
        pattern_file: Some(file),
        ..Default::default()
    };
    match from_file.to_config().unwrap() {
        vernier::DetectorConfig::HpCode(p) => {
            assert_eq!((p.period, p.code_size), (15.5, 37));
        }
        other => panic!("{other:?}"),
    }
    let missing = DetectorSettings {
        pattern_type: MarkerKind::HpCode,
        period: Some(15.5),
        ..Default::default()
    };
    let e = missing.to_config().unwrap_err().to_string();
    assert!(e.contains("code_size"), "{e}");
    for (w, window) in [(35, None), (33, Some(101)), (33, Some(8))] {
        let mut p = HpCodeParams::new(15.5, w);
        p.window_size = window;
        assert!(HpCodeDetector::new(p).is_err());
    }
    // Blank and tiny images: no marker, no error.
    let mut d = HpCodeDetector::new(HpCodeParams::new(15.5, 33)).unwrap();
    let blank = GreyImage::new(300, 200, vec![0.5; 300 * 200]).unwrap();
    assert!(d.detect(&blank).unwrap().is_empty());
    let tiny = GreyImage::new(3, 2, vec![0.0; 6]).unwrap();
    assert!(d.detect(&tiny).unwrap().is_empty());
}

/// One row of `Image96-105_reference.csv`: (x, y, alpha, pixelSize) of markers 0 and 1.
fn reference_rows() -> Vec<(u32, [[f64; 4]; 2])> {
    let path = common::data_dir().join("hpcode/Image96-105_reference.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|line| {
            let f: Vec<&str> = line.split(';').collect();
            let num = |i: usize| f[i].parse::<f64>().unwrap();
            (
                f[0].parse().unwrap(),
                [
                    [num(2), num(3), num(4), num(5)],
                    [num(7), num(8), num(9), num(10)],
                ],
            )
        })
        .collect()
}

fn open_hp(name: &str) -> GreyImage {
    GreyImage::open(common::data_dir().join("hpcode").join(name)).unwrap()
}

fn by_id(markers: &[HpCodeMarker], id: u64) -> &HpCodeMarker {
    let matching: Vec<_> = markers.iter().filter(|m| m.id == id).collect();
    assert_eq!(matching.len(), 1, "id {id}: {markers:#?}");
    matching[0]
}

#[test]
fn real_images_96_to_105_match_the_original() {
    let rows = reference_rows();
    assert_eq!(rows.len(), 10);
    // The original's method (band-pass planes, Hann window of 512 px on the truncated centre):
    // reproduces its numbers. The default method refines the planes and keeps the window
    // inside the marker: a different (more stable) estimate, see the report below.
    let mut original = HpCodeDetector::new(HpCodeParams::original(15.5, 33, 512)).unwrap();
    let mut default = HpCodeDetector::new(HpCodeParams::new(15.5, 33)).unwrap();
    let (mut worst_xy, mut worst_alpha, mut worst_ps) = (0.0f64, 0.0f64, 0.0f64);
    let (mut dev_xy, mut dev_alpha, mut dev_ps) = (0.0f64, 0.0f64, 0.0f64);
    for (number, reference) in rows {
        let image = open_hp(&format!("Image{number}.png"));
        let found = original.detect(&image).unwrap();
        assert_eq!(found.len(), 2, "Image{number}");
        let refined = default.detect(&image).unwrap();
        assert_eq!(refined.len(), 2, "Image{number}");
        for (id, r) in reference.iter().enumerate() {
            let m = by_id(&found, id as u64);
            assert_eq!(m.code_size, 33);
            let p = m.pose;
            worst_xy = worst_xy.max((p.x - r[0]).abs()).max((p.y - r[1]).abs());
            worst_alpha = worst_alpha.max((p.alpha - r[2]).abs());
            worst_ps = worst_ps.max((p.pixel_size - r[3]).abs());
            let q = by_id(&refined, id as u64).pose;
            dev_xy = dev_xy.max((q.x - r[0]).abs()).max((q.y - r[1]).abs());
            dev_alpha = dev_alpha.max((q.alpha - r[2]).abs());
            dev_ps = dev_ps.max((q.pixel_size - r[3]).abs());
        }
    }
    println!(
        "original method vs reference: {worst_xy:.4} µm, {worst_alpha:.2e} rad, pixel size {worst_ps:.1e}"
    );
    println!(
        "default method vs reference: {dev_xy:.3} µm, {dev_alpha:.2e} rad, pixel size {dev_ps:.1e}"
    );
    // The reference is printed with 6 significant digits (±5e-6 rad, ±5e-6 px size).
    assert!(worst_xy < 0.01, "{worst_xy} µm");
    assert!(worst_alpha < 2e-5, "{worst_alpha} rad");
    assert!(worst_ps < 1e-4, "{worst_ps}");
    // Refined planes differ from the original's band-pass planes on these real images by up to
    // ~1 µm and ~1.5e-3 rad (the original's own result moves that much with its window size).
    assert!(dev_xy < 1.5 && dev_alpha < 2.5e-3 && dev_ps < 2e-3);
}

/// Largest difference between two marker lists matched by ID, in image position (px) and yaw
/// (rad), and in units of the first list's predicted σ (camera-frame x, y and yaw of
/// [`MarkerPose::covariance`]) for markers of physical period `period`.
fn worst_difference(a: &[MarkerPose], b: &[MarkerPose], period: f64) -> (f64, f64, f64) {
    assert_eq!(a.len(), b.len(), "{a:#?}\n{b:#?}");
    let (mut px, mut rad, mut sigmas) = (0.0f64, 0.0f64, 0.0f64);
    for m in a {
        let n = b.iter().find(|n| n.id == m.id).expect("same IDs");
        px = px.max((m.origin_px - n.origin_px).norm());
        let yaw = wrap_to_pi(m.pose.alpha - n.pose.alpha);
        rad = rad.max(yaw.abs());
        let cov = m.covariance(period, m.window_px as f64);
        let (tm, tn) = (
            m.pose.camera_from_pattern().translation.vector,
            n.pose.camera_from_pattern().translation.vector,
        );
        for (d, v) in [
            (tm.x - tn.x, cov[0][0]),
            (tm.y - tn.y, cov[1][1]),
            (yaw, cov[5][5]),
        ] {
            sigmas = sigmas.max(d.abs() / v.sqrt());
        }
    }
    (px, rad, sigmas)
}

/// The generic detector for W 33 HP codes of physical period `period`.
fn hp_detector(period: f64) -> Detector {
    let settings = DetectorSettings {
        pattern_type: MarkerKind::HpCode,
        period: Some(period),
        code_size: Some(33),
        ..Default::default()
    };
    Detector::new(settings.to_config().unwrap()).unwrap()
}

#[test]
fn tracking_gives_the_full_detection_on_a_moving_sequence() {
    // Two markers drifting 0.9 px and 2e-3 rad per frame (one of them accelerating), 24
    // frames, full search every 10 frames: every frame gives the full detection's markers,
    // their poses within a small fraction of their σ of it (the tracked whole-field fit starts
    // from the last frame's model and converges to the same solution,
    // docs/design.md#tracked-field-fit).
    let layouts = [17u64, 200].map(|id| {
        HpCodeLayout::from_code_size(PERIOD, 33)
            .unwrap()
            .with_id(id)
            .unwrap()
    });
    let mut opts = RenderOptions::new(640, 400);
    opts.blur_sigma = 0.6;
    opts.noise_std = 0.01;
    let (mut tracker, mut full) = (hp_detector(PERIOD), hp_detector(PERIOD));
    let (mut worst_px, mut worst_rad, mut worst_sigma) = (0.0f64, 0.0f64, 0.0f64);
    for frame in 0..24 {
        let t = frame as f64;
        let poses = [
            Pose::from_origin_in_image(Vector2::new(-150.0 + 0.9 * t, 5.0), 0.4 + 2e-3 * t, 1.1),
            Pose::from_origin_in_image(
                Vector2::new(140.0, -10.0 + 0.02 * t * t),
                -1.9 - 2e-3 * t,
                1.1,
            ),
        ];
        let items: Vec<(&dyn Layout, Pose)> = layouts
            .iter()
            .zip(&poses)
            .map(|(l, p)| (l as &dyn Layout, *p))
            .collect();
        opts.seed = frame;
        let image = render_scene(&items, &opts).unwrap();
        let tracked = tracker.detect_next(&image, 10).unwrap();
        let expected = full.detect(&image).unwrap();
        assert_eq!(expected.len(), 2, "frame {frame}");
        let (px, rad, sigma) = worst_difference(&tracked, &expected, PERIOD);
        worst_px = worst_px.max(px);
        worst_rad = worst_rad.max(rad);
        worst_sigma = worst_sigma.max(sigma);
    }
    let counts = tracker.tracking_counts();
    println!(
        "tracked {} frames, full {}: worst {worst_px:.1e} px, {worst_rad:.1e} rad, \
         {worst_sigma:.2} σ",
        counts.tracked, counts.full
    );
    assert_eq!((counts.tracked, counts.full), (21, 3));
    assert!(
        worst_sigma < 0.25,
        "{worst_px} px, {worst_rad} rad, {worst_sigma} σ"
    );
}

/// Robust standard deviation of a series' noise from its second differences (1.4826 × their
/// median absolute deviation, over √6: the second difference of white noise has variance 6σ²).
/// Smooth motion cancels in them.
fn second_difference_noise(series: &[f64]) -> f64 {
    let d2: Vec<f64> = series
        .windows(3)
        .map(|w| w[2] - 2.0 * w[1] + w[0])
        .collect();
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let centre = median(d2.clone());
    1.4826 * median(d2.iter().map(|d| (d - centre).abs()).collect()) / 6f64.sqrt()
}

#[test]
fn tracking_on_the_real_sequence_is_as_precise_as_full_detection() {
    // Image96–125 (30 frames, no ground truth). The tracked whole-field fit starts from the
    // last frame's model (docs/design.md#tracked-field-fit); on real dots, whose model error
    // makes the robust weights depend on the residuals they were judged on, it settles within
    // ~1e-5 rad and a few 1e-3 px of the cold fit (as far as the cold fit moves when its
    // weights are judged one sweep later). It must be at least as precise: the
    // second-difference noise of every marker's x, y and alpha no larger than the full
    // detection's, up to two standard errors of such an estimate over 28 differences.
    let (mut tracker, mut full) = (hp_detector(15.5), hp_detector(15.5));
    let (mut tracked_series, mut full_series) = (vec![vec![]; 6], vec![vec![]; 6]);
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    for number in 96..=125 {
        let image = open_hp(&format!("Image{number}.png"));
        let tracked = tracker.detect_next(&image, 0).unwrap();
        let expected = full.detect(&image).unwrap();
        assert_eq!(expected.len(), 2, "Image{number}");
        let (px, rad, sigma) = worst_difference(&tracked, &expected, 15.5);
        worst = (worst.0.max(px), worst.1.max(rad), worst.2.max(sigma));
        for (list, series) in [
            (&tracked, &mut tracked_series),
            (&expected, &mut full_series),
        ] {
            for id in [0, 1] {
                let m = list.iter().find(|m| m.id == id).expect("markers 0 and 1");
                let k = 3 * id as usize;
                series[k].push(m.origin_px.x);
                series[k + 1].push(m.origin_px.y);
                series[k + 2].push(m.pose.alpha);
            }
        }
    }
    let counts = tracker.tracking_counts();
    let noise = |s: &Vec<Vec<f64>>| {
        s.iter()
            .map(|v| second_difference_noise(v))
            .collect::<Vec<_>>()
    };
    let (tracked_noise, full_noise) = (noise(&tracked_series), noise(&full_series));
    let show = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:.2e}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "real sequence: tracked {} of 30 frames, worst difference from full detection \
         {:.1e} px, {:.1e} rad ({:.1} white-noise σ); second-difference noise (x px, y px, \
         alpha rad) of markers 0, 1: tracked [{}], full [{}]",
        counts.tracked,
        worst.0,
        worst.1,
        worst.2,
        show(&tracked_noise),
        show(&full_noise)
    );
    assert_eq!(counts.tracked, 29);
    let tolerance = 1.0 + 2.0 / (2.0 * 28.0f64).sqrt();
    for (k, (t, f)) in tracked_noise.iter().zip(&full_noise).enumerate() {
        assert!(
            t <= &(f * tolerance),
            "series {k}: tracked {t:.2e} against full {f:.2e}"
        );
    }
}

#[test]
fn dark_dot_image_polarity_from_the_finders() {
    let image = open_hp("HPCodeImage_20um.png");
    let mut auto = HpCodeDetector::new(HpCodeParams::new(20.0, 33)).unwrap();
    let found = auto.detect(&image).unwrap();
    assert_eq!(found.len(), 2, "{found:#?}");
    for id in [0, 1] {
        let m = by_id(&found, id);
        assert_eq!(m.polarity, Polarity::DarkDots);
        // Documented as W = 33, these markers are 39 cells wide (20 dots, finders 16 periods
        // apart); their centre is then the gap between four dots.
        assert_eq!(m.code_size, 39);
        assert!(!m.mirrored);
    }
    // The polarity setting filters; the bright setting finds nothing here.
    let mut p = HpCodeParams::new(20.0, 33);
    p.polarity = Some(Polarity::DarkDots);
    let dark = HpCodeDetector::new(p.clone())
        .unwrap()
        .detect(&image)
        .unwrap();
    for (a, b) in dark.iter().zip(&found) {
        assert_eq!((a.id, a.pose), (b.id, b.pose));
    }
    p.polarity = Some(Polarity::BrightDots);
    assert!(HpCodeDetector::new(p)
        .unwrap()
        .detect(&image)
        .unwrap()
        .is_empty());
    // The original (S = 256, dark dots not inverted: its phase origin is the bright gap, here
    // the true marker centre): id 1 = (106.313, 325.622, 1.57991, 2.39519). For id 0 its peak
    // search took the mirror of a lobe lying on the ky = 0 row (docs/design.md#phase-lobes), so its
    // "plane 1" is the other axis; with that axis we get its numbers too (checked by hand:
    // 325.317, 131.723, 0.00968, 2.40948).
    let mut original = HpCodeDetector::new(HpCodeParams::original(20.0, 33, 256)).unwrap();
    let found = original.detect(&image).unwrap();
    let p = by_id(&found, 1).pose;
    assert!(
        (p.x - 106.313).abs() < 0.01 && (p.y - 325.622).abs() < 0.01,
        "{p:?}"
    );
    // The window's integer centre comes from our finder centres, which may differ by a pixel
    // from the original's Canny-based ones; a 1-px move of this 256-px window turns the
    // band-pass planes by ~2e-5 rad here.
    assert!(
        (p.alpha - 1.57991).abs() < 5e-5 && (p.pixel_size - 2.39519).abs() < 1e-4,
        "{p:?}"
    );
    let p = by_id(&found, 0).pose;
    assert!(
        (p.x - 325.317).abs() < 0.5 && (p.y - 131.723).abs() < 0.5,
        "{p:?}"
    );
}

/// An exact pixel-grid transform: image operation, point map and linear part.
struct Transform {
    name: &'static str,
    apply: fn(&GreyImage) -> GreyImage,
    /// Linear part on `(col, row)` vectors.
    linear: Matrix2<f64>,
}

impl Transform {
    /// Image of pixel `p` of a `w × h` image.
    fn point(&self, p: Vector2<f64>, w: usize, h: usize) -> Vector2<f64> {
        let (w, h) = ((w - 1) as f64, (h - 1) as f64);
        let q = self.linear * p;
        // Translation so that the transformed image starts at (0, 0).
        let corners =
            [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].map(|(x, y)| self.linear * Vector2::new(x, y));
        let min = Vector2::new(
            corners.iter().map(|c| c.x).fold(f64::INFINITY, f64::min),
            corners.iter().map(|c| c.y).fold(f64::INFINITY, f64::min),
        );
        q - min
    }
}

fn transforms() -> Vec<Transform> {
    vec![
        Transform {
            name: "rot90",
            apply: |i| i.rotated_90_clockwise(),
            linear: Matrix2::new(0.0, -1.0, 1.0, 0.0),
        },
        Transform {
            name: "rot180",
            apply: |i| i.rotated_90_clockwise().rotated_90_clockwise(),
            linear: Matrix2::new(-1.0, 0.0, 0.0, -1.0),
        },
        Transform {
            name: "rot270",
            apply: |i| {
                i.rotated_90_clockwise()
                    .rotated_90_clockwise()
                    .rotated_90_clockwise()
            },
            linear: Matrix2::new(0.0, 1.0, -1.0, 0.0),
        },
        Transform {
            name: "flip_h",
            apply: |i| i.flipped_horizontally(),
            linear: Matrix2::new(-1.0, 0.0, 0.0, 1.0),
        },
        Transform {
            name: "flip_v",
            apply: |i| i.flipped_vertically(),
            linear: Matrix2::new(1.0, 0.0, 0.0, -1.0),
        },
        Transform {
            name: "transpose",
            apply: |i| i.transposed(),
            linear: Matrix2::new(0.0, 1.0, 1.0, 0.0),
        },
    ]
}

/// Unit vector at `angle` (image frame, y down).
fn unit(angle: f64) -> Vector2<f64> {
    Vector2::new(angle.cos(), angle.sin())
}

#[test]
fn rotations_and_flips_of_real_images_move_poses_exactly() {
    let cases = [
        ("Image96.png", 15.5),
        ("Image100.png", 15.5),
        ("Image105.png", 15.5),
        ("HPCodeImage_20um.png", 20.0),
    ];
    let (mut worst_px, mut worst_rad) = (0.0f64, 0.0f64);
    for (name, period) in cases {
        let image = open_hp(name);
        let (w, h) = (image.width(), image.height());
        // The automatic window size is quantised (FFT-friendly sizes) from the measured marker
        // size, which on real images moves by ~0.3 % with the window: near a size boundary a
        // transformed image may get the next size and a slightly different (~1e-2 px) result.
        // Fix the size to the smaller automatic one of the image; the window centre still
        // comes from the measurement.
        let auto = HpCodeDetector::new(HpCodeParams::new(period, 33))
            .unwrap()
            .detect(&image)
            .unwrap();
        let mut params = HpCodeParams::new(period, 33);
        params.window_size = auto.iter().map(|m| m.window.1).min();
        params.apodize = Some(false);
        let mut detector = HpCodeDetector::new(params).unwrap();
        let before = detector.detect(&image).unwrap();
        assert_eq!(before.len(), 2, "{name}");
        for t in transforms() {
            let after = detector.detect(&(t.apply)(&image)).unwrap();
            assert_eq!(after.len(), 2, "{name} {}", t.name);
            let reflection = t.linear.determinant() < 0.0;
            for m in &before {
                let hand = if m.mirrored { -1.0 } else { 1.0 };
                let ex = t.linear * unit(m.pose.alpha);
                let ey = t.linear * unit(m.pose.alpha + hand * FRAC_PI_2);
                // A reflection shows the marker from behind. With ID bits the detector sees it
                // (`mirrored`); an ID-0 marker is symmetric about its diagonal, so it reads as
                // a marker seen from the front with its axes swapped.
                let (axis, mirrored) = match (reflection, m.id) {
                    (false, _) => (ex, m.mirrored),
                    (true, 0) => (if m.mirrored { ex } else { ey }, false),
                    (true, _) => (ex, !m.mirrored),
                };
                let origin = t.point(m.origin_px, w, h);
                let n = by_id(&after, m.id);
                assert_eq!(n.mirrored, mirrored, "{name} {} id {}", t.name, m.id);
                let err_px = (n.origin_px - origin).norm();
                let err_rad = wrap_to_pi(n.pose.alpha - axis.y.atan2(axis.x)).abs();
                // The whole-field fit bins a large field 2 × 2 on even image coordinates, so in
                // these even-sized images a turned or flipped image has the same bins and the
                // same estimate, to rounding (worst 3.3e-6 px and 8e-9 rad measured). Before,
                // bins started at the field's edge and a mirrored marker's layout was
                // transposed once too often (one ID dot misplaced): 2.05e-3 px and 5e-6 rad.
                assert!(
                    (n.pose.pixel_size / m.pose.pixel_size - 1.0).abs() < 1e-6,
                    "{name} {}: {:?} {:?} windows {:?} {:?} lobes {:?} {:?}",
                    t.name,
                    m.pose,
                    n.pose,
                    m.window,
                    n.window,
                    m.analysis.lobes,
                    n.analysis.lobes
                );
                assert!(
                    err_px < 3e-5,
                    "{name} {} id {}: {err_px:.2e} px",
                    t.name,
                    m.id
                );
                assert!(
                    err_rad < 1e-7,
                    "{name} {} id {}: {err_rad:.2e} rad",
                    t.name,
                    m.id
                );
                worst_px = worst_px.max(err_px);
                worst_rad = worst_rad.max(err_rad);
            }
        }
    }
    println!("rotations and flips: worst {worst_px:.2e} px, {worst_rad:.2e} rad");
}

#[test]
fn whole_field_fit_ignores_dust_and_hair_over_the_dots() {
    // A 33-cell marker at 9 px per period with 1 % noise; a dark blot over 2 × 3 periods of
    // its dot field and a bright hair across it (docs/design.md#field-fit). The window alone
    // is biased by them; the whole-field fit down-weights their cells.
    let period_px = 9.0;
    let truth = Pose::from_origin_in_image(Vector2::new(3.3, -4.1), 0.37, PERIOD / period_px);
    let layout = HpCodeLayout::new(PERIOD, 17).unwrap().with_id(11).unwrap();
    let mut opts = RenderOptions::new(320, 320);
    opts.blur_sigma = 1.0;
    opts.noise_std = 0.01;
    opts.seed = 7;
    let items: Vec<(&dyn Layout, Pose)> = vec![(&layout, truth)];
    let mut image = render_scene(&items, &opts).unwrap();
    let origin = truth.origin_in_image() + Vector2::new(160.0, 160.0);
    let (w, h) = (image.width(), image.height());
    for r in 0..h {
        for c in 0..w {
            let p = Vector2::new(c as f64, r as f64) - origin;
            let blot = (p - Vector2::new(25.0, 10.0)).abs();
            let hair = (p.x * 0.8 - p.y * 0.6 + 15.0).abs() < 1.2 && p.norm() < 60.0;
            let v = &mut image.pixels_mut()[r * w + c];
            if blot.x < 13.0 && blot.y < 9.0 {
                *v = 0.05;
            } else if hair {
                *v = 0.95;
            }
        }
    }
    let measure = |field_fit: bool| {
        let mut params = HpCodeParams::new(PERIOD, 33);
        params.field_fit = field_fit;
        let found = HpCodeDetector::new(params).unwrap().detect(&image).unwrap();
        assert_eq!(found.len(), 1, "field fit {field_fit}: {found:?}");
        let m = &found[0];
        assert_eq!(m.id, 11);
        assert_eq!(m.field.is_some(), field_fit);
        (
            (m.origin_px - origin).norm(),
            wrap_to_pi(m.pose.alpha - truth.alpha).abs(),
        )
    };
    let (field_px, field_rad) = measure(true);
    let (window_px, window_rad) = measure(false);
    println!(
        "dust and hair: whole field {field_px:.2e} px, {field_rad:.2e} rad; window \
         {window_px:.2e} px, {window_rad:.2e} rad"
    );
    assert!(
        field_px < 3e-3 && field_rad < 5e-5,
        "{field_px:.2e} px {field_rad:.2e} rad"
    );
}

#[test]
fn a_calibrated_pixel_size_removes_the_scale_error_far_from_the_centre() {
    // A marker 350 px from the image centre, 2 % noise: its own scale is measured to ~1e-5,
    // which moves its position by ~4e-3 px there; the calibrated scale (here the true one)
    // leaves the phase offsets' error only (docs/design.md#calibrated-scale).
    let pixel_size = PERIOD / 8.5;
    let truth = Pose::from_origin_in_image(Vector2::new(300.0, -180.0), -0.21, pixel_size);
    let layout = HpCodeLayout::new(PERIOD, 17).unwrap().with_id(6).unwrap();
    let detector = |calibrated: Option<f64>| {
        DetectorSettings {
            pattern_type: MarkerKind::HpCode,
            period: Some(PERIOD),
            code_size: Some(33),
            pixel_size: calibrated,
            ..Default::default()
        }
        .build()
        .unwrap()
    };
    let (mut measured, mut calibrated) = (detector(None), detector(Some(pixel_size)));
    let (mut errors_measured, mut errors_calibrated) = (Vec::new(), Vec::new());
    for seed in 0..12 {
        let mut opts = RenderOptions::new(960, 720);
        opts.blur_sigma = 1.0;
        opts.noise_std = 0.02;
        opts.seed = seed;
        let items: Vec<(&dyn Layout, Pose)> = vec![(&layout, truth)];
        let image = render_scene(&items, &opts).unwrap();
        let (a, b) = (
            &measured.detect(&image).unwrap()[0],
            &calibrated.detect(&image).unwrap()[0],
        );
        // Same measurement in pixels; only the conversion to pattern units differs.
        assert!((a.origin_px - b.origin_px).norm() < 1e-9);
        assert!((a.pose.origin_in_image() - b.pose.origin_in_image()).norm() < 1e-9);
        assert_eq!(a.measured_pixel_size, b.measured_pixel_size);
        assert_eq!(b.pose.pixel_size, pixel_size);
        assert!(a.pixel_size_std > 0.0 && a.pixel_size_std < 1e-4 * pixel_size);
        // Camera-frame translation (what the node publishes; the pattern-frame x, y also turn
        // with alpha's error, 350 px × 3e-5 rad = 1e-2 px here).
        let translation = |p: &Pose| p.camera_from_pattern().translation.vector;
        let error = |m: &MarkerPose| (translation(&m.pose) - translation(&truth)).norm();
        errors_measured.push(error(a) / pixel_size);
        errors_calibrated.push(error(b) / pixel_size);
    }
    let rms = |v: &[f64]| (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt();
    let (m, c) = (rms(&errors_measured), rms(&errors_calibrated));
    println!("position RMS error 350 px from the centre: measured scale {m:.2e} px, calibrated {c:.2e} px");
    assert!(c < 0.5 * m, "calibrated {c:.2e} px, measured {m:.2e} px");
}

#[test]
fn axis_aligned_markers_keep_their_field_fit_where_a_harmonic_meets_nyquist() {
    // Markers along the pixel axes (as lab images often are) at 16 and 20 px per period: the
    // whole-field fit bins them 2 × 2, which puts the order-4 (8 px) or order-5 (10 px)
    // harmonics at the binned Nyquist frequency. Demodulated as if they did not overlap their
    // own conjugates, those fits never settled and the window's planes stood (1 and 0 of 6
    // markers kept the fit, RMS 3.3e-3 px against 0.9e-3 px for turned markers). Then a 2 × 2
    // box average folded the harmonics above its Nyquist frequency onto the modelled ones:
    // 1.28e-3 and 1.15e-3 px, a bias locked to the pixel grid; binned through the
    // anti-aliasing filter, 5.7e-4 and 2.5e-4 px (unbinned: 4.9e-4 and 3.1e-4 px).
    let layout = HpCodeLayout::from_code_size(PERIOD, 33)
        .unwrap()
        .with_id(9)
        .unwrap();
    for period_px in [16.0, 20.0] {
        let (mut field, mut window) = (Vec::new(), Vec::new());
        for seed in 0..4u64 {
            let offset = Vector2::new(0.37 * seed as f64, -0.21 * seed as f64);
            let truth = Pose::from_origin_in_image(offset, 0.0015, PERIOD / period_px);
            let mut options = RenderOptions::new(420, 420);
            (options.blur_sigma, options.noise_std, options.seed) = (1.0, 0.01, seed);
            let image = render_scene(&[(&layout as &dyn Layout, truth)], &options).unwrap();
            let centre = Vector2::new(210.0, 210.0) + offset;
            for (field_fit, errors) in [(true, &mut field), (false, &mut window)] {
                let mut params = HpCodeParams::new(PERIOD, 33);
                params.field_fit = field_fit;
                let found = HpCodeDetector::new(params).unwrap().detect(&image).unwrap();
                assert_eq!(found.len(), 1, "{period_px} px, seed {seed}");
                assert_eq!(
                    found[0].field.is_some(),
                    field_fit,
                    "{period_px} px, seed {seed}"
                );
                errors.push((found[0].origin_px - centre).norm_squared());
            }
        }
        let rms = |e: &[f64]| (e.iter().sum::<f64>() / e.len() as f64).sqrt();
        let (field, window) = (rms(&field), rms(&window));
        println!("{period_px} px: RMS position error {field:.2e} px, window only {window:.2e}");
        assert!(
            field < window,
            "{period_px} px: {field:.2e} against {window:.2e}"
        );
        assert!(field < 8e-4, "{period_px} px: {field:.2e}");
    }
}
