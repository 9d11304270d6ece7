//! The model's nine integers, and the layer shapes derived from them.

use crate::{Error, Result};
use alloc::format;
use alloc::string::{String, ToString};
use drivesim_kernels::{ConvKind, ConvShape, Plane};

/// The architecture of a model: everything needed to know every tensor's shape.
///
/// Stored in a weight file as the JSON metadata `drivesim.config` (see `weights/README.md`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Config {
    /// Frame height in pixels; a multiple of 16, at most 4096.
    pub height: usize,
    /// Frame width in pixels; a multiple of 16, at most 4096.
    pub width: usize,
    /// Colour channels of a frame (3 for RGB); at most 16.
    pub channels: usize,
    /// Channels of the first encoder convolution (`b`); later layers use 2b, 4b, 8b. At most 1024.
    pub base_channels: usize,
    /// Convolutions in the encoder and the generator; must be 4.
    pub layers: usize,
    /// Convolution kernel size; must be 5.
    pub kernel: usize,
    /// Size of the latent code z; at most 8192.
    pub z_dim: usize,
    /// Size of the transition RNN's hidden state h; at most 8192.
    pub hidden_dim: usize,
    /// Size of the control vector c; 2 for (speed, steering). At most 64.
    pub action_dim: usize,
}

/// Upper bounds, far above any sensible model, that keep every size of the model and of a
/// frame's buffers within 64-bit arithmetic; batch sizes are checked by [`crate::Plan`].
const MAX_SIDE: usize = 4096;
const MAX_CHANNELS: usize = 16;
const MAX_BASE_CHANNELS: usize = 1024;
const MAX_CODE: usize = 8192;
const MAX_ACTIONS: usize = 64;

impl Config {
    /// The comma.ai configuration: 80x160 RGB frames, b = 64, z = hidden = 512, 2 controls.
    pub const COMMA: Config = Config {
        height: 80,
        width: 160,
        channels: 3,
        base_channels: 64,
        layers: 4,
        kernel: 5,
        z_dim: 512,
        hidden_dim: 512,
        action_dim: 2,
    };

    /// The JSON metadata key the config is stored under.
    pub const METADATA_KEY: &'static str = "drivesim.config";

    const FIELDS: [&'static str; 9] = [
        "height",
        "width",
        "channels",
        "base_channels",
        "layers",
        "kernel",
        "z_dim",
        "hidden_dim",
        "action_dim",
    ];

    fn values(&self) -> [usize; 9] {
        [
            self.height,
            self.width,
            self.channels,
            self.base_channels,
            self.layers,
            self.kernel,
            self.z_dim,
            self.hidden_dim,
            self.action_dim,
        ]
    }

    fn from_values(v: [usize; 9]) -> Config {
        let [height, width, channels, base_channels, layers, kernel, z_dim, hidden_dim, action_dim] = v;
        Config {
            height,
            width,
            channels,
            base_channels,
            layers,
            kernel,
            z_dim,
            hidden_dim,
            action_dim,
        }
    }

    /// Checks that the model can be built with this config.
    pub fn validate(&self) -> Result<()> {
        let check = |field, ok: bool, expected, found| {
            if ok {
                Ok(())
            } else {
                Err(Error::Config { field, expected, found })
            }
        };
        check("layers", self.layers == 4, "4", self.layers)?;
        check("kernel", self.kernel == 5, "5", self.kernel)?;
        for (field, side) in [("height", self.height), ("width", self.width)] {
            check(field, side > 0 && side % 16 == 0, "a positive multiple of 16", side)?;
            check(field, side <= MAX_SIDE, "at most 4096", side)?;
        }
        for (field, n, max, expected) in [
            ("channels", self.channels, MAX_CHANNELS, "1 to 16"),
            ("base_channels", self.base_channels, MAX_BASE_CHANNELS, "1 to 1024"),
            ("z_dim", self.z_dim, MAX_CODE, "1 to 8192"),
            ("hidden_dim", self.hidden_dim, MAX_CODE, "1 to 8192"),
            ("action_dim", self.action_dim, MAX_ACTIONS, "1 to 64"),
        ] {
            check(field, (1..=max).contains(&n), expected, n)?;
        }
        Ok(())
    }

    /// Parses the `drivesim.config` JSON object and validates it.
    pub fn from_json(json: &str) -> Result<Config> {
        let bad = |reason: String| Error::Metadata {
            reason: format!("`{}`: {reason}", Config::METADATA_KEY),
        };
        let value: serde_json::Value = serde_json::from_str(json).map_err(|e| bad(format!("{e} in {json:?}")))?;
        let object = value
            .as_object()
            .ok_or_else(|| bad(format!("expected a JSON object, found {json:?}")))?;
        let mut values = [0usize; 9];
        for (slot, field) in values.iter_mut().zip(Config::FIELDS) {
            let v = object
                .get(field)
                .ok_or_else(|| bad(format!("missing key `{field}` in {json:?}")))?;
            *slot = v
                .as_u64()
                .and_then(|n| usize::try_from(n).ok())
                .ok_or_else(|| bad(format!("`{field}`: expected a non-negative integer, found {v}")))?;
        }
        let config = Config::from_values(values);
        config.validate()?;
        Ok(config)
    }

    /// The `drivesim.config` JSON object.
    pub fn to_json(&self) -> String {
        let body: alloc::vec::Vec<String> = Config::FIELDS
            .iter()
            .zip(self.values())
            .map(|(k, v)| format!("\"{k}\":{v}"))
            .collect();
        let mut s = "{".to_string();
        s.push_str(&body.join(","));
        s.push('}');
        s
    }

    /// Values in one frame: `height * width * channels`.
    pub const fn frame_len(&self) -> usize {
        self.height * self.width * self.channels
    }

    /// Channels after the last encoder convolution: `8b`.
    pub const fn top_channels(&self) -> usize {
        self.base_channels << (self.layers - 1)
    }

    /// Height and width after the last encoder convolution: `H/16`, `W/16`.
    pub const fn top_size(&self) -> (usize, usize) {
        (self.height >> self.layers, self.width >> self.layers)
    }

    /// Size of the flattened feature map between the convolutions and the dense layers.
    pub const fn flat_len(&self) -> usize {
        let (h, w) = self.top_size();
        self.top_channels() * h * w
    }

    /// The shapes of the encoder's convolutions.
    pub(crate) fn encoder_convs(&self) -> impl Iterator<Item = ConvShape> {
        let config = *self;
        let (k, b) = (config.kernel, config.base_channels);
        let halo = ConvKind::Down.input_halo(k);
        let mut input = Plane::new(config.height, config.width, config.channels, halo);
        (0..config.layers).map(move |i| {
            // The last output feeds the dense heads, which need no border.
            let last = i + 1 == config.layers;
            let shape = ConvShape::new(ConvKind::Down, k, input, b << i, if last { 0 } else { halo });
            input = shape.output;
            shape
        })
    }

    /// The shapes of the generator's transposed convolutions.
    pub(crate) fn generator_convs(&self) -> impl Iterator<Item = ConvShape> {
        let config = *self;
        let k = config.kernel;
        let (c, (h, w)) = (config.top_channels(), config.top_size());
        let halo = ConvKind::Up.input_halo(k);
        let mut input = Plane::new(h, w, c, halo);
        (1..=config.layers).map(move |i| {
            // The last layer writes the frame: no border.
            let (out_channels, out_halo) = if i == config.layers {
                (config.channels, 0)
            } else {
                (c >> i, halo)
            };
            let shape = ConvShape::new(ConvKind::Up, k, input, out_channels, out_halo);
            input = shape.output;
            shape
        })
    }
}
