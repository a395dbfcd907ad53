//! The real images of the data folder under the stress suite's degradations
//! ([`vernier_stress::real`]): markers found, wrong and false per category and per image.
//!
//! ```sh
//! cargo bench -p vernier-stress --bench real_views -- [--draws N] [--seed S] \
//!     [--category NAME] [--image TEXT] [--only SEED] [--dump DIR] [--threads N] \
//!     [--severity X]
//! ```
//!
//! `--draws` views per image and category (default 8: 11 images × 10 categories × 8 = 880
//! scenes), `--image` keeps the images whose file name contains TEXT, `--only SEED` runs the
//! one scene of that seed (with the same `--seed` and `--draws`), `--dump DIR` writes every
//! failing scene (or the `--only` one) as a 16-bit PNG with a line of its severities.
//! `--severity X` (default 1) draws the same views X times harsher, past the issue's ranges
//! ([`vernier_stress::real::generate_harsher`]): where detection breaks, not a target.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;
use vernier::Detector;
use vernier_stress::real::{
    evaluate, generate_harsher, real_seeds, RealCategory, RealImage, RealResult, RealScene,
    REAL_CASES,
};

const USAGE: &str = "usage: real_views [--draws N] [--seed S] [--category NAME] [--image TEXT] \
[--only SEED] [--dump DIR] [--threads N] [--severity X]";

struct Args {
    draws: usize,
    seed: u64,
    category: Option<RealCategory>,
    image: Option<String>,
    only: Option<u64>,
    dump: Option<PathBuf>,
    threads: usize,
    severity: f64,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        draws: 8,
        seed: 1,
        category: None,
        image: None,
        only: None,
        dump: None,
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        severity: 1.0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || {
            it.next()
                .ok_or_else(|| format!("{flag} needs a value\n{USAGE}"))
        };
        let bad = |v: &str| format!("bad value `{v}` for {flag}\n{USAGE}");
        match flag.as_str() {
            // `cargo bench` passes `--bench` to harness-less benches.
            "--bench" => {}
            "--draws" => {
                let v = value()?;
                a.draws = v.parse().map_err(|_| bad(&v))?;
            }
            "--seed" => {
                let v = value()?;
                a.seed = v.parse().map_err(|_| bad(&v))?;
            }
            "--category" => {
                let v = value()?;
                a.category = Some(RealCategory::parse(&v).ok_or_else(|| bad(&v))?);
            }
            "--image" => a.image = Some(value()?),
            "--only" => {
                let v = value()?;
                a.only = Some(v.parse().map_err(|_| bad(&v))?);
            }
            "--dump" => a.dump = Some(PathBuf::from(value()?)),
            "--threads" => {
                let v = value()?;
                a.threads = v.parse().map_err(|_| bad(&v))?;
            }
            "--severity" => {
                let v = value()?;
                a.severity = v.parse().map_err(|_| bad(&v))?;
                if !(a.severity.is_finite() && a.severity > 0.0) {
                    return Err(bad(&v));
                }
            }
            "-h" | "--help" => return Err(USAGE.to_string()),
            other => return Err(format!("unknown argument `{other}`\n{USAGE}")),
        }
    }
    Ok(a)
}

/// Counts of one row.
#[derive(Default)]
struct Row {
    scenes: usize,
    result: RealResult,
}

impl Row {
    fn add(&mut self, r: &RealResult) {
        self.scenes += 1;
        self.add_counts(r);
    }

    fn line(&mut self, name: &str) -> String {
        let r = &mut self.result;
        r.deviations_px.sort_by(f64::total_cmp);
        let at = |q: f64| {
            r.deviations_px
                .get(((r.deviations_px.len().max(1) - 1) as f64 * q).round() as usize)
                .map_or("—".to_string(), |v| format!("{v:.3}"))
        };
        format!(
            "| {name} | {} | {} | {} ({:.1} %) | {} | {} | {} / {} |",
            self.scenes,
            r.expected,
            r.found,
            100.0 * r.found as f64 / r.expected.max(1) as f64,
            r.wrong,
            r.false_markers,
            at(0.5),
            at(1.0),
        )
    }
}

