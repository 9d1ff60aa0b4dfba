//! One error type for the whole crate. Every variant names what went wrong
//! and where (field and index, subdomain, cable), so that a user can fix the
//! input without a debugger. The C ABI maps each variant to a status code.

use std::fmt;

/// Result alias used throughout the crate.
pub type Result<T> = std::result::Result<T, Error>;

/// Everything that can go wrong, from reading a scene to the last iteration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Error {
    /// A scene field is invalid. `field` is the dotted path (`elements.ea`),
    /// `index` the 0-based entry when the problem is in one entry.
    InvalidInput {
        field: String,
        index: Option<usize>,
        message: String,
    },
    /// The scene file could not be read or parsed.
    Parse(String),
    /// I/O failure (file not found, cannot write result).
    Io(String),
    /// The structure has no unique equilibrium: unsupported, a mechanism, or a
    /// mechanism that appears once the slack cables are removed.
    Mechanism(String),
    /// A subdomain matrix is indefinite or too badly conditioned to be
    /// factored reliably (for example from compressive geometric stiffness).
    IndefiniteSubdomain { subdomain: usize, message: String },
    /// A method was asked for that cannot run on this decomposition (for
    /// example `monolevel` with a singular subdomain).
    MethodNotApplicable(String),
    /// The iterations diverged (NaN, or sustained growth of the indicator).
    Diverged { iteration: usize, message: String },
    /// A numerical failure that should not happen on valid input.
    Numerical(String),
}

impl Error {
    /// Shorthand for an [`Error::InvalidInput`].
    pub fn input(field: impl Into<String>, index: Option<usize>, message: impl Into<String>) -> Self {
        Error::InvalidInput {
            field: field.into(),
            index,
            message: message.into(),
        }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::InvalidInput {
                field,
                index: Some(i),
                message,
            } => {
                write!(f, "invalid input: {field}[{i}]: {message}")
            }
            Error::InvalidInput {
                field,
                index: None,
                message,
            } => {
                write!(f, "invalid input: {field}: {message}")
            }
            Error::Parse(m) => write!(f, "cannot parse scene: {m}"),
            Error::Io(m) => write!(f, "i/o error: {m}"),
            Error::Mechanism(m) => write!(f, "no unique solution: {m}"),
            Error::IndefiniteSubdomain { subdomain, message } => {
                write!(f, "subdomain {subdomain}: {message}")
            }
            Error::MethodNotApplicable(m) => write!(f, "method not applicable: {m}"),
            Error::Diverged { iteration, message } => {
                write!(f, "diverged at iteration {iteration}: {message}")
            }
            Error::Numerical(m) => write!(f, "numerical failure: {m}"),
        }
    }
}

impl std::error::Error for Error {}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        Error::Io(e.to_string())
    }
}
