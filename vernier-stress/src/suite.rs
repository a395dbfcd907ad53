//! Running many scenes: generation on worker threads, detection (timed) on the calling thread
//! through `vernier::Detector` built from the scene's `DetectorSettings`, scoring, and the
//! per-family, per-category tallies.

use crate::bound::{self, KnownShapeErrors};
use crate::error::{Result, StressError};
use crate::evaluate::{evaluate, SceneResult, Verdict};
use crate::markers::{Expectation, Family};
use crate::scene::{Category, Generator, Scene, SceneSpec};
use std::collections::hash_map::Entry;
use std::collections::{BTreeMap, HashMap};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Instant;
use vernier::{Detector, MarkerPose};

/// Categories whose position error must stay below [`ACCURACY_LIMIT_PX`] (no perspective,
/// no noise: clean and blurred renders).
pub const ACCURACY_CATEGORIES: [&str; 2] = ["clean", "blur"];

/// Position error target on [`ACCURACY_CATEGORIES`], pixels.
pub const ACCURACY_LIMIT_PX: f64 = 2e-3;

/// The first `count` seeds from `start` on (consecutive) whose scene matches the filters.
pub fn select_seeds(
    start: u64,
    count: usize,
    family: Option<Family>,
    category: Option<Category>,
) -> Vec<u64> {
    (start..)
        .filter(|&s| {
            let spec = SceneSpec::from_seed(s);
            family.is_none_or(|f| spec.family == f) && category.is_none_or(|c| spec.category == c)
        })
        .take(count)
        .collect()
}

/// One scene run: the scene, what the detector said, and its score.
pub struct Outcome {
    /// The scene (image and truth).
    pub scene: Scene,
    /// Detections (empty when the detector failed).
    pub detections: Vec<MarkerPose>,
    /// Score.
    pub result: SceneResult,
}

impl Outcome {
    /// Failed in the sense of the failing-seed lists: something missed, wrong or false, or
    /// (accuracy categories) a position error at or above [`ACCURACY_LIMIT_PX`].
    pub fn failed(&self) -> bool {
        self.result.failed()
            || (ACCURACY_CATEGORIES.contains(&self.scene.spec.category.name())
                && self
                    .result
                    .position_errors
                    .iter()
                    .any(|&e| e >= ACCURACY_LIMIT_PX))
    }
}

/// Detectors by (family, code size), kept between scenes (FFT plans).
#[derive(Default)]
pub struct Detectors {
    cache: HashMap<(Family, Option<usize>), Detector>,
}

impl Detectors {
    /// Detects on `scene` with the settings a user would give; returns the detections (or
    /// the error / panic message) and the detection time in milliseconds (construction
    /// excluded).
    pub fn detect(
        &mut self,
        generator: &Generator,
        scene: &Scene,
    ) -> (std::result::Result<Vec<MarkerPose>, String>, f64) {
        let key = (scene.spec.family, scene.code_size);
        let detector = match self.cache.entry(key) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => {
                let built = scene
                    .detector_settings(generator.stamps())
                    .to_config()
                    .and_then(Detector::new);
                match built {
                    Ok(d) => e.insert(d),
                    Err(err) => return (Err(format!("detector settings: {err}")), 0.0),
                }
            }
        };
        let start = Instant::now();
        let out = catch_unwind(AssertUnwindSafe(|| detector.detect(&scene.image)));
        let ms = start.elapsed().as_secs_f64() * 1e3;
        match out {
            Ok(Ok(d)) => (Ok(d), ms),
            Ok(Err(e)) => (Err(format!("detector error: {e}")), ms),
            Err(panic) => {
                self.cache.remove(&key);
                let msg = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "non-string panic".into());
                (Err(format!("detector panic: {msg}")), ms)
            }
        }
    }
}

