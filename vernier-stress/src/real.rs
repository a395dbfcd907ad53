//! The real images of the data folder under the suite's degradations: the yardstick for real
//! marker appearance (printed or etched finders, faded and dusty dots, real optics and
//! sensors) that renders cannot give.
//!
//! Each scene is one real HP code or stamp image, turned by a random angle and magnified by
//! 0.7–1 (bilinear, 2 × 2 supersampled, onto a canvas that holds the whole turned image),
//! then degraded as a stress scene of its category is ([`Degradations::draw`], the same
//! severities): a tilt up to 25°, added blur, noise, JPEG, illumination, low contrast (the
//! markers' own range of grey squeezed to 10–20 % of full scale), a colour cast, or 2–4 of
//! them. One category of its own, `tone`, applies a tone curve
//! `v ↦ v^γ`, γ 0.4–2.5 (a camera's gamma encoding or its absence). Clutter, dust and hair are
//! left out: the images carry their own.
//!
//! There is no ground truth: the markers a scene must give are those that the detector finds
//! on the image as it is, with the IDs the data README and the tests name, moved by the
//! scene's homography. A marker is *found* when a detection with its ID lies within half a
//! period of where its clean detection moved (a detection further off, up to four periods,
//! has misnumbered the grid: *wrong*, as is another ID there); a detection anywhere else is
//! *false*, except on a marker the image holds but cannot give for certain (listed per case,
//! [`RealCase::others`]), where one of the case's IDs is allowed. The added blur is the
//! drawn one capped at a fifth of the finest period (the images already carry their own
//! optics, σ ≈ 0.5–1 px; renders cap the total at a quarter).

use crate::data::data_dir;
use crate::degrade::{apply_illumination, finish, log_uniform, Degradation, Degradations};
use crate::error::{Result, StressError};
use crate::geometry::Homography;
use crate::raster::{gaussian_blur, warp_into, Plane};
use nalgebra::{Matrix3, Vector2};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use std::f64::consts::TAU;
use std::path::PathBuf;
use vernier::detector::{DetectorSettings, MarkerKind as DetectorKind};
use vernier::{Detector, GreyImage, MarkerPose};

/// Period typed for every real image (pattern units; the HP code and stamp tests' setting).
pub const REAL_PERIOD: f64 = 15.5;

/// One real image and what it must give.
#[derive(Clone, Copy, Debug)]
pub struct RealCase {
    /// Path under the data folder.
    pub file: &'static str,
    /// HP code width `W` (typed with `--code-size`), `None` for a stamp image.
    pub code_size: Option<usize>,
    /// Stamp bitmaps typed with `--bitmap`, in ID order (stamp images).
    pub bitmaps: &'static [&'static str],
    /// The IDs of the markers the image holds (as the data README and the tests name them).
    pub ids: &'static [u64],
    /// Markers the clean image must give (all but the physically ambiguous ones).
    pub required: usize,
    /// Image positions `(col, row)` of markers the image holds but cannot give for certain
    /// (an ID dot half hidden, a dot column cut by the part's edge): a detection there with
    /// one of [`RealCase::ids`] is neither found nor false.
    pub others: &'static [(f64, f64)],
}

const fn hp(file: &'static str, w: usize, ids: &'static [u64], required: usize) -> RealCase {
    RealCase {
        file,
        code_size: Some(w),
        bitmaps: &[],
        ids,
        required,
        others: &[],
    }
}