/// The report's rows and failing scenes, filled from every worker thread.
#[derive(Default)]
struct Tables {
    by_category: BTreeMap<RealCategory, Row>,
    by_image: BTreeMap<usize, Row>,
    failing: Vec<String>,
}

const HEADER: &str =
    "| | scenes | markers | found | wrong | false | deviation px (median / max) |\n\
|---|---|---|---|---|---|---|";

fn main() -> ExitCode {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let (images, cases) = match load_images(&args) {
        Ok(loaded) => loaded,
        Err(e) => {
            eprintln!("real_views: {e}");
            return ExitCode::FAILURE;
        }
    };
    let seeds: Vec<_> = real_seeds(args.seed, &cases, args.draws)
        .into_iter()
        .filter(|(_, c, s)| {
            args.category.is_none_or(|k| k == *c) && args.only.is_none_or(|o| o == *s)
        })
        .collect();
    let tables = run_all(&args, &images, &seeds);
    print_report(&args, seeds.len(), &images, tables);
    ExitCode::SUCCESS
}

/// The images of `REAL_CASES` whose file name contains `--image`, with their case indices.
fn load_images(args: &Args) -> Result<(Vec<RealImage>, Vec<usize>), String> {
    let (mut images, mut cases) = (Vec::new(), Vec::new());
    for (index, case) in REAL_CASES.iter().enumerate() {
        if args
            .image
            .as_ref()
            .is_some_and(|t| !case.file.contains(t.as_str()))
        {
            continue;
        }
        images.push(RealImage::load(*case).map_err(|e| e.to_string())?);
        cases.push(index);
    }
    Ok((images, cases))
}

/// Runs every scene of `seeds` `(image, category, seed)` on `--threads` threads, dumping
/// failing scenes where asked, and tallies them.
fn run_all(args: &Args, images: &[RealImage], seeds: &[(usize, RealCategory, u64)]) -> Tables {
    let total = seeds.len();
    let start = Instant::now();
    let next = AtomicUsize::new(0);
    let tables: Mutex<Tables> = Mutex::default();
    let done = AtomicUsize::new(0);
    std::thread::scope(|s| {
        for _ in 0..args.threads.clamp(1, 64) {
            s.spawn(|| {
                let mut detectors: BTreeMap<usize, Detector> = BTreeMap::new();
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(image, category, seed)) = seeds.get(i) else {
                        break;
                    };
                    let real = &images[image];
                    let (result, scene) =
                        run_scene(real, image, (category, seed, args.severity), &mut detectors);
                    let failed = result.found < result.expected
                        || result.wrong > 0
                        || result.false_markers > 0
                        || result.error.is_some();
                    if failed || args.only.is_some() {
                        if let (Some(dir), Some(scene)) = (&args.dump, &scene) {
                            if let Err(e) = dump(dir, scene, real) {
                                eprintln!("real_views: dump: {e}");
                            }
                        }
                    }
                    let mut tables = tables.lock().unwrap_or_else(|e| e.into_inner());
                    tables.by_category.entry(category).or_default().add(&result);
                    tables.by_image.entry(image).or_default().add(&result);
                    if failed {
                        tables.failing.push(format!(
                            "- seed {seed} ({}, {}): {}/{} found, {} wrong, {} false{}; {}",
                            real.case.file,
                            category.name(),
                            result.found,
                            result.expected,
                            result.wrong,
                            result.false_markers,
                            result.error.map_or(String::new(), |e| format!(", {e}")),
                            scene.map_or(String::new(), |s| s.description),
                        ));
                    }
                    let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                    if n % 50 == 0 || n == total {
                        eprintln!("[{n}/{total}] {:.0} s", start.elapsed().as_secs_f64());
                    }
                }
            });
        }
    });
    tables.into_inner().unwrap_or_else(|e| e.into_inner())
}