/// Generates the scenes of `seeds` on `threads` worker threads and detects on each (on this
/// thread, one at a time, so the timing is the detector's alone). `visit` sees every
/// outcome as it completes (in completion order); the outcomes are not kept.
pub fn run(
    generator: &Generator,
    seeds: &[u64],
    threads: usize,
    visit: &mut dyn FnMut(Outcome),
) -> Result<()> {
    let next = AtomicUsize::new(0);
    let threads = threads.clamp(1, 64);
    let mut detectors = Detectors::default();
    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = mpsc::sync_channel::<Result<Scene>>(threads * 2);
        for _ in 0..threads {
            let tx = tx.clone();
            let next = &next;
            s.spawn(move || loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(&seed) = seeds.get(i) else { break };
                let scene = catch_unwind(AssertUnwindSafe(|| generator.generate(seed)))
                    .unwrap_or_else(|_| {
                        Err(StressError::new(format!("seed {seed}: generator panic")))
                    });
                if tx.send(scene).is_err() {
                    break;
                }
            });
        }
        drop(tx);
        for scene in rx {
            let scene = match scene {
                Ok(s) => s,
                Err(e) => {
                    // Stop the workers, then report.
                    next.store(seeds.len(), Ordering::Relaxed);
                    return Err(e);
                }
            };
            let (detections, ms) = detectors.detect(generator, &scene);
            let result = evaluate(&scene, detections.as_deref().map_err(|e| e.clone()), ms);
            visit(Outcome {
                detections: detections.unwrap_or_default(),
                scene,
                result,
            });
        }
        Ok(())
    })
}

/// Counts of one (family, category) cell.
#[derive(Clone, Debug, Default)]
pub struct Tally {
    /// Scenes.
    pub scenes: usize,
    /// Expected markers.
    pub markers: usize,
    /// Found with the right ID.
    pub found: usize,
    /// Matched with a wrong ID.
    pub wrong_id: usize,
    /// Detections matching no marker.
    pub false_markers: usize,
    /// Expected markers not found.
    pub missed: usize,
    /// Scenes where the detector returned an error or panicked.
    pub errors: usize,
    /// Position errors of the found markers, pixels.
    pub position_errors: Vec<f64>,
    /// Position errors over the detector's predicted σ (see
    /// [`crate::evaluate::Verdict::Found`]).
    pub normalised_errors: Vec<f64>,
    /// `(position error, Cramér–Rao bound)` of the found markers that have a bound, pixels
    /// ([`crate::bound`]).
    pub bounded_errors: Vec<(f64, f64)>,
    /// `(position error, JPEG model's figure)` of the found markers in grey JPEG files,
    /// pixels ([`crate::bound`]).
    pub jpeg_modelled_errors: Vec<(f64, f64)>,
    /// `(the reference estimators' errors, the JPEG model's figure)` of the same markers,
    /// pixels ([`crate::bound::KnownShapeErrors`]).
    pub known_shape_errors: Vec<(KnownShapeErrors, f64)>,
    /// Largest position error (pixels) and the seed of its scene, to reproduce it with
    /// `--only SEED`.
    pub worst: Option<(f64, u64)>,
    /// Largest angle error, radians.
    pub max_angle_error: f64,
    /// Total detection time, milliseconds.
    pub detect_ms: f64,
    /// Seeds of the failing scenes (see [`Outcome::failed`]), in run order.
    pub failing: Vec<u64>,
    /// Seeds of the scenes with a wrong ID or pose or a false marker, in run order (listed in
    /// full: they are the suite's gravest failures).
    pub wrong: Vec<u64>,
    /// Expected markers drawn seen from the back (mirrored), and how many of them were found
    /// (with their ID, angle and side).
    pub mirrored: (usize, usize),
}

impl Tally {
    fn add(&mut self, o: &Outcome) {
        let r = &o.result;
        self.scenes += 1;
        self.markers += r.markers;
        self.found += r.found;
        self.wrong_id += r.wrong_id;
        self.false_markers += r.false_markers;
        self.missed += r.missed;
        self.errors += usize::from(r.error.is_some());
        self.position_errors.extend(&r.position_errors);
        self.normalised_errors.extend(&r.normalised_errors);
        self.bounded_errors.extend(&r.bounded_errors);
        self.jpeg_modelled_errors.extend(&r.jpeg_modelled_errors);
        self.known_shape_errors.extend(&r.known_shape_errors);
        for &e in &r.position_errors {
            self.note_worst(e, o.scene.spec.seed);
        }
        self.max_angle_error = r
            .angle_errors
            .iter()
            .fold(self.max_angle_error, |a, &b| a.max(b));
        self.detect_ms += r.detect_ms;
        if o.failed() {
            self.failing.push(o.scene.spec.seed);
        }
        if r.wrong_id > 0 || r.false_markers > 0 {
            self.wrong.push(o.scene.spec.seed);
        }
        let truth = &o.scene.truth;
        self.mirrored.0 += truth
            .iter()
            .filter(|t| t.mirrored && t.expectation == Expectation::Expected)
            .count();
        self.mirrored.1 += r
            .verdicts
            .iter()
            .filter(|v| match v {
                Verdict::Found { truth: ti, .. } => truth.get(*ti).is_some_and(|t| t.mirrored),
                _ => false,
            })
            .count();
    }

