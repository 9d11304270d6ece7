//! Where the network builders get their tensors: a safetensors file, or a seeded random draw.
//! Both hand out tensors in PyTorch layout; the networks pack them for the kernels.

use crate::metadata::Described;
use crate::{Config, Error, Result};
use alloc::format;
use alloc::string::{String, ToString};
use alloc::vec::Vec;
use drivesim_kernels::f16;
use drivesim_kernels::pack::BatchNorm;
use drivesim_kernels::Tensor;
use half::slice::HalfFloatSliceExt;
use safetensors::{Dtype, SafeTensors};

/// The prefix of the VAE-GAN discriminator's tensors, which a weight file may carry so that
/// training can resume from it (`weights/README.md`); inference does not read them.
pub(crate) const DISCRIMINATOR_PREFIX: &str = "discriminator.";

/// How a random source draws a tensor (PyTorch's default initialisation, roughly).
#[derive(Clone, Copy)]
pub(crate) enum Init {
    /// Uniform in `±1/sqrt(fan_in)`.
    FanIn(usize),
    Zeros,
    Ones,
}

/// A provider of named tensors in PyTorch layout with a known shape.
pub(crate) trait TensorSource {
    fn tensor(&mut self, name: &str, shape: &[usize], init: Init) -> Result<Tensor>;

    fn f32(&mut self, name: &str, shape: &[usize], init: Init) -> Result<Vec<f32>> {
        Ok(self.tensor(name, shape, init)?.into_f32())
    }

    /// Whether the source has a tensor whose name starts with `prefix` (for the optional
    /// networks: a random source has none).
    fn contains(&self, _prefix: &str) -> bool {
        false
    }

    /// The stored shape of tensor `name`, where the source has it (for the optional networks,
    /// whose sizes the config does not give).
    fn shape(&self, _name: &str) -> Option<Vec<usize>> {
        None
    }

    /// Called once every tensor was read: a file must hold no others.
    fn finish(&self) -> Result<()> {
        Ok(())
    }
}

/// A parsed safetensors weight file, borrowing its bytes.
pub(crate) struct SafetensorsSource<'a> {
    file: SafeTensors<'a>,
    /// The tensors handed out so far.
    read: Vec<String>,
}

fn malformed(e: safetensors::SafeTensorError) -> Error {
    Error::Malformed {
        what: "weight file",
        reason: format!("{e:?}"),
    }
}

/// Little-endian values from tensor bytes, which carry no alignment guarantee: one copy
/// (safetensors stores little-endian, which is what every target of the kernels is).
fn values<T: bytemuck::Pod>(bytes: &[u8]) -> Vec<T> {
    #[cfg(target_endian = "big")]
    compile_error!("safetensors are little-endian; drivesim reads them on little-endian targets only");
    bytemuck::pod_collect_to_vec(bytes)
}

/// The index and value of the first non-finite value, as a [`Error::BadWeight`].
fn expect_finite_weights(name: &str, values: impl Iterator<Item = f32>) -> Result<()> {
    for (index, value) in values.enumerate() {
        if !value.is_finite() {
            return Err(Error::BadWeight {
                name: name.to_string(),
                index,
                value,
                expected: "a finite number",
            });
        }
    }
    Ok(())
}

impl<'a> SafetensorsSource<'a> {
    /// Parses the header, the config and what the file describes (actions, frame rate, if
    /// given); tensors are read on demand.
    pub(crate) fn parse(bytes: &'a [u8]) -> Result<(Config, Described, Self)> {
        let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(malformed)?;
        let json = metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get(Config::METADATA_KEY))
            .ok_or_else(|| Error::Metadata {
                reason: format!("no `{}` key in the file's metadata", Config::METADATA_KEY),
            })?;
        let config = Config::from_json(json)?;
        let key = |k: &str| metadata.metadata().as_ref().and_then(|m| m.get(k));
        let described = Described::read(&key, config.action_dim)?;
        let file = SafeTensors::deserialize(bytes).map_err(malformed)?;
        // One supported dtype per file (`weights/README.md`): name the first tensor, in name
        // order, that breaks it.
        let mut tensors = file.tensors();
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        let supported = [Dtype::F32, Dtype::F16, Dtype::BF16];
        if let Some((name, view)) = tensors.iter().find(|(_, v)| !supported.contains(&v.dtype())) {
            return Err(Error::Dtype {
                name: name.clone(),
                found: format!("{:?}", view.dtype()),
            });
        }
        if let Some((_, view)) = tensors.first() {
            if let Some((name, other)) = tensors.iter().find(|(_, v)| v.dtype() != view.dtype()) {
                return Err(Error::MixedDtypes {
                    name: name.clone(),
                    found: format!("{:?}", other.dtype()),
                    expected: format!("{:?}", view.dtype()),
                });
            }
        }
        Ok((config, described, SafetensorsSource { file, read: Vec::new() }))
    }
}

