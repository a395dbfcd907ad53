//! Deterministic scenes from a `u64` seed: markers at random poses, one degradation category,
//! the final [`GreyImage`] and its ground truth.
//!
//! The seed alone fixes everything: its family is `FAMILIES[(seed / 11) % 2]` and its category
//! `Category::ALL[seed % 11]`, so consecutive seeds cycle through every category of both
//! families and any scene is reproduced from its seed.
//!
//! Image formation, in physical order: markers (area-sampled renders of the `vernier`
//! layouts) and clutter on the marker plane with the optical blur → grey levels (polarity,
//! contrast) → dust and hair on the sample → perspective warp → illumination → sensor (colour
//! cast, noise) → file (JPEG or quantisation).

use crate::bound::{self, PositionBound};
use crate::clutter::Clutter;
use crate::data::StampSet;
use crate::degrade::{
    apply_gain, finish, illumination_gain, log_uniform, Degradation, Degradations,
};
use crate::error::{Result, StressError};
use crate::geometry::{rotate, Homography, OrientedRect};
use crate::markers::{Expectation, Family, MarkerKind, Placed, TruthMarker, PERIOD, STAMP_CELLS};
use crate::raster::{add_marker, warp, Plane};
use nalgebra::Vector2;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use std::f64::consts::{PI, SQRT_2, TAU};
use std::time::Instant;
use vernier::detector::{DetectorSettings, MarkerKind as DetectorKind};
use vernier::{GreyImage, Polarity};

/// Largest image side, pixels (keeps the time per scene bounded).
pub const MAX_SIDE: usize = 1600;

/// Share of the scene's HP codes drawn seen from the back (mirrored: the detector must say so,
/// `gamma = −π`, and read the same ID). Not ID 0, which is symmetric about its diagonal and
/// reads from the back as from the front, turned; not stamps, whose `+` glyph is symmetric
/// too.
const MIRRORED_FRACTION: f64 = 0.25;

/// A degradation category: a clean scene, one degradation, or 2–4 of them combined.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Category {
    /// Optics blur 0.4–0.7 px, 16 bits, nothing else.
    Clean,
    /// One degradation.
    Only(Degradation),
    /// 2–4 distinct degradations drawn at random.
    Combined,
}

impl Category {
    /// Every category, in seed order.
    pub const ALL: [Category; 11] = [
        Category::Clean,
        Category::Only(Degradation::Perspective),
        Category::Only(Degradation::Blur),
        Category::Only(Degradation::Noise),
        Category::Only(Degradation::Jpeg),
        Category::Only(Degradation::Illumination),
        Category::Only(Degradation::LowContrast),
        Category::Only(Degradation::ColourCast),
        Category::Only(Degradation::Clutter),
        Category::Only(Degradation::DustHair),
        Category::Combined,
    ];

    /// Short name (`clean`, `perspective`, …, `combined`).
    pub fn name(self) -> &'static str {
        match self {
            Category::Clean => "clean",
            Category::Combined => "combined",
            Category::Only(d) => d.name(),
        }
    }

    /// Parses a name given by [`Category::name`].
    pub fn parse(s: &str) -> Option<Category> {
        Category::ALL.into_iter().find(|c| c.name() == s)
    }

    /// The degradations of a scene of this category (random for `Combined`).
    fn degradations(self, rng: &mut SmallRng) -> Vec<Degradation> {
        match self {
            Category::Clean => Vec::new(),
            Category::Only(d) => vec![d],
            Category::Combined => {
                let mut all = Degradation::ALL.to_vec();
                let k = rng.random_range(2..=4);
                let mut chosen = Vec::with_capacity(k);
                for _ in 0..k {
                    chosen.push(all.remove(rng.random_range(0..all.len())));
                }
                chosen.sort();
                chosen
            }
        }
    }
}

/// What a seed stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneSpec {
    /// The seed.
    pub seed: u64,
    /// Marker family under test.
    pub family: Family,
    /// Degradation category.
    pub category: Category,
}

