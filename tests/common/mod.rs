//! Shared by the integration tests: reading the PyTorch fixtures and comparing outputs.
#![allow(dead_code)] // each test binary uses a different part

use safetensors::{Dtype, SafeTensors, View};
use std::borrow::Cow;
use std::path::PathBuf;

#[path = "../../kernels/tests/common/mod.rs"]
mod kernel_common;
#[allow(unused_imports)] // not every test binary runs on every level
pub use kernel_common::{levels, values, Rng};

/// A small config for the tests of whole calls (environments, candidate rollouts): quick,
/// yet every network has several panels of rows.
pub const SMALL: drivesim::Config = drivesim::Config {
    height: 16,
    width: 32,
    base_channels: 3,
    z_dim: 12,
    hidden_dim: 40,
    ..drivesim::Config::COMMA
};

/// The smallest config of the no-allocation tests of the heads and the policy: every buffer
/// small, so that an allocation stands out.
pub const TINY: drivesim::Config = drivesim::Config {
    height: 16,
    width: 32,
    base_channels: 2,
    z_dim: 12,
    hidden_dim: 24,
    ..drivesim::Config::COMMA
};

/// The PyTorch fixtures (`weights/drivesim_reference/fixtures.py`); `spread_f32`'s transition has the spread head.
pub const FIXTURES: [&str; 6] = [
    "small_f32",
    "small_f16",
    "tiny_bf16",
    "tall_f32",
    "wide_f32",
    "spread_f32",
];

pub fn fixture_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// Relative tolerance against PyTorch: 1e-4 for f32 weights, 1e-3 for half-precision files.
pub fn tolerance(name: &str) -> f32 {
    if name.ends_with("f32") {
        1e-4
    } else {
        1e-3
    }
}

/// The float32 tensors of `NAME.io.safetensors`, written by `weights/drivesim_reference/fixtures.py`.
pub struct Io {
    bytes: Vec<u8>,
}

impl Io {
    pub fn load(name: &str) -> Io {
        Io::open(&format!("{name}.io.safetensors"))
    }

    /// Any float32 fixture file, by its file name.
    pub fn open(file: &str) -> Io {
        Io {
            bytes: std::fs::read(fixture_path(file)).unwrap_or_else(|e| panic!("fixture {file}: {e}")),
        }
    }

    /// A string of the file's metadata.
    pub fn metadata(&self, key: &str) -> String {
        let (_, metadata) = SafeTensors::read_metadata(&self.bytes).expect("fixture parses");
        metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get(key).cloned())
            .unwrap_or_else(|| panic!("no metadata {key}"))
    }

    pub fn get(&self, tensor: &str) -> (Vec<usize>, Vec<f32>) {
        let file = SafeTensors::deserialize(&self.bytes).expect("fixture parses");
        let view = file.tensor(tensor).unwrap_or_else(|_| panic!("fixture lacks {tensor}"));
        assert_eq!(view.dtype(), Dtype::F32);
        let values = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        (view.shape().to_vec(), values)
    }

    pub fn values(&self, tensor: &str) -> Vec<f32> {
        self.get(tensor).1
    }
}

/// max |found - expected| / max |expected|: the error relative to the tensor's scale.
pub fn relative_error(found: &[f32], expected: &[f32]) -> f32 {
    assert_eq!(found.len(), expected.len());
    let scale = expected.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-12);
    found
        .iter()
        .zip(expected)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
        / scale
}

/// One tensor of a safetensors file a test writes.
pub struct Tensor {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl Tensor {
    pub fn new(dtype: Dtype, shape: Vec<usize>, data: Vec<u8>) -> Tensor {
        Tensor { dtype, shape, data }
    }
}

impl View for &Tensor {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

/// `bytes` (a weight file) with the f32 tensors `added` (name, shape, values) added, or in
/// place of the file's own of the same names.
pub fn with_f32_tensors(bytes: &[u8], added: &[(&str, Vec<usize>, Vec<f32>)]) -> Vec<u8> {
    let file = SafeTensors::deserialize(bytes).unwrap();
    let (_, metadata) = SafeTensors::read_metadata(bytes).unwrap();
    let mut tensors: Vec<(String, Tensor)> = file
        .tensors()
        .into_iter()
        .filter(|(n, _)| !added.iter().any(|(a, ..)| a == n))
        .map(|(n, v)| (n, Tensor::new(v.dtype(), v.shape().to_vec(), v.data().to_vec())))
        .collect();
    for (name, shape, values) in added {
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        tensors.push((name.to_string(), Tensor::new(Dtype::F32, shape.clone(), data)));
    }
    let views = tensors.iter().map(|(n, t)| (n.clone(), t));
    safetensors::serialize(views, metadata.metadata().clone()).unwrap()
}

/// `file` with a texture net of width `width` (`transition.texture.*`, values from `seed`), for
/// the config of `file`'s metadata.
pub fn with_texture(file: &[u8], width: usize, seed: u64) -> Vec<u8> {
    let (_, metadata) = SafeTensors::read_metadata(file).unwrap();
    let config = metadata.metadata().as_ref().unwrap()["drivesim.config"].clone();
    let config: serde_json::Value = serde_json::from_str(&config).unwrap();
    let z = config["z_dim"].as_u64().unwrap() as usize;
    let cols = z + config["hidden_dim"].as_u64().unwrap() as usize;
    let net = [
        (
            "transition.texture.hidden.weight",
            vec![width, cols],
            values(seed, width * cols, 0.3),
        ),
        (
            "transition.texture.hidden.bias",
            vec![width],
            values(seed + 1, width, 0.1),
        ),
        (
            "transition.texture.output.weight",
            vec![z, width],
            values(seed + 2, z * width, 0.4),
        ),
        ("transition.texture.output.bias", vec![z], values(seed + 3, z, 0.1)),
    ];
    with_f32_tensors(file, &net)
}