    /// Keeps `(error, seed)` as the worst position error if it is the largest so far.
    fn note_worst(&mut self, error: f64, seed: u64) {
        if self.worst.is_none_or(|(w, _)| error > w) {
            self.worst = Some((error, seed));
        }
    }

    fn merge(&mut self, other: &Tally) {
        self.scenes += other.scenes;
        self.markers += other.markers;
        self.found += other.found;
        self.wrong_id += other.wrong_id;
        self.false_markers += other.false_markers;
        self.missed += other.missed;
        self.errors += other.errors;
        self.position_errors.extend(&other.position_errors);
        self.normalised_errors.extend(&other.normalised_errors);
        self.bounded_errors.extend(&other.bounded_errors);
        self.jpeg_modelled_errors
            .extend(&other.jpeg_modelled_errors);
        self.known_shape_errors.extend(&other.known_shape_errors);
        if let Some((e, seed)) = other.worst {
            self.note_worst(e, seed);
        }
        self.max_angle_error = self.max_angle_error.max(other.max_angle_error);
        self.detect_ms += other.detect_ms;
        self.failing.extend(&other.failing);
        self.wrong.extend(&other.wrong);
        self.mirrored.0 += other.mirrored.0;
        self.mirrored.1 += other.mirrored.1;
    }

    /// `(error, JPEG model's figure)` of one reference estimator over the tally's JPEG
    /// markers: the weighted one or the unweighted one ([`KnownShapeErrors`]), pixels.
    pub fn reference_errors(&self, weighted: bool) -> Vec<(f64, f64)> {
        self.known_shape_errors
            .iter()
            .map(|(k, m)| (if weighted { k.weighted } else { k.unweighted }, *m))
            .collect()
    }

    /// Found fraction of the expected markers (1 when there are none).
    pub fn found_fraction(&self) -> f64 {
        if self.markers == 0 {
            1.0
        } else {
            self.found as f64 / self.markers as f64
        }
    }

    /// `(median, p99, max)` of the position errors (nearest rank); `None` without any.
    pub fn position_stats(&self) -> Option<(f64, f64, f64)> {
        median_p99_max(&self.position_errors)
    }

    /// `(median, p99, max)` of the normalised position errors; `None` without any.
    pub fn normalised_stats(&self) -> Option<(f64, f64, f64)> {
        median_p99_max(&self.normalised_errors)
    }
}

/// The RMS of `e/b` over `(e, b)` pairs, e.g. position errors over their bounds (0 without
/// pairs).
pub fn rms_ratio(pairs: &[(f64, f64)]) -> f64 {
    let mean_square = pairs.iter().map(|(e, b)| (e / b).powi(2)).sum::<f64>();
    (mean_square / pairs.len().max(1) as f64).sqrt()
}

/// `(median, p99, max)` of `values` (nearest rank); `None` when empty.
fn median_p99_max(values: &[f64]) -> Option<(f64, f64, f64)> {
    let mut e = values.to_vec();
    if e.is_empty() {
        return None;
    }
    e.sort_by(f64::total_cmp);
    let rank = |q: f64| e[((q * e.len() as f64).ceil() as usize).clamp(1, e.len()) - 1];
    Some((rank(0.5), rank(0.99), e[e.len() - 1]))
}

/// All tallies of a run, plus the generation-time profile.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Per (family, category).
    pub cells: BTreeMap<(Family, Category), Tally>,
    /// Generation time per stage: (total ms, scenes using it).
    pub generation: BTreeMap<&'static str, (f64, usize)>,
    /// Total generation time, ms.
    pub generation_ms: f64,
}

impl Report {
    /// Adds one outcome.
    pub fn add(&mut self, o: &Outcome) {
        let spec = o.scene.spec;
        self.cells
            .entry((spec.family, spec.category))
            .or_default()
            .add(o);
        for &(stage, ms) in &o.scene.timings {
            let e = self.generation.entry(stage).or_default();
            e.0 += ms;
            e.1 += 1;
            self.generation_ms += ms;
        }
    }

    /// The tally of one family over every category.
    pub fn family_total(&self, family: Family) -> Tally {
        let mut t = Tally::default();
        for ((f, _), cell) in &self.cells {
            if *f == family {
                t.merge(cell);
            }
        }
        t
    }