impl SceneSpec {
    /// Family and category of `seed` (see the module docs).
    pub fn from_seed(seed: u64) -> Self {
        let n = Category::ALL.len() as u64;
        SceneSpec {
            seed,
            family: Family::ALL[((seed / n) % 2) as usize],
            category: Category::ALL[(seed % n) as usize],
        }
    }
}

/// A generated scene.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Seed, family, category.
    pub spec: SceneSpec,
    /// The image given to the detector.
    pub image: GreyImage,
    /// Every marker drawn (expected, ignored and foreign).
    pub truth: Vec<TruthMarker>,
    /// Dot polarity of the scene's markers (not given to the detector: its default finds it).
    pub polarity: Polarity,
    /// HP code width given to the detector (`--code-size`), `None` for stamp scenes.
    pub code_size: Option<usize>,
    /// The degradations and their severities.
    pub degradations: Degradations,
    /// Human-readable notes (grey levels, clutter items, dust, hair).
    pub notes: Vec<String>,
    /// Generation time per stage, milliseconds.
    pub timings: Vec<(&'static str, f64)>,
}

impl Scene {
    /// The detector settings a CLI user would give for this scene: marker type, period, and
    /// code size (HP) or the four bitmaps (stamp); everything else default (polarity
    /// included: found per marker).
    pub fn detector_settings(&self, stamps: &StampSet) -> DetectorSettings {
        match self.spec.family {
            Family::HpCode => DetectorSettings {
                pattern_type: DetectorKind::HpCode,
                period: Some(PERIOD),
                code_size: self.code_size,
                ..Default::default()
            },
            Family::Stamp => DetectorSettings {
                pattern_type: DetectorKind::Stamp,
                period: Some(PERIOD),
                bitmaps: stamps.paths.clone(),
                ..Default::default()
            },
        }
    }
}

/// Range of image periods (pixels per physical period) of a family.
fn period_range(family: Family) -> (f64, f64) {
    match family {
        Family::HpCode => (4.0, 40.0),
        Family::Stamp => (4.0, 12.0),
    }
}

/// Scene generator: holds the stamp bitmaps; any number of threads may share it.
#[derive(Clone, Debug)]
pub struct Generator {
    stamps: StampSet,
    /// Share of HP codes seen from the back ([`MIRRORED_FRACTION`] by default).
    mirrored_fraction: f64,
    /// Compute each marker's Cramér–Rao bound (or JPEG model) where the scene has one (off
    /// by default: it costs eight renders of the marker).
    position_bounds: bool,
}

/// Where things may go: image size, homography, what is already placed.
struct Layout {
    width: usize,
    height: usize,
    homography: Homography,
    markers: Vec<Placed>,
    clutter: Vec<Clutter>,
    /// Distance kept from the image border, pixels.
    margin: f64,
}

impl Layout {
    fn inside(&self, p: Vector2<f64>, margin: f64) -> bool {
        p.x >= margin
            && p.y >= margin
            && p.x <= self.width as f64 - 1.0 - margin
            && p.y <= self.height as f64 - 1.0 - margin
    }

    /// True when `rect` (plane) lies inside the plane raster and its image inside the frame,
    /// both with `margin`.
    fn fits(&self, rect: &OrientedRect, margin: f64) -> bool {
        rect.corners().iter().all(|&c| {
            self.inside(c, margin)
                && self
                    .homography
                    .apply(c)
                    .is_some_and(|q| self.inside(q, margin))
        })
    }

    /// True when `rect`'s image reaches into the frame (at least its centre is visible).
    fn visible(&self, rect: &OrientedRect) -> bool {
        self.homography
            .apply(rect.center)
            .is_some_and(|q| self.inside(q, 0.0))
            && self.inside(rect.center, 0.0)
    }

