//! Helpers shared by the `vernier` binary's end-to-end tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `vernier` binary under test, ready for arguments.
pub fn vernier() -> Command {
    Command::new(env!("CARGO_BIN_EXE_vernier"))
}

/// Runs `vernier args…` and returns its output, whatever the exit status.
pub fn run(args: &[&str]) -> Output {
    vernier().args(args).output().expect("cannot run vernier")
}

/// The stdout of a command that must succeed (the failure shows its stderr).
pub fn stdout_of_success(command: &mut Command) -> Vec<u8> {
    let out = command.output().expect("cannot run vernier");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}

/// A fresh, empty scratch folder for this test process and `name`.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vernier_cli_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The bundled example pattern file (periodic grid, period 15 µm).
pub fn example_pattern() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/periodic_p15.json")
}

/// A path as a `&str` argument (test paths are UTF-8).
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Folder of the real test images: `$VERNIER_DATA_DIR`, else `../shared/data` beside the
/// workspace. Panics (test failure, not skip) when it is missing.
pub fn data_dir() -> PathBuf {
    let dir = std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    assert!(
        dir.is_dir(),
        "test data folder {} is missing: set VERNIER_DATA_DIR to the shared/data folder",
        dir.display()
    );
    dir
}
