use super::*;

/// A dot grid `g = 0.5 + Σ harmonics` with planes `planes`, `n × n` pixels.
fn grid(n: usize, planes: &[PhasePlane; 2], dot: impl Fn(f64, f64) -> f64) -> GreyImage {
    let (cx, cy) = ((n / 2) as f64, (n / 2) as f64);
    let mut px = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let (x, y) = (c as f64 - cx, r as f64 - cy);
            px.push(dot(planes[0].at(x, y), planes[1].at(x, y)) as f32);
        }
    }
    GreyImage::new(n, n, px).unwrap()
}

/// A square field of dots at nodes `−r..=r` per axis, without the `missing` ones.
fn dots(r: i64, missing: &[(i64, i64)]) -> NodeMask {
    NodeMask::from_cells(-r..=r, -r..=r, |v1, v2| {
        let node = (v1.div_euclid(2), v2.div_euclid(2));
        v1 % 2 == 0
            && v2 % 2 == 0
            && node.0.abs() <= r
            && node.1.abs() <= r
            && !missing.contains(&node)
    })
}

fn planes(angle: f64, period: f64, offset: [f64; 2]) -> [PhasePlane; 2] {
    let k = TAU / period;
    let (s, c) = angle.sin_cos();
    [
        PhasePlane {
            a: k * c,
            b: k * s,
            c: offset[0],
        },
        PhasePlane {
            a: -k * s,
            b: k * c,
            c: offset[1],
        },
    ]
}

/// Asserts that `fit` found the `truth` planes: offsets within `offset` rad, slopes within
/// `slope` rad per pixel.
fn assert_planes(fit: &FieldFit, truth: &[PhasePlane; 2], offset: f64, slope: f64) {
    for (f, t) in fit.planes.iter().zip(truth) {
        assert!((f.c - t.c).abs() < offset, "{f:?} {t:?}");
        assert!(
            (f.a - t.a).abs() < slope && (f.b - t.b).abs() < slope,
            "{f:?} {t:?}"
        );
    }
}

/// `image` with uniform noise over `range` (standard deviation `range/√12`; a linear
/// congruential sequence from `seed`).
fn with_noise(mut image: GreyImage, range: f32, seed: u64) -> GreyImage {
    let mut state = seed;
    for v in image.pixels_mut() {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *v += range * ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5);
    }
    image
}

/// Sharp-ish dots: a raised power of the product of cosines (many harmonics).
fn sharp(p1: f64, p2: f64) -> f64 {
    let v = (0.5 + 0.5 * p1.cos()) * (0.5 + 0.5 * p2.cos());
    0.2 + 0.6 * v.powi(3)
}

#[test]
fn recovers_the_planes_of_a_harmonic_rich_grid_from_a_rough_start() {
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let image = grid(160, &truth, sharp);
    let mask = dots(6, &[]);
    let mut start = truth;
    start[0].c += 0.05;
    start[1].a *= 1.002;
    let fit = fit_dot_field(&image, start, &mask).unwrap();
    assert_planes(&fit, &truth, 1e-6, 1e-8);
    assert!(fit.inlier_fraction > 0.95, "{}", fit.inlier_fraction);
}