    /// One try at placing a `kind` marker of half side `half_side` pixels at a random
    /// angle and position, `gap` clear of everything placed; `None` where it does not fit.
    fn try_place(
        &self,
        kind: MarkerKind,
        half_side: f64,
        pixel_size: f64,
        gap: f64,
        rng: &mut SmallRng,
    ) -> Option<Placed> {
        let (width, height, margin) = (self.width, self.height, self.margin);
        let alpha = rng.random_range(-PI..PI);
        let rect = OrientedRect::square(Vector2::zeros(), half_side, alpha);
        let bh = rect.bounding_half() + Vector2::repeat(margin);
        if 2.0 * bh.x > width as f64 - 1.0 || 2.0 * bh.y > height as f64 - 1.0 {
            return None;
        }
        let origin = Vector2::new(
            rng.random_range(bh.x..width as f64 - 1.0 - bh.x),
            rng.random_range(bh.y..height as f64 - 1.0 - bh.y),
        );
        let m = Placed {
            kind,
            origin,
            alpha,
            pixel_size,
            mirrored: false,
            expectation: Expectation::Expected,
        };
        let fp = m.footprint();
        (self.fits(&fp, margin) && self.is_free(&fp, gap)).then_some(m)
    }

    /// True when `rect` keeps `clearance` from every marker and clutter item.
    fn is_free(&self, rect: &OrientedRect, clearance: f64) -> bool {
        let r = rect.expanded(clearance);
        self.markers.iter().all(|m| !r.overlaps(&m.footprint()))
            && self.clutter.iter().all(|c| !r.overlaps(&c.footprint()))
    }
}

impl Generator {
    /// A generator reading the stamp bitmaps from `data_dir`.
    pub fn new(data_dir: &std::path::Path) -> Result<Self> {
        Ok(Generator {
            stamps: StampSet::load(data_dir, PERIOD)?,
            mirrored_fraction: MIRRORED_FRACTION,
            position_bounds: false,
        })
    }

    /// The same generator, also computing the Cramér–Rao bound of each marker's position
    /// (or its JPEG model) where the scene has one ([`bound::kind`];
    /// [`TruthMarker::position_bound`]). The scenes are the same: the bound draws nothing.
    pub fn with_position_bounds(self) -> Self {
        Generator {
            position_bounds: true,
            ..self
        }
    }

    /// The same generator drawing no marker seen from the back: the scenes as they were
    /// before mirrored markers were drawn (regression seeds picked then reproduce what they
    /// were picked for).
    pub fn without_mirrored_markers(self) -> Self {
        Generator {
            mirrored_fraction: 0.0,
            ..self
        }
    }

    /// A generator on [`crate::data::data_dir`].
    pub fn from_env() -> Result<Self> {
        Self::new(&crate::data::data_dir()?)
    }

    /// The stamp bitmaps (their paths go into the detector settings).
    pub fn stamps(&self) -> &StampSet {
        &self.stamps
    }

    /// The scene of `seed`.
    pub fn generate(&self, seed: u64) -> Result<Scene> {
        let spec = SceneSpec::from_seed(seed);
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x7374_7265_7373_2d31);
        let mut laps = Laps::start();
        let kinds = spec.category.degradations(&mut rng);
        let mut deg = Degradations::draw(&kinds, &mut rng);
        let polarity = if rng.random_bool(0.5) {
            Polarity::BrightDots
        } else {
            Polarity::DarkDots
        };
        let code_size = match spec.family {
            Family::HpCode => Some([33, 37][rng.random_range(0..2)]),
            Family::Stamp => None,
        };
        let mut notes = Vec::new();
        let mut layout = self.place_markers(&spec, code_size, &deg, &mut rng)?;
        // Optics that still resolve the dots: σ ≤ P/4 keeps ≥ 29 % of the grid's fundamental
        // (exp(−2π²σ²/P²)); the placement margins used the larger σ.
        if let Some(m) = layout.markers.first() {
            deg.blur_sigma = deg.blur_sigma.min((0.25 * m.period_px()).max(0.4));
        }
        if deg.clutter {
            self.place_clutter(&spec, code_size, &mut layout, &deg, &mut rng, &mut notes);
        }
        laps.lap("placement");

