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
    Malformed {
        /// Which file: "weight file", "episodes file" or "gzipped episodes file".
        what: &'static str,
        /// What the parser found wrong.
        reason: String,
    },
    /// The `drivesim.config` metadata is missing or is not the expected JSON object, or another
    /// `drivesim.*` key (`drivesim.actions`, `drivesim.frame_hz`) cannot be read.
    Metadata {
        /// What is missing or wrong, with the JSON found.
        reason: String,
    },
    /// A config value the model does not support.
    Config {
        /// The config key.
        field: &'static str,
        /// The values allowed.
        expected: &'static str,
        /// The value given.
        found: usize,
    },
    /// The weight file lacks a tensor the config requires.
    MissingTensor {
        /// The tensor's name in the file.
        name: String,
    },
    /// A tensor has the wrong shape for the config.
    Shape {
        /// The tensor's name in the file.
        name: String,
        /// The shape the config implies.
        expected: Vec<usize>,
        /// The shape stored.
        found: Vec<usize>,
    },
    /// A tensor is stored in a dtype other than F32, F16 or BF16.
    Dtype {
        /// The tensor's name in the file.
        name: String,
        /// The dtype stored.
        found: String,
    },
    /// A weight file's tensors do not all share one dtype.
    MixedDtypes {
        /// The first tensor, in name order, whose dtype differs.
        name: String,
        /// Its dtype.
        found: String,
        /// The dtype of the file's other tensors.
        expected: String,
    },
    /// A weight file holds a tensor the config does not use.
    UnexpectedTensor {
        /// The tensor's name in the file.
        name: String,
    },
    /// A weight that no model can have: not finite, or a negative BatchNorm variance.
    BadWeight {
        /// The tensor's name in the file.
        name: String,
        /// The first bad value's index in the tensor, row-major.
        index: usize,
        /// That value.
        value: f32,
        /// What a value of this tensor must be.
        expected: &'static str,
    },
    /// A caller buffer has the wrong number of values.
    BufferLength {
        /// The argument's name.
        buffer: &'static str,
        /// The values it must hold.
        expected: usize,
        /// The values it holds.
        found: usize,
    },
    /// A caller buffer does not hold a whole number of items (frames, codes, actions).
    NotWholeItems {
        /// The argument's name.
        buffer: &'static str,
        /// Values per item.
        item_len: usize,
        /// The values it holds.
        found: usize,
    },
    /// More items in one call than the simulator was planned for.
    BatchTooLarge {
        /// The planned batch.
        max: usize,
        /// The items given.
        found: usize,
    },
    /// An episodes file whose episode boundaries are inconsistent.
    Episodes {
        /// The rule broken, with the values found.
        reason: String,
    },
    /// An index past the end (an episode or frame number).
    OutOfRange {
        /// "episode" or "frame".
        what: &'static str,
        /// The index asked for.
        index: usize,
        /// How many there are.
        len: usize,
    },
    /// An input holds NaN or an infinity.
    NonFinite {
        /// The argument's name.
        buffer: &'static str,
        /// The first such value's index.
        index: usize,
        /// That value.
        value: f32,
    },
    /// A frame value outside [-1, 1].
    FrameValue {
        /// The argument's name.
        buffer: &'static str,
        /// The first such value's index.
        index: usize,
        /// That value.
        value: f32,
    },
    /// A result overflowed to an infinity or NaN although every input was finite: the
    /// weights or the inputs are too large for f32. The output buffer holds no valid result.
    NonFiniteOutput {
        /// The output's name.
        buffer: &'static str,
        /// The first non-finite value's index.
        index: usize,
    },
    /// An action outside the range the model was trained on (its `drivesim.actions`).
    ActionRange {
        /// The value's index in the plan.
        index: usize,
        /// The action's name.
        name: String,
        /// Its unit.
        unit: String,
        /// The value given.
        value: f32,
        /// The smallest value in the training data.
        min: f32,
        /// The largest.
        max: f32,
    },
    /// An [`crate::Environment`] stepped before any reset gave its drives a state (or after a
    /// reset failed).
    NotSeeded,
    /// [`crate::Simulator::act`] on a model whose weight file has no policy (`policy.*`
    /// tensors; `train policy` adds them).
    NoPolicy,
    /// A call that reads the reward or value head on a model whose weight file has none
    /// (`reward.*`, `value.*` tensors; `train heads` adds them).
    NoHead {
        /// The head's name: `reward` or `value`.
        head: &'static str,
    },
    /// Sampling asked of a model whose transition has neither the spread head (`transition.S`
    /// and `transition.s`) nor the texture net (`transition.texture.*`): it predicts its mean only.
    NoSampling,
    /// A trainer asked to apply gradients it has not computed (each set is applied once).
    NoGradients,
    /// A driver or sampler file learnt in another world than the weight file it was given with
    /// ([`crate::Model::from_bytes_with_driver`], [`crate::Model::from_bytes_with_sampler`],
    /// [`crate::sampler_file`]; fingerprints: [`crate::world_fingerprint`]).
    OtherWorld {
        /// The weight file's world.
        world: String,
        /// The world the driver or sampler was learnt in (its file's `drivesim.world`).
        learnt_in: String,
    },
    /// A caller-supplied arena is smaller than its plan.
    ArenaTooSmall {
        /// The bytes the plan needs.
        needed: usize,
        /// The bytes given.
        given: usize,
    },
    /// A training setting outside its range (a learning rate, a clipping norm, an action's
    /// standard deviation).
    Setting {
        /// The setting's name.
        name: &'static str,
        /// The values allowed.
        expected: &'static str,
        /// The value given.
        value: f32,
    },
    /// The memory a plan needs could not be allocated.
    OutOfMemory {
        /// What was being allocated.
        what: &'static str,
        /// The bytes needed in all, or `None`: more than the address space holds.
        bytes: Option<usize>,
    },
    /// A file could not be read.
    #[cfg(feature = "std")]
    Io {
        /// The file's path.
        path: String,
        /// Why (also this error's `source()`).
        source: std::io::Error,
    },
    /// The operating system would not start the requested worker threads.
    #[cfg(feature = "std")]
    Threads {
        /// The threads asked for, the caller's included.
        requested: usize,
        /// Why (also this error's `source()`).
        source: std::io::Error,
    },
}