/// The HP code and stamp images of the data folder, each physical scene once: `code18_90.jpg`
/// and `code18_180.jpg` (turned copies of `code18.jpg`) are left out, and the sequence
/// `Image96`–`105` is represented by two of its frames.
pub const REAL_CASES: &[RealCase] = &[
    hp("hpcode/HPCodeImage_20um.png", 33, &[0, 1], 2),
    hp("hpcode/Image96.png", 33, &[0, 1], 2),
    hp("hpcode/Image100.png", 33, &[0, 1], 2),
    hp("hpcode/code17.jpg", 37, &[0], 1),
    hp("hpcode/code18.jpg", 37, &[1], 1),
    hp("hpcode/code19.png", 33, &[0], 1),
    RealCase {
        others: &[(690.5, 418.5)],
        ..hp("hpcode/code21.jpg", 33, &[0, 0], 1)
    },
    RealCase {
        others: &[(495.3, 165.3)],
        ..hp("hpcode/code22.tif", 33, &[0, 0], 1)
    },
    hp("hpcode/code31.jpg", 37, &[0, 1, 2], 3),
    RealCase {
        file: "stamp/stampPatternImage_15um.jpg",
        code_size: None,
        bitmaps: &["stampD", "stampG"],
        ids: &[0, 1],
        required: 2,
        others: &[],
    },
    RealCase {
        file: "stamp/stamp1.png",
        code_size: None,
        bitmaps: &["stamp69x69"],
        ids: &[0],
        required: 1,
        others: &[],
    },
];

/// A real scene's category: the suite's pixel and geometry degradations, a tone curve, or a
/// mix; every scene is also turned and magnified.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RealCategory {
    /// Turned and magnified only.
    Turned,
    /// One of the suite's degradations.
    Only(Degradation),
    /// A tone curve `v^γ`, γ 0.4–2.5.
    Tone,
    /// 2–4 of the others.
    Combined,
}

/// Whether a suite degradation applies to a real image as it is (clutter, dust and hair are
/// the images' own).
fn applies_to_real(d: Degradation) -> bool {
    !matches!(d, Degradation::Clutter | Degradation::DustHair)
}

impl RealCategory {
    /// Every category, in table order.
    pub const ALL: [RealCategory; 10] = [
        RealCategory::Turned,
        RealCategory::Only(Degradation::Perspective),
        RealCategory::Only(Degradation::Blur),
        RealCategory::Only(Degradation::Noise),
        RealCategory::Only(Degradation::Jpeg),
        RealCategory::Only(Degradation::Illumination),
        RealCategory::Only(Degradation::LowContrast),
        RealCategory::Only(Degradation::ColourCast),
        RealCategory::Tone,
        RealCategory::Combined,
    ];

    /// Lower-case name (`turned`, `perspective`, …, `tone`, `combined`).
    pub fn name(self) -> &'static str {
        match self {
            RealCategory::Turned => "turned",
            RealCategory::Only(d) => d.name(),
            RealCategory::Tone => "tone",
            RealCategory::Combined => "combined",
        }
    }

    /// Parses a name given by [`RealCategory::name`].
    pub fn parse(s: &str) -> Option<RealCategory> {
        RealCategory::ALL.into_iter().find(|c| c.name() == s)
    }

    /// The suite degradations of one scene and whether it gets a tone curve.
    fn draw(self, rng: &mut SmallRng) -> (Vec<Degradation>, bool) {
        match self {
            RealCategory::Turned => (Vec::new(), false),
            RealCategory::Only(d) => (vec![d], false),
            RealCategory::Tone => (Vec::new(), true),
            RealCategory::Combined => {
                // The tone curve counts as one of the 2–4.
                let mut all: Vec<Option<Degradation>> = Degradation::ALL
                    .into_iter()
                    .filter(|&d| applies_to_real(d))
                    .map(Some)
                    .collect();
                all.push(None);
                let k = rng.random_range(2..=4);
                let mut chosen = Vec::with_capacity(k);
                for _ in 0..k {
                    chosen.push(all.remove(rng.random_range(0..all.len())));
                }
                let tone = chosen.contains(&None);
                let mut kinds: Vec<Degradation> = chosen.into_iter().flatten().collect();
                kinds.sort();
                (kinds, tone)
            }
        }
    }
}

/// Where a marker of the clean image must appear in a scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Expected {
    /// The marker's ID.
    pub id: u64,
    /// Its centre, scene image pixels `(col, row)`.
    pub position: Vector2<f64>,
    /// Its grid period there, scene pixels.
    pub period_px: f64,
}