#[test]
fn steps_that_shrink_by_pairs_contract() {
    // Judged against the 20 sweeps left after a few: slow when it cannot converge in them.
    let slow = |(last, fastest): (f64, f64), s: f64| {
        (
            sweeps_to_converge(s, last) > 20.0,
            sweeps_to_converge(s, fastest) > 20.0,
        )
    };
    let mut steps = StepHistory::default();
    assert!(steps.contraction(1e-2).is_none());
    // A hair-crossed marker's frozen sweeps: each pair contracts 5×, its second step grows.
    let mut judged = Vec::new();
    for s in [1.3e-2, 2.3e-3, 2.5e-3, 4.4e-4, 5.0e-4, 8.7e-5] {
        if let Some(c) = steps.contraction(s) {
            judged.push(slow(c, s));
        }
        steps.push(s);
    }
    assert_eq!(judged[1], (true, false), "2.5e-3 after 2.3e-3 and 1.3e-2");
    assert!(judged.iter().all(|&(_, slow)| !slow));
    // Steps that stay put are slow either way.
    let mut flat = StepHistory::default();
    for s in [2e-3, 1.9e-3] {
        flat.push(s);
    }
    let c = flat.contraction(1.8e-3).expect("a previous step");
    assert_eq!(slow(c, 1.8e-3), (true, true));
    // A steady contraction by 0.6 (hair across a 4.5-px stamp, stress scene 82938)
    // reaches 1e-5 rad from 1.3e-2 in 15 sweeps: slow, but not given up.
    let mut steady = StepHistory::default();
    for s in [1.3e-2, 1.1e-2] {
        steady.push(s);
    }
    let c = steady.contraction(6.2e-3).expect("a previous step");
    assert_eq!(slow(c, 6.2e-3), (false, false));
    assert!((sweeps_to_converge(1e-3, 0.1) - 2.0).abs() < 1e-12);
    assert_eq!(sweeps_to_converge(1e-3, 1.0), f64::INFINITY);
    assert_eq!(sweeps_to_converge(1e-6, 1.0), 0.0);
}

#[test]
fn fits_the_harmonics_at_the_nyquist_frequency() {
    // An 8-px grid along the pixel axes: the order-4 harmonics fall on the Nyquist
    // frequency, where a harmonic overlaps its own conjugate (sampled as a cosine of fixed
    // phase), and sharp dots give them weight. Demodulated as if they did not overlap,
    // their amplitudes never settled and the fit was refused.
    let truth = planes(0.0, 8.0, [0.4, -1.1]);
    let sharper = |p1: f64, p2: f64| {
        let v = (0.5 + 0.5 * p1.cos()) * (0.5 + 0.5 * p2.cos());
        0.2 + 0.6 * v.powi(6)
    };
    let image = grid(120, &truth, sharper);
    for miss in [0.05, 0.2] {
        let mut start = truth;
        start[0].c += miss;
        start[1].c -= miss;
        start[1].a *= 1.002;
        let fit = fit_dot_field(&image, start, &dots(6, &[])).expect("fit");
        // The harmonics' unseen phases leave up to 1.6e-6 rad of offset.
        assert_planes(&fit, &truth, 5e-6, 1e-8);
    }
}

#[test]
fn ties_the_harmonics_of_point_symmetric_dots_only() {
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let mask = dots(6, &[]);
    let mut start = truth;
    start[0].c += 0.05;
    start[1].c -= 0.03;
    let symmetric = fit_dot_field(&grid(160, &truth, sharp), start, &mask).unwrap();
    assert!(symmetric.harmonics_tied);
    // Skewed dots (a second, offset layer: the harmonics' phases are not the dot centres'):
    // the offsets follow the fundamentals, whose phase is the planes' by construction.
    let skewed = |p1: f64, p2: f64| {
        sharp(p1, p2) + 0.04 * (2.0 * p1 + 0.5).cos() + 0.03 * (p1 + p2 - 0.7).cos()
    };
    let fit = fit_dot_field(&grid(160, &truth, skewed), start, &mask).unwrap();
    assert!(!fit.harmonics_tied);
    assert_planes(&fit, &truth, 1e-6, 1e-8);
}