/// `Result` with [`Error`].
pub type Result<T> = core::result::Result<T, Error>;

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Malformed { what, reason } => write!(f, "not a readable safetensors {what}: {reason}"),
            Error::Metadata { reason } => write!(f, "bad weight-file metadata: {reason}"),
            Error::Config { field, expected, found } => {
                write!(f, "config `{field}`: expected {expected}, found {found}")
            }
            Error::OtherWorld { world, learnt_in } => write!(
                f,
                "the driver or sampler was learnt in world {learnt_in}, not in this weight file's world {world}"
            ),
            Error::MissingTensor { name } => write!(f, "weight file has no tensor `{name}`"),
            Error::Shape { name, expected, found } => {
                write!(f, "tensor `{name}`: expected shape {expected:?}, found {found:?}")
            }
            Error::Dtype { name, found } => {
                write!(f, "tensor `{name}`: expected dtype F32, F16 or BF16, found {found}")
            }
            Error::MixedDtypes { name, found, expected } => write!(
                f,
                "tensor `{name}` is {found} but the file's other tensors are {expected}: a weight file has one dtype"
            ),
            Error::UnexpectedTensor { name } => {
                write!(f, "weight file has a tensor `{name}` that the config does not use")
            }
            Error::BadWeight {
                name,
                index,
                value,
                expected,
            } => write!(f, "tensor `{name}`[{index}] is {value}: expected {expected}"),
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
            Error::FrameValue { buffer, index, value } => {
                write!(f, "`{buffer}`[{index}] is {value}: frame values lie in [-1, 1]")
            }
            Error::NonFiniteOutput { buffer, index } => write!(
                f,
                "`{buffer}`[{index}] overflowed to a non-finite value: the inputs or weights are too large for f32"
            ),
            Error::ActionRange {
                index,
                name,
                unit,
                value,
                min,
                max,
            } => write!(
                f,
                "action {index} ({name}) is {value} {unit}: the model was trained on {min} to {max}"
            ),
            Error::NotSeeded => write!(
                f,
                "the environment has no state: reset it from seed frames or codes first"
            ),
            Error::NoSampling => write!(
                f,
                "the model's transition predicts no spread and has no texture net (no `transition.S` and \
                 `transition.s`, no `transition.texture.*` in its weight file): it cannot sample, only give its \
                 mean (temperature 0)"
            ),
            Error::NoPolicy => write!(
                f,
                "the model has no policy (no `policy.*` tensors in its weight file): train one with `train policy`"
            ),
            Error::NoHead { head } => write!(
                f,
                "the model has no {head} head (no `{head}.*` tensors in its weight file): train one with `train heads`"
            ),
            Error::NoGradients => write!(
                f,
                "no gradients to apply: compute them first (each set is applied once)"
            ),
            Error::ArenaTooSmall { needed, given } => {
                write!(f, "the arena holds {given} bytes: its plan needs {needed}")
            }
            Error::Setting { name, expected, value } => write!(f, "{name} is {value}: expected {expected}"),
            Error::OutOfMemory {
                what,
                bytes: Some(bytes),
            } => {
                write!(
                    f,
                    "cannot allocate {what}: {bytes} bytes ({:.1} GiB)",
                    *bytes as f64 / (1u64 << 30) as f64
                )
            }
            Error::OutOfMemory { what, bytes: None } => {
                write!(f, "cannot allocate {what}: their size overflows the address space")
            }
            #[cfg(feature = "std")]
            Error::Io { path, .. } => write!(f, "cannot read `{path}`"),
            #[cfg(feature = "std")]
            Error::Threads { requested, .. } => write!(f, "cannot start {requested} threads"),
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

