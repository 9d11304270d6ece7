//! Recorded driving, as written by the Python package (`drivesim.carracing.record`, `drivesim.comma`)
//! (format: `weights/TRAINING_FILES.md`, "Episodes format"): seed frames for rollouts and data for
//! training.

use crate::{Error, Result};
use alloc::format;
use alloc::string::ToString;
use alloc::vec::Vec;
use safetensors::{Dtype, SafeTensors};

/// The metadata key of the frames' rate in an episodes file.
const FRAME_HZ: &str = "frame_hz";

/// Frames and the actions in effect at each, grouped into contiguous episodes.
pub struct Episodes {
    height: usize,
    width: usize,
    /// `[N, H, W, 3]` RGB.
    frames: Vec<u8>,
    /// `[N, 2]`: (speed, steering) at frame i.
    actions: Vec<f32>,
    /// `[N, 2]`, optional: (speed to drive at, steering) a teacher gave for frame i.
    labels: Option<Vec<f32>>,
    /// `[N]` each, optional: the env's reward for the decision at frame i, and 1 where a wheel
    /// touched the road at frame i.
    outcomes: Option<(Vec<f32>, Vec<u8>)>,
    /// First frame of each episode, increasing from 0.
    starts: Vec<usize>,
    /// Frames per second, from the file's `frame_hz` metadata.
    frame_hz: Option<f32>,
}

/// One episode's frames and actions, borrowed from [`Episodes`].
#[derive(Clone, Copy)]
pub struct Episode<'a> {
    /// Frame height in pixels.
    pub height: usize,
    /// Frame width in pixels.
    pub width: usize,
    /// `len() * height * width * 3` bytes, HWC RGB frames back to back.
    pub frames: &'a [u8],
    /// `len() * 2` values: (speed, steering) in effect at each frame.
    pub actions: &'a [f32],
    /// `len() * 2` values, where the file has them: (speed to drive at, steering) that a
    /// teacher gave for each frame (DAgger's labels, `weights/TRAINING_FILES.md`), which a policy
    /// learns instead of the driver's own.
    pub labels: Option<&'a [f32]>,
    /// `len()` values, where the file has them: the env's reward for the decision taken at
    /// each frame (summed over the frames to the next), what a reward head learns.
    pub rewards: Option<&'a [f32]>,
    /// `len()` values with the rewards: 1 where a wheel touched the road at the frame, else 0.
    pub on_road: Option<&'a [u8]>,
}

impl Episode<'_> {
    /// Frames in the episode.
    pub fn len(&self) -> usize {
        self.actions.len() / Episodes::ACTION_DIM
    }

    /// Whether the episode has no frame (never, for a loaded file).
    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }

    /// Frame `i` scaled to the model's [-1, 1] range, into `out` (`height * width * 3` values).
    pub fn frame_f32(&self, i: usize, out: &mut [f32]) -> Result<()> {
        let len = self.height * self.width * Episodes::CHANNELS;
        crate::error::expect_len("out", out, len)?;
        let out_of_range = Error::OutOfRange {
            what: "frame",
            index: i,
            len: self.len(),
        };
        if i >= self.len() {
            return Err(out_of_range);
        }
        let frame = &self.frames[i * len..][..len];
        for (o, &p) in out.iter_mut().zip(frame) {
            *o = p as f32 / 127.5 - 1.0;
        }
        Ok(())
    }
}

/// A tensor's little-endian f32 bytes as values.
fn f32_values(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
        .collect()
}

/// The first two bytes of a gzip stream.
const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];

impl Episodes {
    /// Colour channels of a frame (RGB).
    pub const CHANNELS: usize = 3;
    /// Values of an action: (speed, steering).
    pub const ACTION_DIM: usize = 2;

