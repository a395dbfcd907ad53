//! Regression tests for stamp failures, rebuilt from renders at a known pose and detected with
//! only the settings a user types (`--stamp --period P --bitmap …`):
//! * issue 11's "a bright-field colour microscope image of two stamps (D and G), blue-tinted,
//!   stamps darker than the substrate inside a bright frame: neither stamp found";
//! * the real-image stress bench's (`cargo bench -p vernier-stress --bench real_views`) faint
//!   `stamp69x69` under a steep illumination gradient, read mirrored (and so dropped).

mod common;

use image::{DynamicImage, Rgb, RgbImage, Rgba, RgbaImage};
use nalgebra::Vector2;
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::layout::{BitmapLayout, Layout};
use vernier::render::{render_scene, RenderOptions};
use vernier::{Detector, GreyImage, Pose};

const PERIOD: f64 = 15.5;

/// Two stamps (D, G) as dark material on a lighter substrate, each inside a saturated bright
/// rim, an illumination gradient, and a blue cast; returned as RGB and RGBA colour images with
/// the truth (ID, centre pixel).
fn blue_bright_field() -> (Vec<DynamicImage>, Vec<(u64, Vector2<f64>)>) {
    let dir = common::data_dir().join("layouts");
    let bitmaps: Vec<BitmapLayout> = ["stampD", "stampG"]
        .iter()
        .map(|n| BitmapLayout::from_image_file(PERIOD, dir.join(format!("{n}.png"))).unwrap())
        .collect();
    let (w, h) = (1100usize, 560usize);
    let center = Vector2::new((w / 2) as f64, (h / 2) as f64);
    let truth = [
        (0u64, Vector2::new(290.0, 285.0), 0.03, 7.1),
        (1u64, Vector2::new(800.0, 270.0), -0.4, 7.3),
    ];
    let poses: Vec<Pose> = truth
        .iter()
        .map(|&(_, at, alpha, period_px)| {
            Pose::from_origin_in_image(at - center, alpha, PERIOD / period_px)
        })
        .collect();
    let items: Vec<(&dyn Layout, Pose)> = bitmaps
        .iter()
        .zip(&poses)
        .map(|(b, p)| (b as &dyn Layout, *p))
        .collect();
    let mut options = RenderOptions::new(w, h);
    options.blur_sigma = 0.8;
    let material = render_scene(&items, &options).unwrap();
    // Bright rim: a band 1.5–3.5 periods outside each stamp's frame (stamps are 34.5 periods
    // wide), saturated.
    let rim = |c: f64, r: f64| {
        truth.iter().any(|&(_, at, alpha, period_px)| {
            let d = Vector2::new(c, r) - at;
            let (s, co) = alpha.sin_cos();
            let local = Vector2::new(co * d.x + s * d.y, -s * d.x + co * d.y) / period_px;
            let half = local.x.abs().max(local.y.abs());
            (34.5 / 2.0 + 1.5..34.5 / 2.0 + 3.5).contains(&half)
        })
    };
    let mut rgb = RgbImage::new(w as u32, h as u32);
    let mut rgba = RgbaImage::new(w as u32, h as u32);
    for (i, &m) in material.pixels().iter().enumerate() {
        let (c, r) = ((i % w) as f64, (i / w) as f64);
        let light = 0.75 + 0.25 * (c / w as f64) - 0.1 * (r / h as f64);
        let grey = if rim(c, r) {
            1.3
        } else {
            light * (0.62 - 0.4 * m as f64)
        };
        // Blue cast: red and green attenuated, blue saturates first.
        let px = [0.45 * grey, 0.7 * grey, 1.15 * grey].map(|v| (v.clamp(0.0, 1.0) * 255.0) as u8);
        rgb.put_pixel((i % w) as u32, (i / w) as u32, Rgb(px));
        rgba.put_pixel(
            (i % w) as u32,
            (i / w) as u32,
            Rgba([px[0], px[1], px[2], 255]),
        );
    }
    let truth = truth
        .iter()
        .zip(&poses)
        .map(|(t, p)| (t.0, center + p.origin_in_image()))
        .collect();
    (
        vec![DynamicImage::ImageRgb8(rgb), DynamicImage::ImageRgba8(rgba)],
        truth,
    )
}

