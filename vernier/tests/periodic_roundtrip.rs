//! Render → detect round trips of plain periodic grids at random poses (issue 2 acceptance):
//! periods 7–15 px, 8–30 periods visible per side, odd and even sizes, any orientation.

mod common;

use rand::{rngs::SmallRng, Rng, SeedableRng};
use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions, Sampling};
use vernier::{PeriodicDetector, PeriodicParams, Pose};

struct Case {
    period_px: f64,
    size: (usize, usize),
    pose: Pose,
    period: f64,
}

fn random_case(rng: &mut SmallRng) -> Case {
    let period_px: f64 = rng.random_range(7.0..15.0);
    let periods_w: f64 = rng.random_range(8.0..30.0);
    let periods_h: f64 = rng.random_range(8.0..30.0);
    let size = (
        (periods_w * period_px).round() as usize,
        (periods_h * period_px).round() as usize,
    );
    let pixel_size = rng.random_range(0.5..2.0);
    let period = period_px * pixel_size;
    let pose = Pose::planar(
        rng.random_range(-3.0..3.0) * period,
        rng.random_range(-3.0..3.0) * period,
        rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
        pixel_size,
    );
    Case {
        period_px,
        size,
        pose,
        period,
    }
}

/// Image formation of a round-trip batch.
#[derive(Clone, Copy)]
struct Imaging {
    sampling: Sampling,
    blur: f64,
    noise: f64,
    bits: Option<u32>,
}

const SHARP: Imaging = Imaging {
    sampling: Sampling::Area,
    blur: 0.0,
    noise: 0.0,
    bits: None,
};

struct Stats {
    worst_px: f64,
    rms_px: f64,
    worst_rad: f64,
}

fn run(
    imaging: Imaging,
    cases: usize,
    seed: u64,
    configure: impl Fn(&mut PeriodicParams),
) -> Stats {
    let mut rng = SmallRng::seed_from_u64(seed);
    let (mut worst_px, mut worst_rad, mut sum2) = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..cases {
        let case = random_case(&mut rng);
        let dots = (2.0 * (case.size.0.max(case.size.1) as f64) / case.period_px) as usize + 9;
        let layout = PeriodicLayout::new(case.period, dots | 1, dots | 1).unwrap();
        let mut opts = RenderOptions::new(case.size.0, case.size.1);
        opts.sampling = imaging.sampling;
        opts.blur_sigma = imaging.blur;
        opts.noise_std = imaging.noise;
        opts.bit_depth = imaging.bits;
        opts.seed = i as u64;
        if imaging.noise > 0.0 {
            // No saturation (as the method requires): noise must not be clipped at 0 or 1.
            opts.background = 0.05;
            opts.foreground = 0.95;
        }
        let image = render(&layout, &case.pose, &opts).unwrap();
        let mut params = PeriodicParams::new(case.period);
        configure(&mut params);
        let found = PeriodicDetector::new(params)
            .unwrap()
            .detect(&image)
            .unwrap();
        let center = ((case.size.0 / 2) as f64, (case.size.1 / 2) as f64);
        let (err_px, err_rad) = common::lattice_error(&found.pose, &case.pose, case.period, center);
        if std::env::var("VERBOSE").is_ok() && err_px > 1e-5 {
            eprintln!("case {i}: {:?} period {:.2} px: {err_px:.2e} px {err_rad:.2e} rad, iterations {}, lobes {:?}", case.size, case.period_px, found.analysis.iterations, found.analysis.lobes);
        }
        worst_px = worst_px.max(err_px);
        worst_rad = worst_rad.max(err_rad);
        sum2 += err_px * err_px;
    }
    let stats = Stats {
        worst_px,
        rms_px: (sum2 / cases as f64).sqrt(),
        worst_rad,
    };
    eprintln!(
        "{cases} cases: worst {:.2e} px, rms {:.2e} px, worst angle {:.2e} rad",
        stats.worst_px, stats.rms_px, stats.worst_rad
    );
    stats
}

#[test]
fn noise_free_with_optical_blur_meets_targets() {
    // Sharp square dots seen through 0.5 px (σ) optics, area-sampled by the pixels.
    let s = run(Imaging { blur: 0.5, ..SHARP }, 60, 1, |_| {});
    assert!(s.worst_px < 1e-3, "translation {:.2e} px", s.worst_px);
    assert!(s.worst_rad < 1e-5, "angle {:.2e} rad", s.worst_rad);
    // Measured: 3e-5 px, 4e-7 rad. Keep a margin check so regressions show.
    assert!(s.worst_px < 1e-4 && s.worst_rad < 2e-6);
}