        let coverage = self.coverage(&layout, &deg, &mut laps)?;
        let (bg, fg) = grey_levels(&mut deg, polarity, &mut rng, &mut notes);
        let (bgf, fgf) = (bg as f32, fg as f32);
        let mut plane = Plane {
            width: coverage.width,
            height: coverage.height,
            data: coverage
                .data
                .iter()
                .map(|&c| bgf + (fgf - bgf) * c.clamp(0.0, 1.0))
                .collect(),
        };
        if deg.dust_hair {
            self.dust_and_hair(&layout, &deg, &mut plane, &mut rng, &mut notes);
            laps.lap("dust_hair");
        }
        if !layout.homography.is_identity() {
            plane = warp(&plane, &layout.homography, 3, bgf);
            laps.lap("perspective");
        }
        let gain = deg.illumination.map(|illum| {
            let gain = illumination_gain(plane.width, plane.height, &illum);
            apply_gain(&mut plane, &gain);
            laps.lap("illumination");
            gain
        });
        let image = finish(&plane, &deg, &mut rng)?;
        laps.lap("sensor");
        let formation = bound::Formation {
            clean: &plane,
            gain: gain.as_ref(),
            contrast: fg - bg,
            blur_sigma: deg.blur_sigma,
            noise: deg.noise,
            jpeg_quality: deg.jpeg_quality,
            observed: Some(&image),
        };
        let bounds = self.position_bounds(&spec, &layout, &deg, &formation)?;
        if bounds.iter().any(Option::is_some) {
            laps.lap("bound");
        }
        Ok(Scene {
            spec,
            image,
            truth: truth_markers(&layout, bounds)?,
            polarity,
            code_size,
            degradations: deg,
            notes,
            timings: laps.timings,
        })
    }

    /// Coverage of the marker plane: markers, then clutter, all through the same optics.
    fn coverage(&self, layout: &Layout, deg: &Degradations, laps: &mut Laps) -> Result<Plane> {
        let (w, h) = (layout.width, layout.height);
        let mut coverage = Plane::filled(w, h, 0.0);
        for m in &layout.markers {
            let l = m.kind.layout(&self.stamps)?;
            add_marker(
                &mut coverage,
                l.as_ref(),
                m.origin,
                m.alpha,
                m.pixel_size,
                deg.blur_sigma,
                m.mirrored,
            )?;
        }
        laps.lap("render");
        if !layout.clutter.is_empty() {
            let mut clutter = Plane::filled(w, h, 0.0);
            for c in &layout.clutter {
                c.paint(&mut clutter);
            }
            clutter.blur(deg.blur_sigma);
            for (v, c) in coverage.data.iter_mut().zip(&clutter.data) {
                *v += c;
            }
            laps.lap("clutter");
        }
        Ok(coverage)
    }

    /// The position bound of each expected marker of the scene's family, where the scene
    /// has one ([`bound::kind`]), under the scene's image `formation`.
    fn position_bounds(
        &self,
        spec: &SceneSpec,
        layout: &Layout,
        deg: &Degradations,
        formation: &bound::Formation,
    ) -> Result<Vec<Option<PositionBound>>> {
        if !self.position_bounds || bound::kind(deg).is_none() {
            return Ok(vec![None; layout.markers.len()]);
        }
        layout
            .markers
            .iter()
            .map(|m| {
                if m.expectation != Expectation::Expected || m.kind.family() != spec.family {
                    return Ok(None);
                }
                bound::position_bound(m.kind.layout(&self.stamps)?.as_ref(), m, formation)
            })
            .collect()
    }

    /// Image size, homography and the 1–3 markers of the scene's family (same scale, random
    /// angles, IDs and positions, inside the frame, not overlapping).
    fn place_markers(
        &self,
        spec: &SceneSpec,
        code_size: Option<usize>,
        deg: &Degradations,
        rng: &mut SmallRng,
    ) -> Result<Layout> {
        let (lo, hi) = period_range(spec.family);
        let mut period_px = log_uniform(rng, lo, hi);
        let count = rng.random_range(1..=3usize);
        let cells = code_size.unwrap_or(STAMP_CELLS) as f64;
        let margin = 3.0 + 4.0 * deg.blur_sigma;
        // Image size from the first scale drawn: the markers may nearly fill the frame.
        let side = cells * period_px / 2.0;
        let need = side * SQRT_2 + 2.0 * margin;
        let (width, height) = frame_size(need, count, deg.clutter, rng);
        let homography = match deg.perspective {
            Some(t) => {
                let diag = (width as f64).hypot(height as f64);
                let center = Vector2::new((width / 2) as f64, (height / 2) as f64);
                Homography::tilt(center, t.angle, t.axis, t.focal_diagonals * diag)
                    .ok_or_else(|| StressError::new("invalid tilt"))?
            }
            None => Homography::identity(),
        };
        let mut layout = Layout {
            width,
            height,
            homography,
            markers: Vec::new(),
            clutter: Vec::new(),
            margin,
        };
        // Which markers are seen from the back: a stream of its own, so that every other
        // draw of the scene stays what it was before mirrored markers were added.
        let mut sides = SmallRng::seed_from_u64(spec.seed ^ 0x6d69_7272_6f72_6564);
        for _shrink in 0..40 {
            let pixel_size = PERIOD / period_px;
            let gap = 2.0 * period_px;
            for _ in 0..count {
                let kind = match code_size {
                    Some(w) => MarkerKind::HpCode {
                        code_size: w,
                        id: rng.random_range(0..1u64 << ((w - 15) / 2)),
                    },
                    None => MarkerKind::Stamp {
                        index: rng.random_range(0..self.stamps.layouts.len()),
                    },
                };
                let half_side = cells * period_px / 2.0;
                let placed =
                    (0..400).find_map(|_| layout.try_place(kind, half_side, pixel_size, gap, rng));
                match placed {
                    Some(m) => {
                        let mirrored = matches!(m.kind, MarkerKind::HpCode { id, .. } if id != 0)
                            && sides.random_bool(self.mirrored_fraction);
                        layout.markers.push(Placed { mirrored, ..m })
                    }
                    None => break,
                }
            }
            if !layout.markers.is_empty() {
                return Ok(layout);
            }
            period_px = (period_px * 0.9).max(lo * 0.5);
        }
        Err(StressError::new(format!(
            "seed {}: no room for a marker in {width}x{height}",
            spec.seed
        )))
    }

    /// 2–6 clutter items beside the markers: glyph blocks, stripes, grid paper, and other
    /// markers (the other W of HP codes: expected; the other family: foreign; 30 % of them
    /// cut by the image border: ignored or foreign).
    fn place_clutter(
        &self,
        spec: &SceneSpec,
        code_size: Option<usize>,
        layout: &mut Layout,
        deg: &Degradations,
        rng: &mut SmallRng,
        notes: &mut Vec<String>,
    ) {
        let Some(first) = layout.markers.first().copied() else {
            return;
        };
        let period_px = first.period_px();
        let clearance = (1.5 * period_px).max(4.0) + 3.0 * deg.blur_sigma;
        let (w, h) = (layout.width as f64, layout.height as f64);
        let n = rng.random_range(2..=6);
        let mut names = Vec::new();
        for _ in 0..n {
            if rng.random_bool(0.3) {
                // Another marker.
                let kind = self.other_marker_kind(spec, code_size, period_px, rng);
                if let Some(name) = place_other_marker(spec, kind, layout, clearance, rng) {
                    names.push(name);
                }
            } else {
                let placed = (0..100).find_map(|_| {
                    let center = Vector2::new(rng.random_range(0.0..w), rng.random_range(0.0..h));
                    let c = Clutter::random(rng, center);
                    layout.is_free(&c.footprint(), clearance).then_some(c)
                });
                if let Some(c) = placed {
                    names.push(c.name().to_string());
                    layout.clutter.push(c);
                }
            }
        }
        notes.push(format!("clutter: {}", names.join(", ")));
    }

    /// Draws the kind and pixel period of a clutter marker: the other HP code size (at the
    /// scene's period) or the other family than the scene's.
    fn other_marker_kind(
        &self,
        spec: &SceneSpec,
        code_size: Option<usize>,
        period_px: f64,
        rng: &mut SmallRng,
    ) -> (MarkerKind, f64) {
        match (spec.family, code_size) {
            (Family::HpCode, Some(w0)) if rng.random_bool(0.5) => {
                let w1 = if w0 == 33 { 37 } else { 33 };
                let id = rng.random_range(0..1u64 << ((w1 - 15) / 2));
                (MarkerKind::HpCode { code_size: w1, id }, period_px)
            }
            (Family::HpCode, _) => (
                MarkerKind::Stamp {
                    index: rng.random_range(0..self.stamps.layouts.len()),
                },
                log_uniform(rng, 4.0, 12.0),
            ),
            (Family::Stamp, _) => {
                let w1 = [33, 37][rng.random_range(0..2)];
                let id = rng.random_range(0..1u64 << ((w1 - 15) / 2));
                (
                    MarkerKind::HpCode { code_size: w1, id },
                    log_uniform(rng, 4.0, 40.0),
                )
            }
        }
    }

    /// Dust blobs (2–8, dark or bright, half of them over a marker) and 1–2 dark hairs
    /// crossing a marker. HP codes: nothing touches the ID strips (top row, left column) and
    /// at most one finder per marker is (partly) covered; stamps: dust touches at most one
    /// frame side, a hair crosses the frame where it must.
    fn dust_and_hair(
        &self,
        layout: &Layout,
        deg: &Degradations,
        plane: &mut Plane,
        rng: &mut SmallRng,
        notes: &mut Vec<String>,
    ) {
        let (w, h) = (plane.width, plane.height);
        let markers = &layout.markers;
        let mut touched = vec![0u32; markers.len()];
        let mut dark = Plane::filled(w, h, 0.0);
        let mut light = Plane::filled(w, h, 0.0);
        let (n_dust, over) = draw_dust(markers, &mut touched, (&mut dark, &mut light), rng);
        let mut hairs = 0;
        let n_hair = if rng.random_bool(0.8) { 1 } else { 2 };
        let candidates: Vec<&Placed> = markers
            .iter()
            .filter(|m| m.expectation == Expectation::Expected)
            .collect();
        for _ in 0..n_hair {
            let Some(m) = candidates.get(rng.random_range(0..candidates.len().max(1))) else {
                break;
            };
            let half_width = (rng.random_range(0.1..0.25) * m.period_px()).max(0.75);
            for _ in 0..200 {
                let curve = random_hair(m, rng);
                let discs: Vec<(Vector2<f64>, f64)> =
                    curve.iter().map(|&p| (p, half_width + 1.0)).collect();
                if accept_discs(markers, &discs, true, &mut touched) {
                    let opacity = rng.random_range(0.7..1.0f32);
                    for pair in curve.windows(2) {
                        dark.draw_segment(pair[0], pair[1], half_width, opacity);
                    }
                    hairs += 1;
                    break;
                }
            }
        }
        dark.blur(deg.blur_sigma);
        light.blur(deg.blur_sigma);
        plane.composite(&dark, 0.03);
        plane.composite(&light, 0.97);
        notes.push(format!(
            "dust: {n_dust} blobs tried, {over} over markers; hairs crossing a marker: {hairs}"
        ));
    }
}