    /// Markdown table of `family`, one row per category and a total row.
    pub fn markdown(&self, family: Family) -> String {
        let mut out = format!(
            "### {}\n\n| category | scenes | markers | found % | wrong ID or pose | false markers | missed | \
             position error median / p99 / max (px) (seed of the max) | error/σ median / p99 | \
             max angle error (rad) | detect ms/scene |\n\
             |---|---:|---:|---:|---:|---:|---:|---|---|---:|---:|\n",
            family.name()
        );
        let row = |name: &str, t: &Tally| {
            let pos = match (t.position_stats(), t.worst) {
                (Some((m, p, x)), Some((_, seed))) => {
                    format!("{m:.1e} / {p:.1e} / {x:.1e} ({seed})")
                }
                _ => "—".into(),
            };
            let normalised = match t.normalised_stats() {
                Some((m, p, _)) => format!("{m:.2} / {p:.2}"),
                None => "—".into(),
            };
            let errors = if t.errors > 0 {
                format!(" ({} det. errors)", t.errors)
            } else {
                String::new()
            };
            format!(
                "| {name} | {} | {} | {:.1} | {} | {} | {}{errors} | {pos} | {normalised} | {:.1e} | \
                 {:.1} |\n",
                t.scenes,
                t.markers,
                100.0 * t.found_fraction(),
                t.wrong_id,
                t.false_markers,
                t.missed,
                t.max_angle_error,
                t.detect_ms / t.scenes.max(1) as f64
            )
        };
        for ((f, c), t) in &self.cells {
            if *f == family {
                out.push_str(&row(c.name(), t));
            }
        }
        let total = self.family_total(family);
        out.push_str(&row("**all**", &total));
        out.push_str(&self.bound_markdown(family));
        let (drawn, found) = total.mirrored;
        if drawn > 0 {
            out.push_str(&format!(
                "\nOf these, {drawn} markers seen from the back (mirrored): {found} found with \
                 their ID, angle and side ({:.1} %).\n",
                100.0 * found as f64 / drawn as f64
            ));
        }
        out
    }

    /// The rows with bounded markers ([`crate::bound`]): each one's Cramér–Rao bound `B`, the
    /// p99 an estimator at the bound would reach on the same markers, the measured p99, and
    /// error / B (an estimator at the bound: RMS 1, p99 2.15); then the same figures of the
    /// grey JPEG files under the additive model. Empty without any.
    fn bound_markdown(&self, family: Family) -> String {
        let cramer_rao = self.bound_table(family, |t| &t.bounded_errors);
        let jpeg = self.bound_table(family, |t| &t.jpeg_modelled_errors);
        let references = self.known_shape_table(family);
        let header = |bound: &str| {
            format!(
                "| category | markers | {bound} median / p99 (px) | p99 at {bound} (px) | \
                 measured p99 (px) | error/{bound} RMS / p99 (at {bound}: 1 / 2.15) |\n\
                 |---|---:|---|---:|---:|---|\n"
            )
        };
        let mut out = String::new();
        if !cramer_rao.is_empty() {
            out.push_str(&format!(
                "\nCramér–Rao bound B where the image is the render plus sensor noise (no \
                 perspective, JPEG, colour cast, dust): the least radial position error of any \
                 unbiased estimator, with the dot shape, grey levels and blur known \
                 (`vernier_stress::bound`).\n\n{}{cramer_rao}",
                header("B")
            ));
        }
        if !jpeg.is_empty() {
            out.push_str(&format!(
                "\nGrey JPEG files, the same figure M with each DCT coefficient's rounding taken \
                 as additive uniform noise: a model of what the file keeps, not a bound \
                 (`vernier_stress::bound`).\n\n{}{jpeg}",
                header("M")
            ));
        }
        if !references.is_empty() {
            out.push_str(&format!(
                "\nThe same files read by two reference estimators that know the dot shape, grey \
                 levels and blur (least squares linearised about the true pose; \
                 `vernier_stress::bound::KnownShapeErrors`): every pixel weighted alike, as the \
                 detector's fit does, and each DCT coefficient weighted by M's model.\n\n\
                 | category | markers | unweighted p99 (px) | unweighted error/M RMS | \
                 weighted p99 (px) | weighted error/M RMS |\n|---|---:|---:|---:|---:|---:|\n\
                 {references}"
            ));
        }
        out
    }

