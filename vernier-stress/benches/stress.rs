//! The generalisation stress suite over many seeded scenes.
//!
//! ```sh
//! cargo bench -p vernier-stress --bench stress -- [--scenes N] [--seed S] \
//!     [--family hpcode|stamp|all] [--category NAME] [--only SEED] [--dump DIR] [--threads N]
//! ```
//!
//! Prints progress on stderr, then per family a Markdown table (one row per degradation
//! category) and, for the rows with sensor noise, each marker's Cramér–Rao bound against its
//! error, and for grey JPEG files the same under the model of their rounding with two
//! reference estimators' errors on the same files (`vernier_stress::bound`), then the failing
//! seeds and the generation-time profile.
//! `--only SEED` runs one scene and prints its truth, detections and verdicts as JSON;
//! `--dump DIR` writes every failing scene (or the `--only` scene) as a 16-bit PNG plus a JSON
//! file.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use vernier_stress::dump::{dump, outcome_json};
use vernier_stress::suite::Outcome;
use vernier_stress::{run, select_seeds, Category, Family, Generator, Report};

const USAGE: &str = "usage: stress [--scenes N] [--seed S] [--family hpcode|stamp|all] \
[--category clean|perspective|blur|noise|jpeg|illumination|low_contrast|colour_cast|clutter|dust_hair|combined] \
[--only SEED] [--dump DIR] [--threads N]";

struct Args {
    scenes: usize,
    seed: u64,
    family: Option<Family>,
    category: Option<Category>,
    only: Option<u64>,
    dump: Option<PathBuf>,
    threads: usize,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        scenes: 2200,
        seed: 1,
        family: None,
        category: None,
        only: None,
        dump: None,
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
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
            "--scenes" => {
                let v = value()?;
                a.scenes = v.parse().map_err(|_| bad(&v))?;
            }
            "--seed" => {
                let v = value()?;
                a.seed = v.parse().map_err(|_| bad(&v))?;
            }
            "--family" => {
                let v = value()?;
                a.family = match v.as_str() {
                    "all" => None,
                    other => Some(Family::parse(other).ok_or_else(|| bad(&v))?),
                };
            }
            "--category" => {
                let v = value()?;
                a.category = Some(Category::parse(&v).ok_or_else(|| bad(&v))?);
            }
            "--only" => {
                let v = value()?;
                a.only = Some(v.parse().map_err(|_| bad(&v))?);
            }
            "--dump" => a.dump = Some(PathBuf::from(value()?)),
            "--threads" => {
                let v = value()?;
                a.threads = v.parse().map_err(|_| bad(&v))?;
            }
            "-h" | "--help" => return Err(USAGE.to_string()),
            other => return Err(format!("unknown argument `{other}`\n{USAGE}")),
        }
    }
    Ok(a)
}

fn main() -> ExitCode {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let generator = match Generator::from_env() {
        Ok(g) => g.with_position_bounds(),
        Err(e) => {
            eprintln!("stress: {e}");
            return ExitCode::FAILURE;
        }
    };
    let seeds = match args.only {
        Some(s) => vec![s],
        None => select_seeds(args.seed, args.scenes, args.family, args.category),
    };
    let total = seeds.len();
    let start = Instant::now();
    let mut report = Report::default();
    let mut done = 0usize;
    let mut dump_error = None;
    let mut visit = |o: Outcome| {
        done += 1;
        report.add(&o);
        if args.only.is_some() {
            match serde_json::to_string_pretty(&outcome_json(&o)) {
                Ok(text) => println!("{text}"),
                Err(e) => eprintln!("stress: {e}"),
            }
        }
        if let Some(dir) = &args.dump {
            if args.only.is_some() || o.failed() {
                if let Err(e) = dump(dir, &o) {
                    dump_error = Some(e);
                }
            }
        }
        if done % 50 == 0 || done == total {
            let found: usize = report.cells.values().map(|t| t.found).sum();
            let markers: usize = report.cells.values().map(|t| t.markers).sum();
            let failing: usize = report.cells.values().map(|t| t.failing.len()).sum();
            eprintln!(
                "[{done}/{total}] {:.0} s: {found}/{markers} markers found, {failing} failing scenes",
                start.elapsed().as_secs_f64()
            );
        }
    };
    if let Err(e) = run(&generator, &seeds, args.threads, &mut visit) {
        eprintln!("stress: {e}");
        return ExitCode::FAILURE;
    }
    if let Some(e) = dump_error {
        eprintln!("stress: dump: {e}");
    }
    print_report(&args, total, &report);
    ExitCode::SUCCESS
}

/// Prints the tables per family, the failing scenes and the generation profile.
fn print_report(args: &Args, total: usize, report: &Report) {
    println!(
        "## vernier stress: {total} scenes from seed {} ({} generation threads)\n",
        args.only.unwrap_or(args.seed),
        args.threads
    );
    println!(
        "Detector settings as a CLI user gives them: marker type, period, code size (HP) or the \
         four bitmaps (stamp); everything else default (polarity: auto). \
         `error/σ` is each position error over the σ the detector predicts for it (from its \
         phase σ): about 0.83 / 2.15 (median / p99) when the error is the image noise the \
         detector accounts for, larger when something else moves the pose. \
         `detect ms/scene` is the time of `Detector::detect` only (generation excluded).\n"
    );
    for family in Family::ALL {
        if report.cells.keys().any(|(f, _)| *f == family) {
            println!("{}", report.markdown(family));
        }
    }
    println!(
        "Failing scenes (missed, wrong ID, false marker, detector error, or a position error \
         ≥ 2e-3 px in clean/blur), reproduce with `--only SEED [--dump DIR]`:\n"
    );
    println!("{}", report.failing_list(20));
    println!("{}", report.generation_profile());
}