/// A real image ready to be degraded: its pixels, detector settings and clean detections.
pub struct RealImage {
    /// The case it comes from.
    pub case: RealCase,
    /// The settings a user types for it.
    pub settings: DetectorSettings,
    plane: Plane,
    /// Median grey level: the canvas outside the turned image.
    fill: f32,
    /// The 2nd and 98th percentiles of the markers' own pixels (dots and background).
    marker_levels: (f32, f32),
    /// The markers of the clean image (image pixels).
    clean: Vec<Expected>,
}

impl RealImage {
    /// Loads `case` from the data folder and detects its markers as they are. Errors when the
    /// image is missing or its clean detection does not give the case's required markers with
    /// its IDs (the tests check the same).
    pub fn load(case: RealCase) -> Result<Self> {
        let dir = data_dir()?;
        let image = GreyImage::open(dir.join(case.file))
            .map_err(|e| StressError::new(format!("{}: {e}", case.file)))?;
        let settings = settings_for(&case, &dir);
        let found = detect_once(&settings, &image)
            .map_err(|e| StressError::new(format!("{}: {e}", case.file)))?;
        let clean: Vec<Expected> = found
            .iter()
            .filter(|m| !near_other(&case, m.origin_px, &Homography::identity()))
            .map(|m| Expected {
                id: m.id,
                position: m.origin_px,
                period_px: REAL_PERIOD / m.measured_pixel_size,
            })
            .collect();
        if clean.len() < case.required || clean.iter().any(|e| !case.ids.contains(&e.id)) {
            return Err(StressError::new(format!(
                "{}: the clean image gives IDs {:?}, the case needs {} of {:?}",
                case.file,
                clean.iter().map(|e| e.id).collect::<Vec<_>>(),
                case.required,
                case.ids
            )));
        }
        let plane = Plane {
            width: image.width(),
            height: image.height(),
            data: image.pixels().to_vec(),
        };
        let mut sorted = plane.data.clone();
        sorted.sort_unstable_by(f32::total_cmp);
        let fill = percentile(&sorted, 0.5);
        let marker_levels = marker_levels(&plane, &case, &clean);
        Ok(RealImage {
            case,
            settings,
            plane,
            fill,
            marker_levels,
            clean,
        })
    }
}

/// One degraded view of a real image.
pub struct RealScene {
    /// Its category.
    pub category: RealCategory,
    /// The seed that reproduces it.
    pub seed: u64,
    /// The scene image.
    pub grey: GreyImage,
    /// Where each clean marker must appear.
    pub expected: Vec<Expected>,
    /// Clean image pixels → scene pixels.
    pub homography: Homography,
    /// The drawn severities, one line.
    pub description: String,
}

/// Salt of a real scene's random stream (independent of the render suite's).
const SALT: u64 = 0x7265_616c_2d76_3031;

/// Generates the view `seed` of `real` in `category`.
pub fn generate(real: &RealImage, category: RealCategory, seed: u64) -> Result<RealScene> {
    generate_harsher(real, category, seed, 1.0)
}

