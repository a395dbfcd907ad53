//! The small, fixed-seed stress suite with the detectors' targets.
//!
//! 110 scenes (5 per category and family: seeds 0..110 cycle through the 11 categories of
//! both families), detected with the settings a CLI user would give. Targets, per family over
//! every category: ≥ 99 % of the expected markers found with their ID, no wrong ID, no false
//! marker; on the `clean` and `blur` categories (no perspective, no noise) every position
//! error below 2e-3 px.
//!
//! The stamp bitmaps come from `$VERNIER_DATA_DIR` (default `../shared/data` beside the
//! workspace): without them the test fails, it does not skip.

use vernier_stress::degrade::Degradation;
use vernier_stress::suite::{rms_ratio, Tally, ACCURACY_CATEGORIES, ACCURACY_LIMIT_PX};
use vernier_stress::{run, select_seeds, Category, Family, Generator, Report};

/// First seed of the fixed set.
const FIRST_SEED: u64 = 0;
/// 5 scenes per (family, category).
const SCENES: usize = 110;

#[test]
fn small_stress_suite_meets_the_targets() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let seeds = select_seeds(FIRST_SEED, SCENES, None, None);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut report = Report::default();
    run(&generator, &seeds, threads, &mut |o| report.add(&o))
        .unwrap_or_else(|e| panic!("scene generation failed: {e}"));
    for family in Family::ALL {
        println!("{}", report.markdown(family));
    }
    println!("failing seeds (run the bench with `--only SEED --dump DIR`):");
    println!("{}", report.failing_list(20));
    println!("{}", report.generation_profile());

    let mut problems = Vec::new();
    for family in Family::ALL {
        let t = report.family_total(family);
        let name = family.name();
        if t.found_fraction() < 0.99 {
            problems.push(format!(
                "{name}: {:.1} % found ({} of {}), target ≥ 99 %",
                100.0 * t.found_fraction(),
                t.found,
                t.markers
            ));
        }
        if t.wrong_id > 0 {
            problems.push(format!("{name}: {} wrong IDs, target 0", t.wrong_id));
        }
        if t.false_markers > 0 {
            problems.push(format!(
                "{name}: {} false markers, target 0",
                t.false_markers
            ));
        }
        for ((f, c), cell) in &report.cells {
            if *f != family || !ACCURACY_CATEGORIES.contains(&c.name()) {
                continue;
            }
            if let Some((_, _, max)) = cell.position_stats() {
                if max >= ACCURACY_LIMIT_PX {
                    problems.push(format!(
                        "{name} / {}: position error up to {max:.2e} px, target < {ACCURACY_LIMIT_PX:.0e} px",
                        c.name()
                    ));
                }
            }
        }
    }
    assert!(
        problems.is_empty(),
        "stress targets missed:\n{}",
        problems.join("\n")
    );
}

#[test]
fn scenes_are_reproducible_from_their_seed() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    for seed in [3u64, 18, 32] {
        let a = generator.generate(seed).unwrap_or_else(|e| panic!("{e}"));
        let b = generator.generate(seed).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(a.image, b.image, "seed {seed}");
        assert_eq!(a.truth, b.truth, "seed {seed}");
        assert_eq!(a.spec, b.spec);
    }
}

/// HP code scenes that once were missed or misread, most with dust or hair over a corner of a
/// marker: over a finder (119, 141, 427, 581, 691, 1505, 2143; 581 once read a quarter turn) and
/// over the dot corner with one finder hidden too (59189, once read as another ID), and a blob
/// darker than the dots beside a finder (52831: read a half-turn while the corners were judged
/// against thresholds extrapolated from the inner dots' quadrants, a tried design), two blobs
/// brighter than the dots over the inner dots beside the dot corner (51666: the corner check found
/// no threshold there and refused the marker); and a marker tilted by 23° whose edge dots lie 0.3
/// period off the window's linear grid (52669: missed until the ID edges were sampled with their
/// reference dots' local shift). These and the seeds below are drawn as they were picked, with no
/// marker seen from the back (52669's marker is drawn mirrored now: see [`STEEP_TILT_SEEDS`]).
const REGRESSION_SEEDS: [u64; 11] = [
    119, 141, 427, 581, 691, 1505, 2143, 51666, 52669, 52831, 59189,
];