#[test]
fn a_fit_that_cannot_beat_its_rival_stops_and_one_that_can_is_unchanged() {
    // Sharp dots with 1 % noise (uniform, from a linear congruential sequence): no cell
    // stands out of the others, none is spoiled.
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let image = with_noise(grid(160, &truth, sharp), 0.0346, 12345);
    let mask = dots(6, &[]);
    let mut start = truth;
    start[0].c += 0.05;
    let plain = fit_dot_field(&image, start, &mask).unwrap();
    assert_eq!(plain.spoiled_cells, 0);
    let at = (3.0, -2.0);
    let rival = |std: f64| Rival {
        phase_std: [std / std::f64::consts::SQRT_2; 2],
        at,
    };
    let own = rival(0.0).field_std(&plain.covariance, plain.frame, plain.model_error_ratio);
    assert!(own > 0.0);
    // A window 100 times better: the fit stops once its weights settle.
    assert!(fit_dot_field_against(&image, start, &mask, Some(rival(own / 100.0)), None).is_none());
    // A window it beats, or loses to by less than `HOPELESS`: the fit of `fit_dot_field`.
    // (With free harmonics, on the first sweep on settled weights, σ is twice `own` here.)
    for std in [10.0 * own, own / 2.0, own / 4.0] {
        let against = fit_dot_field_against(&image, start, &mask, Some(rival(std)), None).unwrap();
        assert_eq!(against.planes, plain.planes);
        assert_eq!(against.iterations, plain.iterations);
    }
}

#[test]
fn ignores_a_blotch_and_irregular_nodes() {
    let truth = planes(-0.2, 11.0, [1.0, 2.0]);
    let mut image = grid(180, &truth, sharp);
    // A dark blotch over several dots, and a missing dot at a masked node.
    let (w, _) = (image.width(), image.height());
    for r in 60..80 {
        for c in 100..125 {
            image.pixels_mut()[r * w + c] = 0.05;
        }
    }
    let mask = dots(5, &[(0, 0)]);
    let fit = fit_dot_field(&image, truth, &mask).unwrap();
    // Noise-free, the blotch's rim (the pixels beside it that the biweight keeps, whose
    // residual still stands out) goes with it (`outlier_extents`): nothing is left to
    // make the harmonics' phases inconsistent, they are tied, and the offsets are 5.6e-8
    // and 4.3e-7 rad off. With the rim kept, the phases were inconsistent and the
    // fundamentals alone were 2.3e-5 and 8.8e-5 rad off.
    assert!(fit.harmonics_tied);
    assert_planes(&fit, &truth, 2e-6, 1e-8);
    assert!(fit.inlier_fraction < 0.99, "{}", fit.inlier_fraction);
}

#[test]
fn an_outlier_grows_along_its_edge_and_nowhere_else() {
    // 6 × 4 residuals: a rejected core (9), its edge (4, 3.5) above the threshold 3, a
    // pixel above it but not joined to the core, and a pixel the sweep did not visit.
    let nan = f32::NAN;
    #[rustfmt::skip]
    let residuals = [
        0.0, 0.0, 0.0, 0.0, 0.0, 5.0,
        9.0, -4.0, 3.5, 1.0, 0.0, 0.0,
        0.0, 0.0, 0.0, 2.9, 0.0, 0.0,
        nan, 0.0, 0.0, 0.0, 0.0, 0.0,
    ];
    let grown = outlier_extents(&residuals, 6, 8.0, |_| 3.0);
    let which: Vec<usize> = (0..grown.len()).filter(|&i| grown[i]).collect();
    assert_eq!(which, [6, 7, 8]);
    // Every pixel is an edge where nothing reaches the cut-off: none grows.
    assert!(!outlier_extents(&residuals, 6, 10.0, |_| 0.0).contains(&true));
}

#[test]
fn refuses_a_start_that_is_not_the_grid() {
    let truth = planes(0.1, 10.0, [0.0, 0.0]);
    let image = grid(128, &truth, sharp);
    let mask = dots(4, &[]);
    let wrong = planes(0.1, 13.0, [0.0, 0.0]);
    assert!(fit_dot_field(&image, wrong, &mask).is_none());
}

/// Where `planes` put the lattice node `(0, 0)`, image frame.
fn centre_of(planes: &[PhasePlane; 2]) -> Vector2<f64> {
    let m = Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
    m.try_inverse().unwrap() * Vector2::new(-planes[0].c, -planes[1].c)
}