/// The truth of each marker of `layout` in the image, with its position bound.
fn truth_markers(layout: &Layout, bounds: Vec<Option<PositionBound>>) -> Result<Vec<TruthMarker>> {
    layout
        .markers
        .iter()
        .zip(bounds)
        .map(|(m, bound)| {
            m.truth(&layout.homography)
                .map(|t| TruthMarker {
                    position_bound: bound,
                    ..t
                })
                .ok_or_else(|| StressError::new("marker beyond the horizon"))
        })
        .collect()
}

/// Image size for `count` markers needing `need` pixels each (more room with `clutter`),
/// random aspect and orientation.
fn frame_size(need: f64, count: usize, clutter: bool, rng: &mut SmallRng) -> (usize, usize) {
    let packing = [1.0, 1.75, 2.1][count - 1];
    let extra = if clutter {
        rng.random_range(1.3..2.0)
    } else {
        rng.random_range(1.0..1.6)
    };
    let aspect = rng.random_range(1.0..1.4);
    let base = need * packing * extra;
    let (fw, fh) = if rng.random_bool(0.5) {
        (base * aspect, base)
    } else {
        (base, base * aspect)
    };
    let clamp_side = |v: f64| (v.round() as usize).clamp(96, MAX_SIDE);
    (
        clamp_side(fw.max(need + 1.0)),
        clamp_side(fh.max(need + 1.0)),
    )
}