#[test]
fn dark_blue_tinted_stamps_inside_a_bright_rim_are_found() {
    let dir = common::data_dir().join("layouts");
    let settings = DetectorSettings {
        pattern_type: MarkerKind::Stamp,
        period: Some(PERIOD),
        bitmaps: vec![dir.join("stampD.png"), dir.join("stampG.png")],
        ..Default::default()
    };
    let mut detector = Detector::new(settings.to_config().unwrap()).unwrap();
    let (images, truth) = blue_bright_field();
    for colour in &images {
        let image = GreyImage::from_dynamic(colour).unwrap();
        let found = detector.detect(&image).unwrap();
        assert_eq!(found.len(), 2, "{:?}: {found:#?}", colour.color());
        for (id, at) in &truth {
            let m = found
                .iter()
                .find(|m| (m.origin_px - at).norm() < 1.0)
                .unwrap_or_else(|| panic!("stamp {id} at {at:?} missing: {found:#?}"));
            assert_eq!(m.id, *id);
        }
    }
}

/// `stamp69x69` (nearly its own mirror image: only its glyphs tell them apart) as bright dots
/// of low contrast under a steep illumination gradient, seen turned by ~274°, 8 bits (the
/// real-image stress bench's scene 879 of `stamp1.png`): the stamp and its proper reading
/// (not mirrored).
fn faint_stamp_under_a_gradient(alpha: f64) -> (GreyImage, Vector2<f64>) {
    let dir = common::data_dir().join("layouts");
    let bitmap = BitmapLayout::from_image_file(PERIOD, dir.join("stamp69x69.png")).unwrap();
    let (w, h) = (520usize, 520usize);
    let center = Vector2::new((w / 2) as f64, (h / 2) as f64);
    let at = Vector2::new(266.0, 251.0);
    let pose = Pose::from_origin_in_image(at - center, alpha, PERIOD / 10.9);
    let mut options = RenderOptions::new(w, h);
    options.blur_sigma = 1.0;
    let material = render_scene(&[(&bitmap as &dyn Layout, pose)], &options).unwrap();
    let pixels = material
        .pixels()
        .iter()
        .enumerate()
        .map(|(i, &m)| {
            let (c, r) = ((i % w) as f64 / w as f64, (i / w) as f64 / h as f64);
            // Gain from 1 down to 0.43 across the field, a little vignetting.
            let light =
                1.0 - 0.5 * (0.8 * c + 0.2 * r) - 0.07 * ((c - 0.5).powi(2) + (r - 0.5).powi(2));
            let grey = light * (0.70 + 0.15 * m as f64);
            ((grey.clamp(0.0, 1.0) * 255.0).round() / 255.0) as f32
        })
        .collect();
    (
        GreyImage::new(w, h, pixels).unwrap(),
        center + pose.origin_in_image(),
    )
}

#[test]
fn a_faint_nearly_symmetric_stamp_under_a_steep_gradient_is_read_the_right_way_round() {
    let dir = common::data_dir().join("layouts");
    let settings = DetectorSettings {
        pattern_type: MarkerKind::Stamp,
        period: Some(PERIOD),
        bitmaps: vec![dir.join("stamp69x69.png")],
        ..Default::default()
    };
    let mut detector = Detector::new(settings.to_config().unwrap()).unwrap();
    for degrees in [274.2f64, 94.2, 4.2, 184.2] {
        let (image, at) = faint_stamp_under_a_gradient(degrees.to_radians());
        let found = detector.detect(&image).unwrap();
        assert_eq!(found.len(), 1, "{degrees}°: {found:#?}");
        assert!(
            (found[0].origin_px - at).norm() < 1.0,
            "{degrees}°: {found:#?}"
        );
        assert_eq!(found[0].pose.gamma, 0.0, "{degrees}°: read mirrored");
    }
}