    /// Reads an episodes file (`weights/TRAINING_FILES.md`), gzipped or not.
    ///
    /// ```
    /// use drivesim::Episodes;
    ///
    /// // The seed clip `hallucinate` starts from: one episode of CarRacing.
    /// let clip = Episodes::load("weights/seed_clip.safetensors")?;
    /// let episode = clip.episode(0)?;
    /// let (height, width) = clip.frame_size();
    /// let mut frame = vec![0.0; height * width * Episodes::CHANNELS];
    /// episode.frame_f32(0, &mut frame)?; // in [-1, 1], ready for Simulator::encode
    /// let (speed, steering) = (episode.actions[0], episode.actions[1]);
    /// assert!(speed.is_finite() && steering.abs() <= 1.0);
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    #[cfg(feature = "std")]
    pub fn load(path: impl AsRef<std::path::Path>) -> Result<Episodes> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        Episodes::from_bytes(&bytes)
    }

    /// Reads an episodes file from its bytes: safetensors, or (with std) safetensors gzipped.
    pub fn from_bytes(bytes: &[u8]) -> Result<Episodes> {
        if bytes.starts_with(&GZIP_MAGIC) {
            return Episodes::from_gzip(bytes);
        }
        let file = SafeTensors::deserialize(bytes).map_err(|e| Error::Malformed {
            what: "episodes file",
            reason: format!("{e:?}"),
        })?;
        let get = |name: &str, dtype: Dtype, rank: usize| {
            let view = file
                .tensor(name)
                .map_err(|_| Error::MissingTensor { name: name.to_string() })?;
            if view.dtype() != dtype {
                return Err(Error::Dtype {
                    name: name.to_string(),
                    found: format!("{:?} (expected {dtype:?})", view.dtype()),
                });
            }
            if view.shape().len() != rank {
                let expected = alloc::vec![0; rank];
                return Err(Error::Shape {
                    name: name.to_string(),
                    expected,
                    found: view.shape().to_vec(),
                });
            }
            Ok(view)
        };
        let frames = get("frames", Dtype::U8, 4)?;
        let starts = get("episode_starts", Dtype::I64, 1)?;
        let &[n, height, width, channels] = frames.shape() else {
            unreachable!("rank checked")
        };
        if channels != Episodes::CHANNELS || n == 0 {
            let expected = alloc::vec![n.max(1), height, width, Episodes::CHANNELS];
            return Err(Error::Shape {
                name: "frames".into(),
                expected,
                found: frames.shape().to_vec(),
            });
        }
        // `[n, 2]` finite f32 values: the actions, and the labels where the file has them.
        let pairs = |name: &'static str| -> Result<Vec<f32>> {
            let view = get(name, Dtype::F32, 2)?;
            if view.shape() != [n, Episodes::ACTION_DIM] {
                return Err(Error::Shape {
                    name: name.into(),
                    expected: alloc::vec![n, Episodes::ACTION_DIM],
                    found: view.shape().to_vec(),
                });
            }
            let values = f32_values(view.data());
            crate::error::expect_finite(name, &values)?;
            Ok(values)
        };
        let actions = pairs("actions")?;
        let starts: Vec<i64> = starts
            .data()
            .chunks_exact(8)
            .map(|b| i64::from_le_bytes(b.try_into().expect("8 bytes")))
            .collect();
        let increasing = starts.windows(2).all(|w| w[0] < w[1]);
        if starts.first() != Some(&0) || !increasing || starts.last().is_some_and(|&s| s as u64 >= n as u64) {
            return Err(Error::Episodes {
                reason: format!("episode_starts must start at 0 and increase below {n} frames, found {starts:?}"),
            });
        }
        let labels = match file.tensor("labels") {
            Err(_) => None,
            Ok(_) => Some(pairs("labels")?),
        };
        let outcomes = Episodes::outcomes(&file, n)?;
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| Error::Malformed {
            what: "episodes file",
            reason: format!("{e:?}"),
        })?;
        let frame_hz = header.metadata().as_ref().and_then(|m| m.get(FRAME_HZ));
        let frame_hz = frame_hz
            .map(|text| crate::metadata::parse_frame_hz(FRAME_HZ, text))
            .transpose()?;
        Ok(Episodes {
            height,
            width,
            frames: frames.data().to_vec(),
            actions,
            labels,
            outcomes,
            starts: starts.into_iter().map(|s| s as usize).collect(),
            frame_hz,
        })
    }

    /// The optional `reward` (f32, finite) and `on_road` (u8, 0 or 1), `[n]` each: both or
    /// neither (`weights/TRAINING_FILES.md`).
    fn outcomes(file: &SafeTensors<'_>, n: usize) -> Result<Option<(Vec<f32>, Vec<u8>)>> {
        let bad = |reason: alloc::string::String| Error::Episodes { reason };
        let (reward, on_road) = match (file.tensor("reward"), file.tensor("on_road")) {
            (Err(_), Err(_)) => return Ok(None),
            (Ok(r), Ok(o)) => (r, o),
            _ => return Err(bad("`reward` and `on_road` come together or not at all".into())),
        };
        if reward.dtype() != Dtype::F32 || on_road.dtype() != Dtype::U8 {
            return Err(bad("`reward` must be F32 and `on_road` U8".into()));
        }
        if reward.shape() != [n] || on_road.shape() != [n] {
            return Err(bad(format!(
                "`reward` and `on_road` must have one value per frame ({n}), found {:?} and {:?}",
                reward.shape(),
                on_road.shape()
            )));
        }
        let rewards = f32_values(reward.data());
        crate::error::expect_finite("reward", &rewards)?;
        let on_road = on_road.data().to_vec();
        if on_road.iter().any(|&v| v > 1) {
            return Err(bad("`on_road` values must be 0 or 1".into()));
        }
        Ok(Some((rewards, on_road)))
    }

    #[cfg(feature = "std")]
    fn from_gzip(bytes: &[u8]) -> Result<Episodes> {
        use std::io::Read;
        let mut inflated = Vec::new();
        flate2::read::MultiGzDecoder::new(bytes)
            .read_to_end(&mut inflated)
            .map_err(|e| Error::Malformed {
                what: "gzipped episodes file",
                reason: e.to_string(),
            })?;
        if inflated.starts_with(&GZIP_MAGIC) {
            return Err(Error::Malformed {
                what: "gzipped episodes file",
                reason: "gzipped twice".into(),
            });
        }
        Episodes::from_bytes(&inflated)
    }

    #[cfg(not(feature = "std"))]
    fn from_gzip(_: &[u8]) -> Result<Episodes> {
        Err(Error::Malformed {
            what: "episodes file",
            reason: "it is gzipped, and this build has no gzip reader: decompress it first (gunzip) or enable the `std` feature".into(),
        })
    }

    /// Number of episodes.
    pub fn len(&self) -> usize {
        self.starts.len()
    }

    /// Frames per second (the file's `frame_hz` metadata; `None` if it has none): what the
    /// trainers write as a model's `drivesim.frame_hz` ([`crate::Model::frame_hz`]).
    pub fn frame_hz(&self) -> Option<f32> {
        self.frame_hz
    }

    /// Whether there is no episode (never, for a loaded file).
    pub fn is_empty(&self) -> bool {
        self.starts.is_empty()
    }

    /// `(height, width)` of every frame.
    pub fn frame_size(&self) -> (usize, usize) {
        (self.height, self.width)
    }

    /// Episode `i`.
    pub fn episode(&self, i: usize) -> Result<Episode<'_>> {
        let start = *self.starts.get(i).ok_or(Error::OutOfRange {
            what: "episode",
            index: i,
            len: self.len(),
        })?;
        let end = self
            .starts
            .get(i + 1)
            .copied()
            .unwrap_or(self.actions.len() / Episodes::ACTION_DIM);
        let frame_len = self.height * self.width * Episodes::CHANNELS;
        Ok(Episode {
            height: self.height,
            width: self.width,
            frames: &self.frames[start * frame_len..end * frame_len],
            actions: &self.actions[start * Episodes::ACTION_DIM..end * Episodes::ACTION_DIM],
            labels: self
                .labels
                .as_ref()
                .map(|l| &l[start * Episodes::ACTION_DIM..end * Episodes::ACTION_DIM]),
            rewards: self.outcomes.as_ref().map(|(r, _)| &r[start..end]),
            on_road: self.outcomes.as_ref().map(|(_, o)| &o[start..end]),
        })
    }
}

/// Sizes, not the megabytes of pixels.
impl core::fmt::Debug for Episodes {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Episodes")
            .field("episodes", &self.len())
            .field("frames", &(self.actions.len() / Episodes::ACTION_DIM))
            .field("frame_size", &self.frame_size())
            .finish_non_exhaustive()
    }
}

impl core::fmt::Debug for Episode<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Episode")
            .field("frames", &self.len())
            .field("frame_size", &(self.height, self.width))
            .finish_non_exhaustive()
    }
}