/// Runs the HP code scenes of `seeds`, prints their table and checks that every marker is found
/// with its ID and nothing false is reported; returns their tally.
fn every_hp_marker_read_right(seeds: &[u64]) -> Tally {
    let generator = Generator::from_env()
        .unwrap_or_else(|e| panic!("{e}"))
        .without_mirrored_markers();
    every_marker_read_right(&generator, seeds)
}

/// The scenes of `seeds` drawn by `generator`, run on every core: their report.
fn run_scenes(generator: &Generator, seeds: &[u64]) -> Report {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut report = Report::default();
    run(generator, seeds, threads, &mut |o| report.add(&o))
        .unwrap_or_else(|e| panic!("scene generation failed: {e}"));
    report
}

/// The HP code scenes of `seeds` drawn by `generator`, run: their report and HP tally.
fn hp_scenes(generator: &Generator, seeds: &[u64]) -> (Report, Tally) {
    let report = run_scenes(generator, seeds);
    let t = report.family_total(Family::HpCode);
    println!("{}", report.markdown(Family::HpCode));
    (report, t)
}

/// [`every_hp_marker_read_right`] with the scenes of `generator`.
fn every_marker_read_right(generator: &Generator, seeds: &[u64]) -> Tally {
    let (report, t) = hp_scenes(generator, seeds);
    assert!(t.markers > 0);
    assert_eq!(
        (t.found, t.wrong_id, t.false_markers),
        (t.markers, 0, 0),
        "{}",
        report.failing_list(20)
    );
    t
}

#[test]
fn dusty_corner_scenes_are_read_right() {
    every_hp_marker_read_right(&REGRESSION_SEEDS);
}

/// HP code scenes of markers tilted by 21–24° before a camera of 1.5–2.3 image diagonals of
/// focal length, drawn as the bench draws them (52669: seen from the back), missed while the
/// finders had to sit on the window's linear grid: their legs were half a period off it. The
/// finders' view now has the marker's perspective (`hpcode/fine.rs`, `finder_view`).
const STEEP_TILT_SEEDS: [u64; 6] = [51085, 52383, 52669, 53263, 53285, 54979];

#[test]
fn steeply_tilted_markers_are_read_right() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    every_marker_read_right(&generator, &STEEP_TILT_SEEDS);
}

/// An HP code whose finder is half hidden by a hair and a blob brighter than the dots, beside
/// a blob darker than the dots near its dot corner (62907, a fresh seed): it was read
/// reflected across its diagonal, with a wrong ID at confidence 0.9995, the spoiled finder
/// taken for the dot corner. It must not be reported (it is not readable: missed), and the
/// scene's other marker must still be found. Read on the grid fitted to its own dots, the
/// marker passed every check with its right ID, while the planes of its dusty window put its
/// centre 0.05 period (1.1 px) off: the planes must agree with the dots
/// (docs/design.md#hp-dot-homography).
#[test]
fn a_hidden_dot_corner_never_confirms_a_reflected_reading() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let (_, t) = hp_scenes(&generator, &[62907]);
    assert_eq!((t.found, t.wrong_id, t.false_markers), (1, 0, 0));
    let worst = t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e));
    assert!(
        worst < GROSS_OUTLIER_MAX_ERROR_PX,
        "position error {worst:.2e} px"
    );
}

/// HP code scenes whose fine fit or ID once went wrong while the marker was "found": a dust
/// blob darker than the dots over the field (54481: 0.40 px off; 52634, with hair, JPEG and low
/// contrast: 0.51 px), a hair across the field (41061: 4e-2 px in a first fix), a small
/// marker under strong vignetting at low contrast, read a half-turn with ID 0 (51050), and a
/// hair with five blobs over a noise-free marker (54987: 3.3e-2 px while the whole-field fit
/// tied the harmonics to the dot centres without first testing that their phases allow it).
const GROSS_OUTLIER_SEEDS: [u64; 5] = [54481, 52634, 41061, 51050, 54987];

/// Largest position error accepted on those scenes, pixels (none has perspective; the
/// JPEG-compressed, low-contrast one is noise-limited near 4e-3).
const GROSS_OUTLIER_MAX_ERROR_PX: f64 = 5e-3;