#[test]
fn noise_free_sharp_area_sampled_dots() {
    // Perfectly sharp dots alias their high harmonics onto the fundamentals when sampled by
    // pixels: this bounds any estimator. Measured 7.3e-4 px and 1.2e-5 rad worst.
    let s = run(SHARP, 60, 1, |_| {});
    assert!(s.worst_px < 1e-3, "translation {:.2e} px", s.worst_px);
    assert!(s.worst_rad < 1.5e-5, "angle {:.2e} rad", s.worst_rad);
    assert!(s.rms_px < 2e-4, "rms {:.2e} px", s.rms_px);
}

#[test]
fn noise_free_raised_cosine_point_samples() {
    // The original's renderer (band-limited profile): the estimator alone is tested here.
    let s = run(
        Imaging {
            sampling: Sampling::Point,
            ..SHARP
        },
        60,
        3,
        |_| {},
    );
    assert!(s.worst_px < 5e-6, "translation {:.2e} px", s.worst_px);
    assert!(s.worst_rad < 5e-7, "angle {:.2e} rad", s.worst_rad);
}

#[test]
fn one_percent_noise_on_12_bit_images() {
    let imaging = Imaging {
        blur: 0.5,
        noise: 0.01,
        bits: Some(12),
        ..SHARP
    };
    let s = run(imaging, 60, 2, |_| {});
    assert!(s.worst_px < 5e-3, "translation {:.2e} px", s.worst_px);
    let sharp = run(
        Imaging {
            blur: 0.0,
            ..imaging
        },
        60,
        4,
        |_| {},
    );
    assert!(
        sharp.worst_px < 5e-3,
        "translation {:.2e} px",
        sharp.worst_px
    );
}

#[test]
fn band_pass_alone_is_the_original_method() {
    // Without refinement the planes are those of docs/design.md#phase-bandpass (Gaussian band-pass,
    // plane fit), whose harmonic leakage costs accuracy on raised-cosine renders.
    let plain = run(
        Imaging {
            sampling: Sampling::Point,
            ..SHARP
        },
        30,
        3,
        |p| p.phase.refine_iterations = 0,
    );
    assert!(
        plain.worst_px < 2e-3,
        "translation {:.2e} px",
        plain.worst_px
    );
    assert!(
        plain.worst_px > 2e-5,
        "refinement should be what brings the 1e-5 px level"
    );
}

/// The decimated band-pass evaluates the same band-limited phase field as the full-size inverse
/// transform, sample for sample (the original's band-pass made cheap,
/// docs/design.md#phase-bandpass).
#[test]
fn demodulated_band_pass_samples_the_full_size_phase_exactly() {
    // 144 px and 216 px sides: the 36-point decimated grid falls on every 4th / 6th pixel.
    let layout = PeriodicLayout::new(10.0, 61, 61).unwrap();
    let image = render(
        &layout,
        &Pose::planar(1.3, -2.2, 0.37, 1.0),
        &RenderOptions::new(144, 216),
    )
    .unwrap();
    let mut engine = vernier::PhaseEngine::new();
    let mut params = vernier::PhaseParams {
        keep_phase_maps: true,
        spectrum_binning: false,
        ..Default::default()
    };
    let decimated = engine.analyze(&image, &params).unwrap();
    params.full_resolution_bandpass = true;
    let full = engine.analyze(&image, &params).unwrap();
    let (dec_maps, full_maps) = (decimated.maps.unwrap(), full.maps.unwrap());
    let mut worst = 0.0f64;
    for (d, f) in dec_maps.iter().zip(&full_maps) {
        assert_eq!((f.rows, f.cols), (216, 144));
        assert_eq!((d.step_x, d.step_y), (4.0, 6.0));
        for j in 0..d.rows {
            for i in 0..d.cols {
                let (x, y) = (i * 4, j * 6);
                let diff = (d.phase[j * d.cols + i] as f64 - f.phase[y * f.cols + x] as f64)
                    .rem_euclid(std::f64::consts::TAU);
                worst = worst.max(diff.min(std::f64::consts::TAU - diff));
            }
        }
    }
    eprintln!("decimated vs full-size phase samples: worst difference {worst:.2e} rad");
    assert!(worst < 2e-4, "{worst:.2e} rad");
}

