//! The crate's one error type. Every variant carries enough text to say what was wrong and where
//! (the tensor, the argument, the call); the C ABI maps variants onto its status codes.

use std::fmt;

/// Everything that can go wrong inside libflame.
#[derive(Debug)]
pub enum Error {
    /// Reading a file failed (`path` says which).
    Io {
        /// The file, as given.
        path: String,
        /// What the operating system reported.
        source: std::io::Error,
    },
    /// Writing a file failed (`path` says which); the C ABI reports it as an I/O error too.
    Write {
        /// The file, as given.
        path: String,
        /// What the operating system reported.
        source: std::io::Error,
    },
    /// The model file is not a valid libflame file: bad header, bad JSON config, a missing or
    /// mis-shaped tensor, an unsupported dtype. The message names the first offending item.
    BadModelFile(String),
    /// A caller-supplied value is out of range or malformed (the message names the argument).
    InvalidArgument(String),
    /// A call made in an order the session does not allow (for example `step` before a prompt).
    WrongState(String),
    /// The generation was cancelled from another thread.
    Cancelled,
    /// The tokenizer rejected the text or could not be built.
    Tokenizer(String),
    /// A step produced NaN or infinity (the message names the step and the likely cause).
    NotFinite(String),
}

/// Shorthand used across the crate.
pub type Result<T> = std::result::Result<T, Error>;

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io { path, source } => write!(f, "cannot read {path}: {source}"),
            Error::Write { path, source } => write!(f, "cannot write {path}: {source}"),
            Error::BadModelFile(m) => write!(f, "bad model file: {m}"),
            Error::InvalidArgument(m) => write!(f, "invalid argument: {m}"),
            Error::WrongState(m) => write!(f, "wrong state: {m}"),
            Error::Cancelled => write!(f, "cancelled"),
            Error::Tokenizer(m) => write!(f, "tokenizer: {m}"),
            Error::NotFinite(m) => write!(f, "not finite: {m}"),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Io { source, .. } | Error::Write { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// Builds an [`Error::BadModelFile`] from format arguments.
macro_rules! bad_file {
    ($($arg:tt)*) => { $crate::error::Error::BadModelFile(format!($($arg)*)) };
}
/// Builds an [`Error::InvalidArgument`] from format arguments.
macro_rules! invalid_arg {
    ($($arg:tt)*) => { $crate::error::Error::InvalidArgument(format!($($arg)*)) };
}
pub(crate) use bad_file;
pub(crate) use invalid_arg;