/// [`generate`] with every drawn severity made `severity` times harsher
/// ([`Degradations::harsher`]; 1 is [`generate`]'s view): also the shrinking (magnification
/// `m^severity`), the blur's cap (`0.2·severity` of the finest period, at most 0.3), the
/// markers' contrast under low contrast (divided by it) and the tone curve's exponent (raised
/// to it). The random stream is the same at every severity.
pub fn generate_harsher(
    real: &RealImage,
    category: RealCategory,
    seed: u64,
    severity: f64,
) -> Result<RealScene> {
    let mut rng = SmallRng::seed_from_u64(seed ^ SALT);
    let (kinds, tone) = category.draw(&mut rng);
    let d = Degradations::draw(&kinds, &mut rng).harsher(severity);
    let angle = rng.random_range(0.0..TAU);
    let magnification = log_uniform(&mut rng, 0.7, 1.0).powf(severity);
    let (homography, size) = view_homography(&real.plane, angle, magnification, &d)?;
    let mut plane = warp_into(&real.plane, &homography, 2, real.fill, size);
    let mut parts = vec![format!(
        "turned {:.1}°, magnified {magnification:.2}",
        angle.to_degrees()
    )];
    let finest = real
        .clean
        .iter()
        .map(|e| e.period_px * magnification)
        .fold(f64::INFINITY, f64::min);
    if kinds.contains(&Degradation::Blur) {
        let sigma = d.blur_sigma.min((0.2 * severity).min(0.3) * finest);
        gaussian_blur(&mut plane.data, plane.width, plane.height, sigma);
        parts.push(format!("blur σ {sigma:.2} px added"));
    }
    if d.low_contrast {
        let c = rng.random_range(0.10..0.20) / severity;
        let offset = rng.random_range(0.0..1.0 - c);
        let (lo, hi) = real.marker_levels;
        let gain = c as f32 / (hi - lo).max(1e-6);
        for v in plane.data.iter_mut() {
            *v = offset as f32 + (*v - lo) * gain;
        }
        parts.push(format!("markers' contrast {c:.2} from {offset:.2}"));
    }
    if tone {
        let gamma = log_uniform(&mut rng, 0.4, 2.5).powf(severity);
        for v in plane.data.iter_mut() {
            *v = v.clamp(0.0, 1.0).powf(gamma as f32);
        }
        parts.push(format!("tone γ {gamma:.2}"));
    }
    if let Some(illumination) = &d.illumination {
        apply_illumination(&mut plane, illumination);
    }
    let mut described = d.describe();
    // The suite's base optics line does not apply (no blur is added but the drawn one).
    if let Some(rest) = described.split_once(", ") {
        described = rest.1.to_string();
    } else {
        described.clear();
    }
    if !described.is_empty() {
        parts.push(described);
    }
    let grey = finish(&plane, &d, &mut rng)?;
    let expected = real
        .clean
        .iter()
        .filter_map(|e| {
            let position = homography.apply(e.position)?;
            let scale = homography.jacobian(e.position)?.determinant().abs().sqrt();
            Some(Expected {
                position,
                period_px: e.period_px * scale,
                ..*e
            })
        })
        .collect();
    Ok(RealScene {
        category,
        seed,
        grey,
        expected,
        homography,
        description: parts.join(", "),
    })
}

/// The view's homography (image pixels → scene pixels) and the canvas that holds the whole
/// viewed image: turned by `angle` and magnified about the image centre, then tilted about it
/// as `d` draws.
fn view_homography(
    plane: &Plane,
    angle: f64,
    magnification: f64,
    d: &Degradations,
) -> Result<(Homography, (usize, usize))> {
    let (w, h) = (plane.width as f64, plane.height as f64);
    let (s, c) = angle.sin_cos();
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let k = magnification;
    // p ↦ k·R·(p − centre), the centre at the origin.
    let turn = Matrix3::new(
        k * c,
        -k * s,
        -k * (c * cx - s * cy),
        k * s,
        k * c,
        -k * (s * cx + c * cy),
        0.0,
        0.0,
        1.0,
    );
    let tilt = match d.perspective {
        Some(t) => {
            let focal = t.focal_diagonals * w.hypot(h) * k;
            Homography::tilt(Vector2::zeros(), t.angle, t.axis, focal)
                .ok_or_else(|| StressError::new("tilt homography"))?
                .matrix()
        }
        None => Matrix3::identity(),
    };
    let centred = tilt * turn;
    let centred_map = Homography::from_matrix(centred)
        .ok_or_else(|| StressError::new("singular view homography"))?;
    let corners = [
        (0.0, 0.0),
        (w - 1.0, 0.0),
        (0.0, h - 1.0),
        (w - 1.0, h - 1.0),
    ];
    let mut lo = Vector2::repeat(f64::INFINITY);
    let mut hi = Vector2::repeat(f64::NEG_INFINITY);
    for (x, y) in corners {
        let q = centred_map
            .apply(Vector2::new(x, y))
            .ok_or_else(|| StressError::new("image corner beyond the horizon"))?;
        lo = lo.inf(&q);
        hi = hi.sup(&q);
    }
    let shift = Matrix3::new(1.0, 0.0, -lo.x, 0.0, 1.0, -lo.y, 0.0, 0.0, 1.0);
    let homography = Homography::from_matrix(shift * centred)
        .ok_or_else(|| StressError::new("singular view homography"))?;
    let size = (
        (hi.x - lo.x).ceil() as usize + 1,
        (hi.y - lo.y).ceil() as usize + 1,
    );
    Ok((homography, size))
}