    /// The rows of one bound table: per category and over all, the `(error, bound)` pairs
    /// that `pairs` picks from a tally. Empty without any.
    fn bound_table(&self, family: Family, pairs: impl Fn(&Tally) -> &Vec<(f64, f64)>) -> String {
        self.category_rows(family, |name, t| {
            let pairs = pairs(t);
            let errors: Vec<f64> = pairs.iter().map(|p| p.0).collect();
            let bounds: Vec<f64> = pairs.iter().map(|p| p.1).collect();
            let ratios: Vec<f64> = pairs.iter().map(|(e, b)| e / b).collect();
            let (Some((bm, bp, _)), Some(efficient), Some((_, ep, _)), Some((_, rp, _))) = (
                median_p99_max(&bounds),
                bound::efficient_quantile(&bounds, 0.99),
                median_p99_max(&errors),
                median_p99_max(&ratios),
            ) else {
                return None;
            };
            Some(format!(
                "| {name} | {} | {bm:.1e} / {bp:.1e} | {efficient:.1e} | {ep:.1e} | \
                 {:.2} / {rp:.2} |\n",
                bounds.len(),
                rms_ratio(pairs)
            ))
        })
    }

    /// The rows of the reference estimators' table (`Tally::known_shape_errors`): per
    /// category and over all, each estimator's p99 and RMS error over the JPEG model's figure.
    fn known_shape_table(&self, family: Family) -> String {
        self.category_rows(family, |name, t| {
            let (unweighted, weighted) = (t.reference_errors(false), t.reference_errors(true));
            let p99 = |pairs: &[(f64, f64)]| {
                let errors: Vec<f64> = pairs.iter().map(|p| p.0).collect();
                median_p99_max(&errors).map(|(_, p99, _)| p99)
            };
            Some(format!(
                "| {name} | {} | {:.1e} | {:.2} | {:.1e} | {:.2} |\n",
                unweighted.len(),
                p99(&unweighted)?,
                rms_ratio(&unweighted),
                p99(&weighted)?,
                rms_ratio(&weighted)
            ))
        })
    }

    /// One row per category of `family` and one over all, as `row(name, tally)` writes them
    /// (`None`: no row). Empty when no category has a row.
    fn category_rows(
        &self,
        family: Family,
        mut row: impl FnMut(&str, &Tally) -> Option<String>,
    ) -> String {
        let mut rows = String::new();
        for ((f, c), t) in &self.cells {
            if *f == family {
                rows.extend(row(c.name(), t));
            }
        }
        if !rows.is_empty() {
            rows.extend(row("**all**", &self.family_total(family)));
        }
        rows
    }

    /// The failing seeds, first `limit` per (family, category), then every seed with a wrong
    /// ID or pose or a false marker.
    pub fn failing_list(&self, limit: usize) -> String {
        let mut out = String::new();
        for ((f, c), t) in &self.cells {
            if t.failing.is_empty() {
                continue;
            }
            let shown: Vec<String> = t
                .failing
                .iter()
                .take(limit)
                .map(|s| s.to_string())
                .collect();
            out.push_str(&format!(
                "- {} / {}: {} failing: {}{}\n",
                f.name(),
                c.name(),
                t.failing.len(),
                shown.join(" "),
                if t.failing.len() > limit { " …" } else { "" }
            ));
            if !t.wrong.is_empty() {
                let wrong: Vec<String> = t.wrong.iter().map(|s| s.to_string()).collect();
                out.push_str(&format!(
                    "  - wrong ID or pose, or false: {}\n",
                    wrong.join(" ")
                ));
            }
        }
        if out.is_empty() {
            out.push_str("- none\n");
        }
        out
    }

    /// Mean generation time per stage (over the scenes using it).
    pub fn generation_profile(&self) -> String {
        let mut stages: Vec<_> = self.generation.iter().collect();
        stages.sort_by(|a, b| b.1 .0.total_cmp(&a.1 .0));
        let parts: Vec<String> = stages
            .iter()
            .map(|(name, (total, n))| {
                format!(
                    "{name} {:.0} % ({:.1} ms × {n})",
                    100.0 * total / self.generation_ms.max(1e-9),
                    total / (*n).max(1) as f64
                )
            })
            .collect();
        format!(
            "generation {:.1} s in all: {}",
            self.generation_ms / 1e3,
            parts.join(", ")
        )
    }
}