impl TensorSource for SafetensorsSource<'_> {
    fn contains(&self, prefix: &str) -> bool {
        self.file.names().iter().any(|n| n.starts_with(prefix))
    }

    fn shape(&self, name: &str) -> Option<Vec<usize>> {
        self.file.tensor(name).ok().map(|view| view.shape().to_vec())
    }

    fn tensor(&mut self, name: &str, shape: &[usize], _init: Init) -> Result<Tensor> {
        let view = self
            .file
            .tensor(name)
            .map_err(|_| Error::MissingTensor { name: name.to_string() })?;
        if view.shape() != shape {
            return Err(Error::Shape {
                name: name.to_string(),
                expected: shape.to_vec(),
                found: view.shape().to_vec(),
            });
        }
        self.read.push(name.to_string());
        let data = view.data();
        let tensor = match view.dtype() {
            Dtype::F32 => Tensor::F32(values(data)),
            Dtype::F16 => Tensor::F16(values(data)),
            Dtype::BF16 => {
                let halves: Vec<half::bf16> = values(data);
                let mut v = alloc::vec![0.0; halves.len()];
                halves.convert_to_f32_slice(&mut v);
                Tensor::F32(v)
            }
            other => {
                return Err(Error::Dtype {
                    name: name.to_string(),
                    found: format!("{other:?}"),
                })
            }
        };
        match &tensor {
            Tensor::F32(v) => expect_finite_weights(name, v.iter().copied())?,
            Tensor::F16(v) => expect_finite_weights(name, v.iter().map(|x| x.to_f32()))?,
        }
        Ok(tensor)
    }

    fn finish(&self) -> Result<()> {
        let mut names = self.file.names();
        names.sort();
        let unread = |n: &&str| !n.starts_with(DISCRIMINATOR_PREFIX) && !self.read.iter().any(|r| r == *n);
        match names.into_iter().find(unread) {
            Some(name) => Err(Error::UnexpectedTensor { name: name.to_string() }),
            None => Ok(()),
        }
    }
}

/// The dtype a random model stores its weights in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WeightDtype {
    /// Single precision.
    F32,
    /// Values rounded to f16; dense layers keep them as f16 in memory, as for an F16 file.
    F16,
}

/// Seeded pseudo-random weights, for tests and benchmarks (SplitMix64: tiny and portable).
pub(crate) struct RandomSource {
    state: u64,
    dtype: WeightDtype,
}

impl RandomSource {
    pub(crate) fn new(seed: u64, dtype: WeightDtype) -> Self {
        RandomSource { state: seed, dtype }
    }

    /// Uniform in [-1, 1).
    fn next_signed(&mut self) -> f32 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 40) as f32 / (1u64 << 23) as f32) - 1.0
    }
}

impl TensorSource for RandomSource {
    fn tensor(&mut self, _name: &str, shape: &[usize], init: Init) -> Result<Tensor> {
        // The config's bounds keep the product from overflowing; the allocator may still refuse.
        let len: usize = shape.iter().product();
        let mut values: Vec<f32> = Vec::new();
        values.try_reserve_exact(len).map_err(|_| Error::OutOfMemory {
            what: "the model's weights",
            bytes: len.checked_mul(4),
        })?;
        match init {
            Init::Zeros => values.resize(len, 0.0),
            Init::Ones => values.resize(len, 1.0),
            Init::FanIn(fan_in) => {
                let bound = (1.0 / drivesim_kernels::math::sqrt(fan_in.max(1) as f64)) as f32;
                values.extend((0..len).map(|_| bound * self.next_signed()));
            }
        }
        Ok(match self.dtype {
            WeightDtype::F32 => Tensor::F32(values),
            WeightDtype::F16 => Tensor::F16(values.iter().map(|&v| f16::from_f32(v)).collect()),
        })
    }
}

/// BatchNorm parameters as read from a source.
pub(crate) struct BatchNormParams([Vec<f32>; 4]);

impl BatchNormParams {
    pub fn view(&self) -> BatchNorm<'_> {
        let [weight, bias, running_mean, running_var] = &self.0;
        BatchNorm {
            weight,
            bias,
            running_mean,
            running_var,
        }
    }
}

/// Reads BatchNorm `name`'s four tensors; a negative running variance is an error.
pub(crate) fn read_batch_norm(src: &mut dyn TensorSource, name: &str, channels: usize) -> Result<BatchNormParams> {
    let mut read = |part: &str, init| src.f32(&format!("{name}.{part}"), &[channels], init);
    let params = [
        read("weight", Init::Ones)?,
        read("bias", Init::Zeros)?,
        read("running_mean", Init::Zeros)?,
        read("running_var", Init::Ones)?,
    ];
    if let Some(index) = params[3].iter().position(|&v| v < 0.0) {
        return Err(Error::BadWeight {
            name: format!("{name}.running_var"),
            index,
            value: params[3][index],
            expected: "a variance, at least 0",
        });
    }
    Ok(BatchNormParams(params))
}

