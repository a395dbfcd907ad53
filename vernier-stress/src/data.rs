//! The shared data folder (`$VERNIER_DATA_DIR`, default `../shared/data` beside the workspace)
//! and the stamp bitmaps read from it. Nothing from it is copied into the repository.

use crate::error::{Result, StressError};
use std::path::{Path, PathBuf};
use vernier::layout::BitmapLayout;

/// The stamp bitmaps, in ID order (`layouts/<name>.png` in the data folder).
pub const STAMP_NAMES: [&str; 4] = ["stamp69x69", "stampD", "stampG", "stamp+"];

/// The data folder: `$VERNIER_DATA_DIR`, else `../shared/data` relative to the workspace root.
/// Errors (never a silent skip) when it is not a folder.
pub fn data_dir() -> Result<PathBuf> {
    let dir = std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    if dir.is_dir() {
        Ok(dir)
    } else {
        Err(StressError::new(format!(
            "test data folder {} is missing: set VERNIER_DATA_DIR to the shared/data folder",
            dir.display()
        )))
    }
}

/// The stamp bitmaps: their files (for the detector settings) and layouts (for rendering).
#[derive(Clone, Debug)]
pub struct StampSet {
    /// `layouts/<name>.png` for each of [`STAMP_NAMES`].
    pub paths: Vec<PathBuf>,
    /// The bitmaps at the suite's physical period.
    pub layouts: Vec<BitmapLayout>,
}

impl StampSet {
    /// Loads [`STAMP_NAMES`] from `data_dir/layouts` at physical period `period`.
    pub fn load(data_dir: &Path, period: f64) -> Result<Self> {
        let paths: Vec<PathBuf> = STAMP_NAMES
            .iter()
            .map(|n| data_dir.join("layouts").join(format!("{n}.png")))
            .collect();
        let layouts = paths
            .iter()
            .map(|p| {
                BitmapLayout::from_image_file(period, p)
                    .map_err(|e| StressError::new(format!("{}: {e}", p.display())))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(StampSet { paths, layouts })
    }
}