/// The value at fraction `q` of `sorted` (ascending, not empty).
fn percentile(sorted: &[f32], q: f64) -> f32 {
    sorted[((sorted.len().max(1) - 1) as f64 * q).round() as usize]
}

/// The 2nd and 98th percentiles of the pixels within a third of a marker's side from the
/// centre of each clean marker: the range that low contrast squeezes to 10–20 % of full scale,
/// as the suite's renders have it between dots and background (the image's own range, with
/// paper, metal and shadows, is often several times the markers').
fn marker_levels(plane: &Plane, case: &RealCase, clean: &[Expected]) -> (f32, f32) {
    // Periods across a marker: W/2 for an HP code, the bitmap's 69 cells / 2 for a stamp.
    let side_periods = case.code_size.map_or(34.5, |w| w as f64 / 2.0);
    let mut values = Vec::new();
    for e in clean {
        let r = side_periods * e.period_px / 3.0;
        let rows =
            (e.position.y - r).max(0.0) as usize..((e.position.y + r) as usize).min(plane.height);
        for row in rows {
            let cols = (e.position.x - r).max(0.0) as usize
                ..((e.position.x + r) as usize).min(plane.width);
            values.extend_from_slice(
                &plane.data[row * plane.width + cols.start..row * plane.width + cols.end],
            );
        }
    }
    if values.is_empty() {
        return (0.0, 1.0);
    }
    values.sort_unstable_by(f32::total_cmp);
    (percentile(&values, 0.02), percentile(&values, 0.98))
}

/// The settings a user types for `case`: marker type, period, code size or bitmaps.
fn settings_for(case: &RealCase, dir: &std::path::Path) -> DetectorSettings {
    match case.code_size {
        Some(w) => DetectorSettings {
            pattern_type: DetectorKind::HpCode,
            period: Some(REAL_PERIOD),
            code_size: Some(w),
            ..Default::default()
        },
        None => DetectorSettings {
            pattern_type: DetectorKind::Stamp,
            period: Some(REAL_PERIOD),
            bitmaps: case
                .bitmaps
                .iter()
                .map(|b| dir.join("layouts").join(format!("{b}.png")))
                .collect::<Vec<PathBuf>>(),
            ..Default::default()
        },
    }
}

fn detect_once(settings: &DetectorSettings, image: &GreyImage) -> vernier::Result<Vec<MarkerPose>> {
    Detector::new(settings.to_config()?)?.detect(image)
}

/// True when `position` (scene pixels) is within four periods of one of the case's other
/// markers moved by `homography`.
fn near_other(case: &RealCase, position: Vector2<f64>, homography: &Homography) -> bool {
    case.others.iter().any(|&(x, y)| {
        homography
            .apply(Vector2::new(x, y))
            .is_some_and(|q| (q - position).norm() < OTHER_RADIUS_PX * scale_at(homography, x, y))
    })
}

/// Radius around an ambiguous marker within which a detection is its, image pixels.
const OTHER_RADIUS_PX: f64 = 60.0;

fn scale_at(homography: &Homography, x: f64, y: f64) -> f64 {
    homography
        .jacobian(Vector2::new(x, y))
        .map_or(1.0, |j| j.determinant().abs().sqrt())
}

/// Periods within which a detection belongs to an expected marker.
const MATCH_PERIODS: f64 = 4.0;
/// Periods within which it is that marker's right grid node (beyond: misnumbered).
const RIGHT_NODE_PERIODS: f64 = 0.5;

/// What one scene gave.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RealResult {
    /// Markers the scene must give.
    pub expected: usize,
    /// Found with their ID at their place.
    pub found: usize,
    /// An expected marker read with another ID, or more than half a period off its place.
    pub wrong: usize,
    /// Detections on no marker of the image.
    pub false_markers: usize,
    /// Distance of each found marker from its clean detection moved by the view, pixels.
    pub deviations_px: Vec<f64>,
    /// The scene could not be detected (error message).
    pub error: Option<String>,
}