#[test]
fn a_tilted_field_s_centre_is_where_its_tilt_leaves_it() {
    // Lattice coordinates u = v/(1 − p·v), v linear in the image (the `truth` planes):
    // node (0, 0) is where the truth planes vanish; linear planes fitted to the field miss
    // it by about Σ·p (0.03 period here). Sharp dots (free harmonics) and dots with no
    // harmonics at all.
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let p = Vector2::new(0.0015, -0.001);
    let smooth = |p1: f64, p2: f64| 0.5 + 0.2 * (p1.cos() + p2.cos());
    for dot in [sharp as fn(f64, f64) -> f64, smooth] {
        let image = tilted_grid(160, &truth, p, dot);
        let mask = dots(6, &[]);
        let centre = centre_of(&truth);
        let linear = fit_dot_field_against(&image, truth, &mask, None, None).unwrap();
        let tilted =
            fit_dot_field_against(&image, truth, &mask, None, Some(TiltStart::default())).unwrap();
        let missed = (centre_of(&linear.planes) - centre).norm();
        let left = (centre_of(&tilted.planes) - centre).norm();
        assert!(linear.perspective.is_none());
        let measured = tilted.perspective.unwrap();
        assert!(
            (measured - p).norm() < 0.15 * p.norm(),
            "{measured:?} for {p:?}"
        );
        assert!(tilted.tilt_weight > 0.99, "{}", tilted.tilt_weight);
        assert!(missed > 0.1, "the linear planes' bias: {missed} px");
        assert!(left < 0.1 * missed, "{left} px left of {missed}");
    }
}

/// An `n × n` render of `dot` on the lattice `u = v/(1 − p·v)`, `v` the linear lattice
/// coordinates of `truth` (node (0, 0) where the truth planes vanish).
fn tilted_grid(
    n: usize,
    truth: &[PhasePlane; 2],
    p: Vector2<f64>,
    dot: fn(f64, f64) -> f64,
) -> GreyImage {
    let (cx, cy) = ((n / 2) as f64, (n / 2) as f64);
    let mut px = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let (x, y) = (c as f64 - cx, r as f64 - cy);
            let v = Vector2::new(truth[0].at(x, y), truth[1].at(x, y)) / TAU;
            let u = v / (1.0 - p.dot(&v));
            px.push(dot(TAU * u.x, TAU * u.y) as f32);
        }
    }
    GreyImage::new(n, n, px).unwrap()
}

#[test]
fn a_steep_tilt_is_fitted_in_the_phase_to_its_centre() {
    // p·v up to 0.06 at the field's edge: one linear step leaves the centre a tenth of a
    // pixel off; with the tilt in the phase model the passes converge on it, from the flat
    // fit's step or from a coarse measure of the tilt 20 % off.
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let p = Vector2::new(0.006, -0.004);
    let image = tilted_grid(160, &truth, p, sharp);
    let mask = dots(6, &[]);
    let centre = centre_of(&truth);
    for prior in [Vector2::zeros(), p * 0.8] {
        let tilt = TiltStart {
            centre: [0.0, 0.0],
            perspective: prior,
        };
        let fit = fit_dot_field_against(&image, truth, &mask, None, Some(tilt)).unwrap();
        let measured = fit.perspective.unwrap();
        let off = (centre_of(&fit.planes) - centre).norm();
        assert!(
            (measured - p).norm() < 0.01 * p.norm(),
            "{measured:?} for {p:?}"
        );
        assert!(off < 1e-3, "centre {off:.2e} px off (prior {prior:?})");
    }
}

#[test]
fn an_untilted_field_s_planes_are_not_moved_by_the_tilt_probe() {
    // Sharp dots with 2 % noise: the measured perspective is noise, which moves nothing.
    let truth = planes(0.3, 9.3, [0.4, -1.1]);
    let image = with_noise(grid(160, &truth, sharp), 0.0693, 777);
    let mask = dots(6, &[]);
    let plain = fit_dot_field_against(&image, truth, &mask, None, None).unwrap();
    let probed =
        fit_dot_field_against(&image, truth, &mask, None, Some(TiltStart::default())).unwrap();
    assert!(probed.perspective.is_some());
    assert_eq!(probed.tilt_weight, 0.0);
    for (a, b) in plain.planes.iter().zip(&probed.planes) {
        assert_eq!((a.a, a.b, a.c), (b.a, b.b, b.c));
    }
}