/// Places one clutter marker `(kind, pixel period)` (cut by the border three times in ten),
/// `clearance` from everything, shrinking it every 30 tries; returns its note, or `None`
/// when there is no room.
fn place_other_marker(
    spec: &SceneSpec,
    (kind, mut p_px): (MarkerKind, f64),
    layout: &mut Layout,
    clearance: f64,
    rng: &mut SmallRng,
) -> Option<String> {
    let (w, h) = (layout.width as f64, layout.height as f64);
    let cut = rng.random_bool(0.3);
    let mut placed = None;
    for attempt in 0..120 {
        if attempt % 30 == 29 {
            p_px = (p_px * 0.8).max(4.0);
        }
        let side = kind.cells() as f64 * p_px / 2.0;
        let origin = if cut {
            Vector2::new(
                rng.random_range(-side / 3.0..w + side / 3.0),
                rng.random_range(-side / 3.0..h + side / 3.0),
            )
        } else {
            Vector2::new(rng.random_range(0.0..w), rng.random_range(0.0..h))
        };
        let m = Placed {
            kind,
            origin,
            alpha: rng.random_range(-PI..PI),
            pixel_size: PERIOD / p_px,
            mirrored: false,
            expectation: Expectation::Expected,
        };
        let fp = m.footprint();
        let whole = layout.fits(&fp, layout.margin);
        let ok_place = if cut {
            !whole && layout.visible(&fp)
        } else {
            whole
        };
        if ok_place && layout.is_free(&fp, clearance.max(2.0 * p_px)) {
            placed = Some(m);
            break;
        }
    }
    let mut m = placed?;
    m.expectation = match (m.kind.family() == spec.family, cut) {
        (true, false) => Expectation::Expected,
        (true, true) => Expectation::Ignored,
        (false, _) => Expectation::Foreign,
    };
    let name = format!(
        "{} marker ({}{})",
        m.kind.family().name(),
        m.expectation.name(),
        if cut { ", cut by the border" } else { "" }
    );
    layout.markers.push(m);
    Some(name)
}