#[test]
fn gross_outliers_do_not_move_a_found_marker() {
    let t = every_hp_marker_read_right(&GROSS_OUTLIER_SEEDS);
    let worst = t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e));
    assert!(
        worst < GROSS_OUTLIER_MAX_ERROR_PX,
        "worst position error {worst:.2e} px"
    );
}

/// A noise-free HP code crossed by a hair (51137): once the robust weights froze, its
/// whole-field fit's steps shrank by pairs, one sweep of each pair a little larger than the one
/// before (2.3e-3, 2.5e-3, 4.4e-4, 5.0e-4 rad, ...), and the fit was given up as not
/// contracting. The window's planes, which the hair pulls, then put the marker 1.3e-2 px off.
/// Judged over pairs of sweeps the fit converges, 1.1e-4 px off.
#[test]
fn a_field_fit_whose_steps_shrink_by_pairs_is_kept() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let (_, t) = hp_scenes(&generator, &[51137]);
    assert_eq!((t.found, t.wrong_id, t.false_markers), (t.markers, 0, 0));
    let worst = t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e));
    assert!(worst < 1e-3, "worst position error {worst:.2e} px");
}

/// Noise-free HP code scenes with a hair (and dust) across the dot field, 3.4e-3 to 5.2e-3 px
/// off while the whole-field fit kept the soft, blurred edges of the hair and the dust: the
/// biweight rejected their cores only, and the edges, not point-symmetric about the dots they
/// cross, pulled the planes. The edges now go with the cores (`phase/field_fit/`,
/// `outlier_extents`): 1.9e-5 to 3.4e-4 px.
const OUTLIER_EDGE_SEEDS: [u64; 6] = [52831, 60795, 59673, 52787, 58639, 63787];

#[test]
fn the_soft_edges_of_hair_and_dust_do_not_pull_a_marker() {
    let t = every_hp_marker_read_right(&OUTLIER_EDGE_SEEDS);
    let worst = t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e));
    assert!(worst < 1e-3, "worst position error {worst:.2e} px");
}

/// Two hairs across a stamp of 4.5-px period (82938): once its robust weights froze, the
/// whole-field fit contracted by a steady 0.6 per sweep (steps 1.3e-2, 1.1e-2, 6.2e-3,
/// 4.5e-3 rad, ...), too slowly for the rule that every step must halve, and it was given up.
/// The window's planes, which the hairs pull, put the marker 5.1e-2 px off with a σ of
/// 2.6e-5 px. A fit now runs on while its contraction can converge within the iterations
/// left: 23 sweeps, 3.4e-5 px off.
#[test]
fn a_field_fit_that_contracts_slowly_but_steadily_is_kept() {
    let worst = worst_stamp_error(&[82938]);
    assert!(worst < 1e-3, "worst position error {worst:.2e} px");
}

/// The stamp scenes of `seeds`, run: every marker found with its ID and nothing false; the
/// largest position error, pixels.
fn worst_stamp_error(seeds: &[u64]) -> f64 {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let report = run_scenes(&generator, seeds);
    let t = report.family_total(Family::Stamp);
    println!("{}", report.markdown(Family::Stamp));
    assert!(t.markers > 0);
    assert_eq!((t.found, t.wrong_id, t.false_markers), (t.markers, 0, 0));
    t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e))
}

/// Steeply tilted markers (21–24° before lenses of 1.5–3 image diagonals, `p·v` up to 0.1 at
/// the field's edge), which the whole-field fit's one linear tilt step left 0.27–1.2 px off
/// (HP 53263, 51085, 54693) or whose flat fit the curvature threw off, so that the window's
/// planes stood (stamps 54000, 57014: 0.36 and 0.18 px). The fit now carries the tilt in its
/// phase model, from the coarse step's measure of it (the HP dots' homography, the stamp
/// frame's outline), and measures what is left pass by pass (`phase/field_fit/pixels.rs`, `Warp`):
/// 3.7e-5 to 2.3e-3 px.
const PHASE_TILT_SEEDS: [u64; 5] = [53263, 51085, 54693, 54000, 57014];