/// What the detector reports is identical with the decimated and the full-size band-pass, and
/// with or without the 2×2-binned spectral stage: the spectral planes only start the refinement,
/// which converges to the same planes.
#[test]
fn demodulated_band_pass_loses_no_accuracy() {
    let mut rng = SmallRng::seed_from_u64(11);
    let mut worst = 0.0f64;
    for i in 0..20 {
        let case = random_case(&mut rng);
        let dots = (2.0 * (case.size.0.max(case.size.1) as f64) / case.period_px) as usize + 9;
        let layout = PeriodicLayout::new(case.period, dots | 1, dots | 1).unwrap();
        let mut opts = RenderOptions::new(case.size.0, case.size.1);
        opts.noise_std = if i % 2 == 0 { 0.0 } else { 0.01 };
        opts.background = 0.05;
        opts.foreground = 0.95;
        opts.seed = i;
        let image = render(&layout, &case.pose, &opts).unwrap();
        let mut engine = vernier::PhaseEngine::new();
        let mut params = vernier::PhaseParams::default();
        let decimated = engine.analyze(&image, &params).unwrap();
        params.full_resolution_bandpass = true;
        let full = engine.analyze(&image, &params).unwrap();
        params.full_resolution_bandpass = false;
        params.spectrum_binning = false;
        let unbinned = engine.analyze(&image, &params).unwrap();
        for (d, f) in decimated
            .planes
            .iter()
            .zip(&full.planes)
            .chain(unbinned.planes.iter().zip(&full.planes))
        {
            let pixels = case.size.0.max(case.size.1) as f64;
            let diff = vernier::phase::wrap_to_pi(d.c - f.c).abs()
                + ((d.a - f.a).abs() + (d.b - f.b).abs()) * pixels;
            worst = worst.max(diff);
        }
    }
    eprintln!(
        "decimated/binned vs full-size band-pass, final planes: worst difference {worst:.2e} rad"
    );
    assert!(worst < 1e-6, "{worst:.2e} rad");
}

#[test]
fn tiles_of_a_grid_calibrate_the_pixel_size_within_its_sigma() {
    use vernier::calibration::{calibrate, tile_samples};
    // Three noisy 600 × 450 renders of one grid (9.3 px per period): 3 × 3 tiles each. The
    // pooled pixel size must agree with the truth within 4σ, with no gradient beyond 4σ, and
    // the tiles must scatter as their own σ say (χ²/dof near 1).
    let (period, pixel_size) = (12.0, 12.0 / 9.3);
    let layout = PeriodicLayout::new(period, 81, 81).unwrap();
    let mut samples = Vec::new();
    let mut detector = vernier::Detector::new(vernier::DetectorConfig::Periodic(
        PeriodicParams::new(period),
    ))
    .unwrap();
    for seed in 0..3 {
        let pose = Pose::planar(
            1.3 * seed as f64,
            -0.7,
            0.31 + 0.01 * seed as f64,
            pixel_size,
        );
        let mut opts = RenderOptions::new(600, 450);
        opts.blur_sigma = 1.0;
        opts.noise_std = 0.02;
        opts.seed = seed;
        let image = render(&layout, &pose, &opts).unwrap();
        samples.extend(tile_samples(&image, &mut detector, 3).unwrap());
    }
    assert_eq!(samples.len(), 27);
    let fit = calibrate(&samples).unwrap();
    let (g, g_std) = (fit.gradient.unwrap(), fit.gradient_std.unwrap());
    let chi2 = fit.chi2_per_dof.unwrap();
    println!(
        "pixel size {:.8} ± {:.1e} (truth {pixel_size:.8}), gradient ({:.1e} ± {:.1e}, {:.1e} \
         ± {:.1e}) /px, χ²/dof {chi2:.2}",
        fit.pixel_size, fit.pixel_size_std, g.x, g_std.x, g.y, g_std.y
    );
    assert!((fit.pixel_size - pixel_size).abs() < 4.0 * fit.pixel_size_std);
    // Pooling 27 tiles: √27 ≈ 5× below one tile's σ (~1e-5 relative here).
    let single = samples.iter().map(|s| s.std).fold(f64::INFINITY, f64::min);
    assert!(
        fit.pixel_size_std < single / 4.0,
        "{} vs {single}",
        fit.pixel_size_std
    );
    assert!(g.x.abs() < 4.0 * g_std.x && g.y.abs() < 4.0 * g_std.y);
    assert!((0.3..3.0).contains(&chi2), "{chi2}");
}
