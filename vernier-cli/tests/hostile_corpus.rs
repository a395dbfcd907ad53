//! The hostile-input corpus of issue 16 (`scripts/hostile_corpus.py`: decompression bombs,
//! truncated and corrupted images, out-of-range settings, unbounded renders, YAML bombs): each
//! case must end with a clean one-line error naming the problem, a non-zero exit and no
//! panic or abort, under an address-space cap of 4 GiB (`prlimit --as=4294967296`).
//!
//! A longer run with a real 60000² PNG (3.5 MB, about a minute to generate):
//! `VERNIER_HOSTILE_BIG=1 cargo test -p vernier-cli --test hostile_corpus`.

mod common;

use common::data_dir;

use std::path::PathBuf;
use std::process::Command;

/// Address-space cap of every run, bytes (4 GiB).
const MEMORY_CAP: u64 = 4 << 30;

#[test]
fn every_hostile_file_gives_a_clean_error_within_the_memory_cap() {
    let dir = common::scratch("hostile");
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scripts/hostile_corpus.py");
    let mut generate = Command::new("python3");
    generate
        .arg(&script)
        .arg(&dir)
        .arg("--data")
        .arg(data_dir());
    if std::env::var_os("VERNIER_HOSTILE_BIG").is_some() {
        generate.arg("--big");
    }
    let out = generate.output().expect("python3 is needed for the corpus");
    assert!(
        out.status.success(),
        "hostile_corpus.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap();
    let cases = manifest.as_array().unwrap();
    assert!(cases.len() >= 25, "{} cases", cases.len());
    let exe = env!("CARGO_BIN_EXE_vernier");
    let mut failures = Vec::new();
    for case in cases {
        let name = case["name"].as_str().unwrap();
        let expect = case["expect"].as_str().unwrap();
        let args: Vec<&str> = case["args"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a.as_str().unwrap())
            .collect();
        let run = Command::new("prlimit")
            .arg(format!("--as={MEMORY_CAP}"))
            .arg(exe)
            .args(&args)
            .output()
            .expect("prlimit (util-linux) is needed");
        let stderr = String::from_utf8_lossy(&run.stderr);
        let code = run.status.code();
        let ok = matches!(code, Some(1 | 2))
            && stderr.contains(expect)
            && stderr.starts_with("vernier: ")
            && !stderr.contains("panicked")
            && !stderr.contains("memory allocation");
        if !ok {
            failures.push(format!("{name}: exit {code:?}, stderr: {stderr}"));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    std::fs::remove_dir_all(&dir).ok();
}