#[test]
fn steeply_tilted_markers_are_measured_with_the_tilt_in_their_phase() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let report = run_scenes(&generator, &PHASE_TILT_SEEDS);
    for family in [Family::HpCode, Family::Stamp] {
        let t = report.family_total(family);
        println!("{}", report.markdown(family));
        assert!(t.markers >= 2, "{family:?}: {} markers", t.markers);
        assert_eq!((t.found, t.wrong_id, t.false_markers), (t.markers, 0, 0));
        let worst = t.position_errors.iter().fold(0.0f64, |w, e| w.max(*e));
        assert!(
            worst < 5e-3,
            "{family:?}: worst position error {worst:.2e} px"
        );
    }
}

/// Clean low-contrast scenes rounded to 8 bits whose found markers were 200–430 times their
/// predicted σ off (HP 54808: 3.7e-3 px; stamp 55171: 1.4e-3 px): the white-noise estimate
/// missed the rounding, so the σ was too small and the whole-field fit lost to a worse
/// window. With the rounding's `Δ²/12` as a floor (the stamp's apodised window taking it from
/// its source) each error is within a few σ.
#[test]
fn clean_8_bit_low_contrast_markers_report_an_honest_sigma() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let report = run_scenes(&generator, &[54808, 55171]);
    for family in [Family::HpCode, Family::Stamp] {
        let t = report.family_total(family);
        println!("{}", report.markdown(family));
        assert_eq!((t.found, t.wrong_id, t.false_markers), (t.markers, 0, 0));
        let (_, _, worst) = t.normalised_stats().expect("found markers");
        assert!(worst < 10.0, "{family:?}: error/σ up to {worst:.1}");
    }
}

/// Stamp scenes with a hair or dust stuck to a frame, missed before: the frame outline found
/// follows the occluder, so its centre lies 0.55–2.5 periods from the frame the reading puts
/// (72136, 74006: the frame is confirmed on the image instead) and its corners suggest a
/// perspective that is not there (73390: the affine view reads the bitmap, the outline's did
/// not).
#[test]
fn stamps_whose_frame_outline_an_occluder_bends_are_read() {
    let generator = Generator::from_env().unwrap_or_else(|e| panic!("{e}"));
    let report = run_scenes(&generator, &[72136, 73390, 74006]);
    let t = report.family_total(Family::Stamp);
    println!("{}", report.markdown(Family::Stamp));
    assert!(t.markers >= 3);
    assert_eq!(
        (t.found, t.wrong_id, t.false_markers),
        (t.markers, 0, 0),
        "{}",
        report.failing_list(20)
    );
}

/// Noisy scenes per family whose markers are measured against their Cramér–Rao bound.
const BOUND_SCENES: usize = 12;

/// Runs `scenes` scenes of `category` per family from a fixed seed set with their position
/// bounds, checks that every marker is read right, and returns each family's tally.
fn bounded_family_totals(category: Category, scenes: usize) -> Vec<(Family, Tally)> {
    let generator = Generator::from_env()
        .unwrap_or_else(|e| panic!("{e}"))
        .with_position_bounds();
    Family::ALL
        .iter()
        .map(|&family| {
            let seeds = select_seeds(FIRST_SEED, scenes, Some(family), Some(category));
            let report = run_scenes(&generator, &seeds);
            let t = report.family_total(family);
            println!("{}", report.markdown(family));
            assert_eq!((t.found, t.wrong_id, t.false_markers), (t.markers, 0, 0));
            (family, t)
        })
        .collect()
}

/// The Cramér–Rao bound of each marker's position (`vernier_stress::bound`) on the noisy scenes
/// of a fixed seed set. No unbiased estimator passes it, so the detector's RMS error over it
/// stays near 1 or above: a bound overstated by a wrong noise, contrast or step scale would
/// show below 0.75. And the detector works near it: within 1.5× in RMS over these varied
/// scenes.
#[test]
fn noisy_markers_are_measured_near_their_cramer_rao_bound() {
    let noise = Category::Only(Degradation::Noise);
    for (family, t) in bounded_family_totals(noise, BOUND_SCENES) {
        assert_eq!(
            t.bounded_errors.len(),
            t.found,
            "every found marker has a bound"
        );
        let rms = rms_ratio(&t.bounded_errors);
        assert!(
            (0.75..=1.5).contains(&rms),
            "{family:?}: RMS error / bound {rms:.2}"
        );
    }
}

/// JPEG scenes per family measured against the additive model of their files' rounding.
const JPEG_MODEL_SCENES: usize = 8;

