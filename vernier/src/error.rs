//! The one error type of the library. Every fallible public function returns [`Result`].

use std::path::PathBuf;

/// Everything that can go wrong in the library, with enough context for a one-line message.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An image could not be read or decoded.
    #[error("cannot read image {path}: {reason}")]
    ImageRead {
        /// File that failed.
        path: PathBuf,
        /// Decoder message.
        reason: String,
    },
    /// An image could not be written.
    #[error("cannot write image {path}: {reason}")]
    ImageWrite {
        /// File that failed.
        path: PathBuf,
        /// Encoder message.
        reason: String,
    },
    /// An image buffer is unusable (empty, too small, wrong length, NaN...).
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// A pattern description (JSON file or constructor argument) is invalid.
    /// `key` names the offending JSON key or parameter.
    #[error("invalid pattern: key `{key}`: {reason}")]
    InvalidPattern {
        /// Offending key or parameter name.
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The JSON text itself is malformed.
    #[error("malformed JSON{}: {reason}", path.as_ref().map(|p| format!(" in {}", p.display())).unwrap_or_default())]
    Json {
        /// File, when read from a file.
        path: Option<PathBuf>,
        /// Parser message with line and column.
        reason: String,
    },
    /// A detector or engine parameter is out of range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Why it is rejected.
        reason: String,
    },
    /// The phase engine found no periodic pattern (spectral lobes too weak or absent).
    #[error("no periodic pattern found: {0}")]
    PatternNotFound(String),
    /// A grid was found but its code could not be read reliably (too few periods visible,
    /// inconsistent or ambiguous bits): no pose is reported rather than a wrong one.
    #[error("cannot decode the marker: {0}")]
    Decode(String),
    /// Filesystem error other than image decoding.
    #[error("{path}: {source}")]
    Io {
        /// File concerned.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
}

/// Result alias of the library.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Shorthand for [`Error::InvalidPattern`].
    pub fn pattern(key: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidPattern {
            key: key.into(),
            reason: reason.into(),
        }
    }
    /// Shorthand for [`Error::InvalidParameter`].
    pub fn parameter(name: &'static str, reason: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }
}