/// Prints the tables per category and per image, and the failing scenes.
fn print_report(args: &Args, total: usize, images: &[RealImage], tables: Tables) {
    let Tables {
        mut by_category,
        mut by_image,
        mut failing,
    } = tables;
    println!(
        "## vernier real views: {total} scenes from seed {} ({} per image and category{})\n",
        args.seed,
        args.draws,
        match args.severity == 1.0 {
            true => String::new(),
            false => format!(", severity ×{}", args.severity),
        }
    );
    println!(
        "Every HP code and stamp image of the data folder, turned and magnified 0.7–1, under \
         the stress suite's degradations (clutter, dust and hair are the images' own) and a \
         tone curve; detector settings as a user types them. `deviation` is the distance of \
         each found marker from its clean detection moved by the view (consistency, not \
         accuracy: there is no ground truth).\n"
    );
    println!("{HEADER}");
    let mut all = Row::default();
    for (category, row) in by_category.iter_mut() {
        all.scenes += row.scenes;
        all.add_counts(&row.result);
        println!("{}", row.line(category.name()));
    }
    println!("{}\n", all.line("**all**"));
    println!("{HEADER}");
    for (image, row) in by_image.iter_mut() {
        println!("{}", row.line(images[*image].case.file));
    }
    failing.sort();
    println!(
        "\nFailing scenes ({}), reproduce with `--seed {} --draws {} --only SEED [--dump DIR]`:\n",
        failing.len(),
        args.seed,
        args.draws
    );
    for line in failing.iter().take(40) {
        println!("{line}");
    }
}

impl Row {
    /// Adds another row's counts (its scenes are counted by the caller).
    fn add_counts(&mut self, r: &RealResult) {
        self.result.expected += r.expected;
        self.result.found += r.found;
        self.result.wrong += r.wrong;
        self.result.false_markers += r.false_markers;
        self.result.deviations_px.extend(&r.deviations_px);
    }
}

/// Generates and detects one scene; the scene is returned for the report when it was made.
fn run_scene(
    real: &RealImage,
    image: usize,
    (category, seed, severity): (RealCategory, u64, f64),
    detectors: &mut BTreeMap<usize, Detector>,
) -> (RealResult, Option<RealScene>) {
    let scene = match generate_harsher(real, category, seed, severity) {
        Ok(s) => s,
        Err(e) => {
            let result = RealResult {
                error: Some(format!("generation: {e}")),
                ..Default::default()
            };
            return (result, None);
        }
    };
    let detector = match detectors.entry(image) {
        std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::btree_map::Entry::Vacant(e) => {
            match real.settings.to_config().and_then(Detector::new) {
                Ok(d) => e.insert(d),
                Err(err) => {
                    let result = evaluate(real, &scene, Err(format!("settings: {err}")));
                    return (result, Some(scene));
                }
            }
        }
    };
    let detections = detector.detect(&scene.grey).map_err(|e| e.to_string());
    let result = evaluate(real, &scene, detections.as_deref().map_err(Clone::clone));
    (result, Some(scene))
}

/// Writes `scene` as `real_SEED.png` (16-bit) and `real_SEED.txt` (image, category,
/// severities, expected markers).
fn dump(dir: &std::path::Path, scene: &RealScene, real: &RealImage) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let png = dir.join(format!("real_{}.png", scene.seed));
    scene
        .grey
        .save_png(&png, 16)
        .map_err(|e| std::io::Error::other(e.to_string()))?;
    let expected: Vec<String> = scene
        .expected
        .iter()
        .map(|e| {
            format!(
                "id {} at ({:.1}, {:.1}) px, period {:.2} px",
                e.id, e.position.x, e.position.y, e.period_px
            )
        })
        .collect();
    std::fs::write(
        dir.join(format!("real_{}.txt", scene.seed)),
        format!(
            "{} ({}): {}\n{}\n",
            real.case.file,
            scene.category.name(),
            scene.description,
            expected.join("\n")
        ),
    )
}