#[test]
fn clearance_keeps_off_missing_dots_and_the_edge() {
    // Dots at nodes −3..=3 without (0, 0): cell (0, 0) is discrepant, and so is every dot
    // cell beyond the edge (node ±4, cell ±8).
    let mask = dots(3, &[(0, 0)]);
    let at = |v1: f64, v2: f64| mask.clearance([v1, v2]);
    let taper = |d: f64| (0.5 * PI * d / MIN_CLEARANCE).sin().powi(2);
    assert_eq!(at(0.2, -0.4), 0.0);
    assert!((at(1.0, 0.0) - taper(0.5)).abs() < 1e-12);
    assert!((at(1.5, 1.5) - taper(2.0f64.sqrt())).abs() < 1e-12);
    assert_eq!(at(2.5, 0.0), 1.0);
    assert_eq!(at(4.0, 4.0), 1.0);
    assert!((at(6.0, 2.0) - taper(1.5)).abs() < 1e-12);
    assert_eq!(at(7.6, 2.0), 0.0);
}

#[test]
fn layout_weight_is_a_partition_of_unity() {
    let mask = dots(3, &[]);
    let plain = NodeWeights::new(&mask, &[]);
    let weight = |u: [f64; 2]| plain.weight(u, u.map(|v| (PI * v).cos())).0;
    for &(u1, u2) in &[(0.0, 0.0), (0.3, -1.7), (2.49, 1.01), (-2.2, 2.9)] {
        assert!((weight([u1, u2]) - 1.0).abs() < 1e-12);
    }
    assert_eq!(weight([4.0, 0.0]), 0.0);
    assert!((weight([3.5, 0.0]) - 0.5).abs() < 1e-12);
    // Lower weight near a node whose robust weight is 0, none at it.
    let nodes: Vec<f64> = (0..mask.len())
        .map(|i| if i == 24 { 0.0 } else { 1.0 })
        .collect();
    let robust = NodeWeights::new(&mask, &nodes);
    let at = |u: [f64; 2]| robust.weight(u, u.map(|v| (PI * v).cos())).1;
    assert_eq!(at([0.0, 0.0]), 0.0);
    assert!((at([0.5, 0.0]) - 0.5).abs() < 1e-12 && at([1.0, 0.0]) == 1.0);
}

#[test]
fn carried_weights_move_with_the_nodes_to_whole_pixels() {
    // A 4×3 box at frame position (−2, −1) whose nodes sat at (0, 0); weights 0..12.
    let carried = CarriedWeights {
        values: (0..12).map(|v| v as f32).collect(),
        width: 4,
        origin_from_nodes: Vector2::new(-2.0, -1.0),
    };
    // The next box: same size, one pixel right (its pixel (0, 0) at frame (−1, −1)), the
    // nodes moved 1.2 px right and 0.3 px down.
    let field = FieldBox {
        cols: 9..13,
        rows: 9..12,
        center: (10.0, 10.0),
        frame: (0.0, 0.0, 2.0),
        clearance: Vec::new(),
        spans: Vec::new(),
        warp: None,
    };
    let moved = carried.moved_into(&field, Vector2::new(1.2, 0.3));
    // Shift (−1, −1) − (1.2, 0.3) − (−2, −1) = (−0.2, −0.3): rounded to none; the box moved
    // with the nodes, so each pixel keeps its own weight.
    assert_eq!(moved, carried.values);
    // The nodes moved two pixels right instead: each pixel takes the weight from one pixel
    // to its left (the box moved one), and the first column is new (NaN).
    let moved = carried.moved_into(&field, Vector2::new(2.0, 0.0));
    for (k, w) in moved.iter().enumerate() {
        let (row, col) = (k / 4, k % 4);
        if col == 0 {
            assert!(w.is_nan(), "pixel {k}: {w}");
        } else {
            assert_eq!(*w, carried.values[row * 4 + col - 1], "pixel {k}");
        }
    }
}
