//! The one error type of the crate.

use alloc::string::String;
use alloc::vec::Vec;
use core::fmt;

/// Everything that can go wrong with bad data. Each variant says what was expected and what
/// was found; no public function panics on bad input.
#[derive(Debug)]
#[non_exhaustive]
pub enum Error {
    /// The bytes are not a readable safetensors file (truncated, bad header, bad offsets).
    Malformed { reason: String },
    /// The `drivesim.config` metadata is missing or is not the expected JSON object.
    Metadata { reason: String },
    /// A config value the model does not support.
    Config {
        field: &'static str,
        expected: &'static str,
        found: usize,
    },
    /// The weight file lacks a tensor the config requires.
    MissingTensor { name: String },
    /// A tensor has the wrong shape for the config.
    Shape {
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    /// A tensor is stored in a dtype other than F32, F16 or BF16.
    Dtype { name: String, found: String },
    /// A caller buffer has the wrong number of values.
    BufferLength {
        buffer: &'static str,
        expected: usize,
        found: usize,
    },
    /// A caller buffer does not hold a whole number of items (frames, codes, actions).
    NotWholeItems {
        buffer: &'static str,
        item_len: usize,
        found: usize,
    },
    /// More items in one call than the simulator was planned for.
    BatchTooLarge { max: usize, found: usize },
    /// An episodes file whose episode boundaries are inconsistent.
    Episodes { reason: String },
    /// An index past the end (an episode or frame number).
    OutOfRange {
        what: &'static str,
        index: usize,
        len: usize,
    },
    /// An input holds NaN or an infinity.
    NonFinite {
        buffer: &'static str,
        index: usize,
        value: f32,
    },
    /// The weight file could not be read.
    #[cfg(feature = "std")]
    Io { path: String, source: std::io::Error },
    /// The operating system would not start the requested worker threads.
    #[cfg(feature = "std")]
    Threads { requested: usize, source: std::io::Error },
}

/// `Result` with [`Error`].
pub type Result<T> = core::result::Result<T, Error>;

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Malformed { reason } => {
                write!(f, "not a readable safetensors weight file: {reason}")
            }
            Error::Metadata { reason } => write!(f, "bad `drivesim.config` metadata: {reason}"),
            Error::Config { field, expected, found } => {
                write!(f, "config `{field}`: expected {expected}, found {found}")
            }
            Error::MissingTensor { name } => write!(f, "weight file has no tensor `{name}`"),
            Error::Shape { name, expected, found } => {
                write!(f, "tensor `{name}`: expected shape {expected:?}, found {found:?}")
            }
            Error::Dtype { name, found } => {
                write!(f, "tensor `{name}`: expected dtype F32, F16 or BF16, found {found}")
            }
            Error::BufferLength {
                buffer,
                expected,
                found,
            } => write!(f, "`{buffer}`: expected {expected} values, found {found}"),
            Error::NotWholeItems {
                buffer,
                item_len,
                found,
            } => {
                write!(
                    f,
                    "`{buffer}`: expected a non-zero multiple of {item_len} values, found {found}"
                )
            }
            Error::BatchTooLarge { max, found } => {
                write!(
                    f,
                    "batch of {found}: the simulator was planned for at most {max} (see Simulator::with_batch)"
                )
            }
            Error::Episodes { reason } => write!(f, "bad episodes file: {reason}"),
            Error::OutOfRange { what, index, len } => write!(f, "{what} {index} does not exist: there are {len}"),
            Error::NonFinite { buffer, index, value } => {
                write!(f, "`{buffer}`[{index}] is {value}: expected a finite number")
            }
            #[cfg(feature = "std")]
            Error::Io { path, source } => write!(f, "cannot read `{path}`: {source}"),
            #[cfg(feature = "std")]
            Error::Threads { requested, source } => write!(f, "cannot start {requested} threads: {source}"),
        }
    }
}

impl core::error::Error for Error {
    fn source(&self) -> Option<&(dyn core::error::Error + 'static)> {
        match self {
            #[cfg(feature = "std")]
            Error::Io { source, .. } | Error::Threads { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// Checks a caller buffer's length.
pub(crate) fn expect_len(buffer: &'static str, data: &[f32], expected: usize) -> Result<()> {
    if data.len() == expected {
        Ok(())
    } else {
        Err(Error::BufferLength {
            buffer,
            expected,
            found: data.len(),
        })
    }
}

/// Checks that every value of an input is finite.
pub(crate) fn expect_finite(buffer: &'static str, data: &[f32]) -> Result<()> {
    match data.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(Error::NonFinite {
            buffer,
            index,
            value: data[index],
        }),
    }
}