/// The weight file `bytes` with the tensors of `replace` (name, shape, PyTorch-layout values)
/// put in place of the stored ones or, where the file has no such tensor, added; every tensor
/// written in `dtype` (or the file's own dtype), the metadata kept but for what `trained_on`
/// gives (`drivesim.actions`, `drivesim.frame_hz`, `drivesim.discount`): how a trainer saves what it trained. The
/// file is validated as
/// [`SafetensorsSource::parse`] does, and each replacement must have its tensor's shape, but
/// under `group` (a prefix such as the policy's): the file's tensors there are left out, and the
/// replacements are the whole group, in their own shapes.
#[cfg(all(feature = "std", feature = "train"))]
pub(crate) fn rewrite(
    bytes: &[u8],
    replace: &[(&str, &[usize], &[f32])],
    group: Option<&str>,
    dtype: Option<WeightDtype>,
    trained_on: crate::metadata::TrainedOn<'_>,
) -> Result<Vec<u8>> {
    let (config, _, mut src) = SafetensorsSource::parse(bytes)?;
    let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(malformed)?;
    let mut metadata = metadata.metadata().clone().unwrap_or_default();
    crate::metadata::write(&trained_on, config.action_dim, &mut metadata)?;
    let in_group = |name: &str| group.is_some_and(|prefix| name.starts_with(prefix));
    let mut names: Vec<String> = src
        .file
        .names()
        .into_iter()
        .filter(|n| !in_group(n))
        .map(String::from)
        .collect();
    names.sort();
    let stored = names.first().map_or(Ok(Dtype::F32), |n| {
        src.file.tensor(n).map(|v| v.dtype()).map_err(malformed)
    })?;
    let dtype = match dtype {
        Some(WeightDtype::F32) => Dtype::F32,
        Some(WeightDtype::F16) => Dtype::F16,
        None => stored,
    };
    let added = replace.iter().filter(|(name, ..)| !names.iter().any(|n| n == name));
    let added: Vec<String> = added.map(|(name, ..)| name.to_string()).collect();
    names.extend(added);
    let mut encoded = Vec::with_capacity(names.len());
    for name in &names {
        let stored = match in_group(name) {
            true => None,
            false => src.file.tensor(name).ok().map(|view| view.shape().to_vec()),
        };
        let values = match (replace.iter().find(|(n, ..)| *n == name.as_str()), stored) {
            (Some((_, shape, values)), stored) => {
                let expected = stored.unwrap_or_else(|| shape.to_vec());
                if *shape != expected || values.len() != shape.iter().product::<usize>() {
                    return Err(Error::Shape {
                        name: name.clone(),
                        expected,
                        found: shape.to_vec(),
                    });
                }
                (expected, values.to_vec())
            }
            (None, Some(shape)) => {
                let values = src.tensor(name, &shape, Init::Zeros)?.into_f32();
                (shape, values)
            }
            (None, None) => unreachable!("every name is stored or replaced"),
        };
        let (shape, values) = values;
        let data: Vec<u8> = match dtype {
            Dtype::F16 => bytemuck::cast_slice(&values.iter().map(|&v| f16::from_f32(v)).collect::<Vec<_>>()).to_vec(),
            Dtype::BF16 => {
                bytemuck::cast_slice(&values.iter().map(|&v| half::bf16::from_f32(v)).collect::<Vec<_>>()).to_vec()
            }
            _ => bytemuck::cast_slice(&values).to_vec(),
        };
        encoded.push((name.clone(), shape, data));
    }
    let views = encoded
        .iter()
        .map(|(name, shape, data)| {
            safetensors::tensor::TensorView::new(dtype, shape.clone(), data)
                .map(|view| (name.clone(), view))
                .map_err(malformed)
        })
        .collect::<Result<Vec<_>>>()?;
    let bytes = safetensors::serialize(views, Some(metadata)).map_err(malformed)?;
    Ok(sort_metadata(bytes))
}

/// A safetensors file with its `__metadata__` entries in key order. `safetensors::serialize`
/// writes them in a `HashMap`'s order, which changes from run to run, so that two runs of a
/// deterministic trainer would write different bytes. The sorted header has the same length
/// (the same entries, written as compactly), so it is rewritten in place.
#[cfg(feature = "std")]
pub(crate) fn sort_metadata(mut bytes: Vec<u8>) -> Vec<u8> {
    use serde_json::{Map, Value};
    let Some(len) = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")) as usize)
    else {
        return bytes;
    };
    let Some(Ok(Value::Object(mut header))) = bytes.get(8..8 + len).map(serde_json::from_slice::<Value>) else {
        return bytes;
    };
    if let Some(Value::Object(metadata)) = header.remove("__metadata__") {
        let mut entries: Vec<(String, Value)> = metadata.into_iter().collect();
        entries.sort_by(|a, b| a.0.cmp(&b.0));
        header.insert(
            "__metadata__".to_string(),
            Value::Object(entries.into_iter().collect::<Map<_, _>>()),
        );
    }
    let sorted = serde_json::to_vec(&Value::Object(header)).unwrap_or_default();
    if sorted.len() <= len {
        let spaces = core::iter::repeat_n(b' ', len - sorted.len());
        bytes.splice(8..8 + len, sorted.into_iter().chain(spaces));
    }
    bytes
}
