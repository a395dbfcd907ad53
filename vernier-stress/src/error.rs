//! The suite's error type: a message naming what failed (data files, encoders, the core).

use std::fmt;

/// Any failure of scene generation, detection set-up or dumping, as a readable message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StressError(pub String);

/// Result of the suite's fallible operations.
pub type Result<T> = std::result::Result<T, StressError>;

impl StressError {
    /// An error with `message`.
    pub fn new(message: impl Into<String>) -> Self {
        StressError(message.into())
    }
}

impl fmt::Display for StressError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for StressError {}

impl From<vernier::Error> for StressError {
    fn from(e: vernier::Error) -> Self {
        StressError(format!("vernier: {e}"))
    }
}

impl From<image::ImageError> for StressError {
    fn from(e: image::ImageError) -> Self {
        StressError(format!("image: {e}"))
    }
}

impl From<std::io::Error> for StressError {
    fn from(e: std::io::Error) -> Self {
        StressError(format!("io: {e}"))
    }
}

impl From<serde_json::Error> for StressError {
    fn from(e: serde_json::Error) -> Self {
        StressError(format!("json: {e}"))
    }
}