/// The JPEG model of each marker's position error (`vernier_stress::bound`: each DCT
/// coefficient's rounding taken as noise), on the JPEG scenes of a fixed seed set, with the
/// two reference estimators that know the dot shape (`KnownShapeErrors`) on the same files.
/// - The weighted reference, generalised least squares under the model, reaches the model's
///   figure on the files themselves: RMS error / model within [0.6, 1.6] (1.13 on HP codes
///   and 1.09 on stamps over the bench's 2,000 scenes; 0.78 and 1.03 on these). A model that
///   credited the file with what it does not keep, or a figure off by a wrong table or
///   transform, would show above; one off by a step scale of 2, below or above.
/// - Weighing every pixel alike, as the detector's fit does, costs the unweighted reference
///   accuracy: its RMS is above the weighted one's.
/// - The detector stays within 2.5× of the model in RMS, above 0.75.
#[test]
fn jpeg_markers_are_measured_near_their_file_s_quantisation_model() {
    let jpeg = Category::Only(Degradation::Jpeg);
    for (family, t) in bounded_family_totals(jpeg, JPEG_MODEL_SCENES) {
        assert_eq!(
            t.jpeg_modelled_errors.len(),
            t.found,
            "every found marker has a figure"
        );
        assert_eq!(
            t.known_shape_errors.len(),
            t.found,
            "and its reference errors"
        );
        let rms = rms_ratio(&t.jpeg_modelled_errors);
        let unweighted = rms_ratio(&t.reference_errors(false));
        let weighted = rms_ratio(&t.reference_errors(true));
        println!(
            "{family:?}: RMS error / JPEG model: detector {rms:.2}, references {unweighted:.2} \
             (unweighted) and {weighted:.2} (weighted)"
        );
        assert!(
            (0.75..=2.5).contains(&rms),
            "{family:?}: RMS error / JPEG model {rms:.2}"
        );
        assert!(
            (0.6..=1.6).contains(&weighted),
            "{family:?}: weighted reference's RMS error / JPEG model {weighted:.2}"
        );
        assert!(
            unweighted > weighted,
            "{family:?}: unweighted {unweighted:.2}, weighted {weighted:.2}"
        );
    }
}

/// HP codes of sharp dots 30–34 px per period under weak noise (0.2–0.8 %), whose whole-field
/// fit stopped at order-5 harmonics: the dots' finer detail, left in the residual, leaked
/// into the planes through the missing dots and put them 10.5 and 14.9 times their
/// Cramér–Rao bound off (2.8e-3 and 1.1e-3 px). Orders up to 8 are now modelled where the
/// pixel grid sees them unfolded (`MAX_ORDER` in `phase/field_fit/mod.rs`).
const SHARP_LARGE_DOT_SEEDS: [u64; 2] = [54189, 54387];

#[test]
fn sharp_large_dots_are_measured_near_their_cramer_rao_bound() {
    let generator = Generator::from_env()
        .unwrap_or_else(|e| panic!("{e}"))
        .with_position_bounds();
    let (report, t) = hp_scenes(&generator, &SHARP_LARGE_DOT_SEEDS);
    assert_eq!(
        (t.found, t.wrong_id, t.false_markers),
        (t.markers, 0, 0),
        "{}",
        report.failing_list(20)
    );
    assert_eq!(
        t.bounded_errors.len(),
        t.found,
        "every found marker has a bound"
    );
    for &(error, bound) in &t.bounded_errors {
        assert!(
            error < 3.0 * bound,
            "{error:.2e} px off, {:.1}× its bound {bound:.2e} px",
            error / bound
        );
    }
}

/// A stamp tilted 24.6° before a lens of 2.2 image diagonals, sharp dots (blur 0.44 px),
/// noise-free (54440): the white noise read on its flat lattice came out at 0.056 (the long
/// lattice displacement that fits the flat planes best is moved by most of a period at the
/// field's edges), which hid the tilt's misfit, so no pass with the tilt in the phase ran and
/// the marker was 0.29 px off. The noise is now read where the tilted lattice still matches
/// (`tilted_white_noise_variance`): 2.3e-4 px.
#[test]
fn a_steep_tilt_on_sharp_dots_is_not_hidden_by_its_own_noise_reading() {
    let worst = worst_stamp_error(&[54440]);
    assert!(worst < 2e-3, "{worst:.2e} px off");
}