/// How many items of `item_len` values `data` holds: a whole, non-zero number.
pub(crate) fn whole_items(buffer: &'static str, data: &[f32], item_len: usize) -> Result<usize> {
    if data.is_empty() || !data.len().is_multiple_of(item_len) {
        return Err(Error::NotWholeItems {
            buffer,
            item_len,
            found: data.len(),
        });
    }
    Ok(data.len() / item_len)
}

/// Checks a caller buffer's length.
pub(crate) fn expect_len<T>(buffer: &'static str, data: &[T], expected: usize) -> Result<()> {
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

/// The index and value of the first of `data` that `ok` rejects.
fn first_bad(data: &[f32], ok: impl Fn(&f32) -> bool) -> Option<(usize, f32)> {
    data.iter().position(|v| !ok(v)).map(|index| (index, data[index]))
}

/// Whether every value is finite, in one vectorisable pass (`v · 0` is 0 for a finite value
/// and NaN otherwise, and NaN survives every sum): the fast path of the checks on large
/// buffers, which then search for the index only when there is one to find.
pub(crate) fn all_finite(data: &[f32]) -> bool {
    let mut lanes = [0.0f32; 16];
    let mut chunks = data.chunks_exact(16);
    for chunk in &mut chunks {
        lanes.iter_mut().zip(chunk).for_each(|(l, &v)| *l += v * 0.0);
    }
    lanes.iter().chain(chunks.remainder()).all(|v| v.is_finite())
}

/// Checks that every value of an input is finite.
pub(crate) fn expect_finite(buffer: &'static str, data: &[f32]) -> Result<()> {
    first_bad(data, |v| v.is_finite()).map_or(Ok(()), |(index, value)| Err(Error::NonFinite { buffer, index, value }))
}

/// Checks that every value of a frame is finite and within [-1, 1].
pub(crate) fn expect_frames(buffer: &'static str, data: &[f32]) -> Result<()> {
    expect_finite(buffer, data)?;
    first_bad(data, |v| (-1.0..=1.0).contains(v))
        .map_or(Ok(()), |(index, value)| Err(Error::FrameValue { buffer, index, value }))
}

/// Checks that a result is finite.
pub(crate) fn expect_finite_output(buffer: &'static str, data: &[f32]) -> Result<()> {
    if all_finite(data) {
        return Ok(());
    }
    first_bad(data, |v| v.is_finite()).map_or(Ok(()), |(index, _)| Err(Error::NonFiniteOutput { buffer, index }))
}