/// Accepts a set of discs `(centre, radius)` if every marker keeps its constraints (no ID
/// strip touched, at most one finder or frame side, a hair exempt on stamps); updates
/// `touched`.
fn accept_discs(
    markers: &[Placed],
    discs: &[(Vector2<f64>, f64)],
    is_hair: bool,
    touched: &mut Vec<u32>,
) -> bool {
    let mut next = touched.clone();
    for (i, m) in markers.iter().enumerate() {
        for &(p, r) in discs {
            let (mask, id) = m.touches(p, r);
            if id {
                return false;
            }
            next[i] |= mask;
        }
        let exempt = is_hair && m.kind.family() == Family::Stamp;
        if !exempt && next[i].count_ones() > 1 {
            return false;
        }
    }
    *touched = next;
    true
}

/// Draws 2–8 dust blobs into the `(dark, light)` planes, half of them aimed at a marker;
/// returns how many were tried and how many landed over a marker.
fn draw_dust(
    markers: &[Placed],
    touched: &mut Vec<u32>,
    (dark, light): (&mut Plane, &mut Plane),
    rng: &mut SmallRng,
) -> (i32, usize) {
    let (w, h) = (dark.width, dark.height);
    let n_dust: i32 = rng.random_range(2..=8);
    let mut over = 0;
    for _ in 0..n_dust {
        let target = (rng.random_bool(0.5) && !markers.is_empty())
            .then(|| markers[rng.random_range(0..markers.len())]);
        let soft = rng.random_range(0.5..3.0);
        for _ in 0..60 {
            let (center, radius) = match target {
                Some(m) => {
                    let s = m.side_px() / 2.0;
                    let local = Vector2::new(rng.random_range(-s..s), rng.random_range(-s..s));
                    (
                        m.origin + rotate(local, m.alpha),
                        (rng.random_range(0.3..1.2) * m.period_px()).max(1.5),
                    )
                }
                None => (
                    Vector2::new(
                        rng.random_range(0.0..w as f64),
                        rng.random_range(0.0..h as f64),
                    ),
                    rng.random_range(
                        1.5..(3.0 * markers.first().map_or(4.0, |m| m.period_px())).max(3.0),
                    ),
                ),
            };
            if accept_discs(markers, &[(center, radius + soft)], false, touched) {
                let opacity = rng.random_range(0.5..1.0f32);
                let into = if rng.random_bool(0.6) {
                    &mut *dark
                } else {
                    &mut *light
                };
                into.draw_disc(center, radius, soft, opacity);
                over += usize::from(target.is_some());
                break;
            }
        }
    }
    (n_dust, over)
}