/// Scores the detections of `scene` (of `real`).
pub fn evaluate(
    real: &RealImage,
    scene: &RealScene,
    detections: std::result::Result<&[MarkerPose], String>,
) -> RealResult {
    let mut result = RealResult {
        expected: scene.expected.len(),
        ..Default::default()
    };
    let detections = match detections {
        Ok(d) => d,
        Err(e) => {
            result.error = Some(e);
            return result;
        }
    };
    let mut claimed = vec![false; detections.len()];
    for e in &scene.expected {
        let distance = |d: &MarkerPose| (d.origin_px - e.position).norm() / e.period_px;
        let near: Vec<usize> = (0..detections.len())
            .filter(|&i| distance(&detections[i]) < MATCH_PERIODS)
            .collect();
        for &i in &near {
            claimed[i] = true;
        }
        let best = near
            .iter()
            .filter(|&&i| detections[i].id == e.id)
            .min_by(|&&a, &&b| distance(&detections[a]).total_cmp(&distance(&detections[b])));
        match best {
            Some(&i) if distance(&detections[i]) < RIGHT_NODE_PERIODS => {
                result.found += 1;
                result
                    .deviations_px
                    .push((detections[i].origin_px - e.position).norm());
            }
            _ if near.is_empty() => {}
            _ => result.wrong += 1,
        }
    }
    for (d, claimed) in detections.iter().zip(claimed) {
        let allowed =
            near_other(&real.case, d.origin_px, &scene.homography) && real.case.ids.contains(&d.id);
        if !claimed && !allowed {
            result.false_markers += 1;
        }
    }
    result
}

/// Seeds of the real scenes: `draws` per image and category from `base`, in the order
/// (image, category, draw). `cases[i]` is the index in [`REAL_CASES`] of image `i`: a scene's
/// seed depends on its case, category and draw only, not on which images are selected.
pub fn real_seeds(base: u64, cases: &[usize], draws: usize) -> Vec<(usize, RealCategory, u64)> {
    let mut out = Vec::new();
    for (image, &case) in cases.iter().enumerate() {
        for (k, &category) in RealCategory::ALL.iter().enumerate() {
            for draw in 0..draws {
                let seed = base + ((case * RealCategory::ALL.len() + k) * draws + draw) as u64;
                out.push((image, category, seed));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::degrade::Tilt;

    #[test]
    fn every_view_holds_the_whole_image() {
        let plane = Plane::filled(120, 70, 0.5);
        let mut rng = SmallRng::seed_from_u64(3);
        for k in 0..20 {
            let mut d = Degradations::draw(&[], &mut rng);
            if k % 2 == 1 {
                d.perspective = Some(Tilt {
                    angle: 0.4,
                    axis: 0.3 * k as f64,
                    focal_diagonals: 1.5,
                });
            }
            let (h, (w, ht)) = view_homography(&plane, 0.37 * k as f64, 0.7, &d).unwrap();
            for (x, y) in [
                (0.0, 0.0),
                (119.0, 0.0),
                (0.0, 69.0),
                (119.0, 69.0),
                (60.0, 35.0),
            ] {
                let q = h.apply(Vector2::new(x, y)).unwrap();
                assert!(q.x > -1e-6 && q.y > -1e-6, "{k}: {q:?}");
                assert!(
                    q.x < w as f64 && q.y < ht as f64,
                    "{k}: {q:?} in {w} × {ht}"
                );
            }
        }
    }

    #[test]
    fn seeds_do_not_depend_on_the_images_selected() {
        let all = real_seeds(7, &[0, 1, 2], 3);
        let one = real_seeds(7, &[2], 3);
        let third: Vec<_> = all
            .iter()
            .filter(|s| s.0 == 2)
            .map(|s| (s.1, s.2))
            .collect();
        let alone: Vec<_> = one.iter().map(|s| (s.1, s.2)).collect();
        assert_eq!(third, alone);
        let mut seeds: Vec<u64> = all.iter().map(|s| s.2).collect();
        seeds.sort();
        seeds.dedup();
        assert_eq!(seeds.len(), 3 * RealCategory::ALL.len() * 3);
    }
}