/// A random hair across marker `m`: a quadratic Bézier curve sampled every half pixel.
fn random_hair(m: &Placed, rng: &mut SmallRng) -> Vec<Vector2<f64>> {
    let side = m.side_px();
    let reach = side * rng.random_range(0.8..1.5);
    let t0: f64 = rng.random_range(0.0..TAU);
    let t2 = t0 + PI + rng.random_range(-1.0..1.0);
    let dir = |t: f64| Vector2::new(t.cos(), t.sin());
    let p0 = m.origin + dir(t0) * reach;
    let p2 = m.origin + dir(t2) * reach;
    let p1 = m.origin
        + Vector2::new(
            rng.random_range(-0.4..0.4) * side,
            rng.random_range(-0.4..0.4) * side,
        );
    let steps = ((2.0 * reach + side) / 0.5).ceil() as usize;
    (0..=steps)
        .map(|i| {
            let t = i as f64 / steps as f64;
            p0 * (1.0 - t).powi(2) + p1 * (2.0 * t * (1.0 - t)) + p2 * t * t
        })
        .collect()
}

/// Wall time of each stage of a scene's generation, milliseconds.
struct Laps {
    clock: Instant,
    timings: Vec<(&'static str, f64)>,
}

impl Laps {
    fn start() -> Laps {
        Laps {
            clock: Instant::now(),
            timings: Vec::new(),
        }
    }

    /// Records the time since the last lap as stage `name`.
    fn lap(&mut self, name: &'static str) {
        self.timings
            .push((name, self.clock.elapsed().as_secs_f64() * 1e3));
        self.clock = Instant::now();
    }
}

/// Background and dot grey levels `(bg, fg)` for `polarity` (drawn from `rng`, noted in
/// `notes`); caps `deg`'s noise so that the dimmest dot contrast stays ≥ 5 σ.
fn grey_levels(
    deg: &mut Degradations,
    polarity: Polarity,
    rng: &mut SmallRng,
    notes: &mut Vec<String>,
) -> (f64, f64) {
    let bright = polarity == Polarity::BrightDots;
    let (bg, fg): (f64, f64) = if deg.low_contrast {
        let c = rng.random_range(0.10..0.20);
        let bg = rng.random_range(0.0..1.0 - c);
        if bright {
            (bg, bg + c)
        } else {
            (bg + c, bg)
        }
    } else if bright {
        (rng.random_range(0.02..0.25), rng.random_range(0.65..0.95))
    } else {
        (rng.random_range(0.65..0.95), rng.random_range(0.03..0.3))
    };
    notes.push(format!("background {bg:.3}, dots {fg:.3}"));
    // Combined degradations stay measurable: the noise is capped so that the dot contrast
    // at the dimmest point is ≥ 5 σ (never binds for the noise category alone).
    if let Some(noise) = deg.noise.as_mut() {
        let gain = deg.illumination.map_or(1.0, |i| i.min_gain);
        let limit = (fg - bg).abs() * gain / 5.0;
        let sigma = noise.gaussian + noise.shot * bg.max(fg).sqrt();
        if sigma > limit {
            noise.gaussian *= limit / sigma;
            noise.shot *= limit / sigma;
        }
    }
    (bg, fg)
}
