//! The encoder: a frame to the VAE's mean and log-sigma.

use crate::layers::{for_each_item, run_convs, ConvLayer, DenseLayer};
use crate::plan::StackBuffers;
use crate::pool::Exec;
use crate::weights::{Init, TensorSource};
use crate::{Config, Result};
use alloc::format;
use alloc::vec::Vec;
use drivesim_kernels::pack::permute_cols_chw_to_hwc;
use drivesim_kernels::{Activation, Tensor};

/// `LeakyReLU(0.2)` after every encoder convolution.
pub(crate) const LEAKY_SLOPE: f32 = 0.2;

pub(crate) struct Encoder {
    convs: Vec<ConvLayer>,
    mean: DenseLayer,
    logsigma: DenseLayer,
}

impl Encoder {
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Self> {
        let convs = config
            .encoder_convs()
            .enumerate()
            .map(|(i, shape)| {
                let bn = (i > 0).then(|| format!("encoder.bn{i}"));
                let act = Activation::LeakyRelu(LEAKY_SLOPE);
                ConvLayer::load(src, &format!("encoder.conv{i}"), bn.as_deref(), shape, act)
            })
            .collect::<Result<Vec<_>>>()?;
        let (flat, z) = (config.flat_len(), config.z_dim);
        let (c, (h, w)) = (config.top_channels(), config.top_size());
        let mut head = |name: &str, act| -> Result<DenseLayer> {
            // PyTorch flattens CHW; the convolutions leave HWC: permute the columns once.
            let weights = match src.tensor(&format!("encoder.{name}.weight"), &[z, flat], Init::FanIn(flat))? {
                Tensor::F32(v) => Tensor::F32(permute_cols_chw_to_hwc(&v, z, c, h, w)),
                Tensor::F16(v) => Tensor::F16(permute_cols_chw_to_hwc(&v, z, c, h, w)),
            };
            let bias = src.f32(&format!("encoder.{name}.bias"), &[z], Init::FanIn(flat))?;
            Ok(DenseLayer::new(weights, bias, z, flat, act))
        };
        let mean = head("mean", Activation::Identity)?;
        let logsigma = head("logsigma", Activation::Tanh)?;
        Ok(Encoder { convs, mean, logsigma })
    }

    /// Encodes `frames` (whole HWC frames, at most the planned batch, already validated).
    pub fn forward(
        &self,
        exec: Exec<'_>,
        buf: &mut StackBuffers,
        frames: &[f32],
        mean: &mut [f32],
        logsigma: Option<&mut [f32]>,
    ) {
        let frame_len = self.convs[0].shape.input.interior_len();
        let flat_len = self.mean.cols;
        let flat = &mut buf.flat[..frames.len() / frame_len * flat_len];
        for_each_item(
            exec,
            &mut buf.planes,
            frames,
            frame_len,
            flat,
            flat_len,
            |exec, planes, frame, flat| {
                self.convs[0].shape.input.write_interior(planes.input(), frame);
                run_convs(exec, &self.convs, planes, flat);
            },
        );
        self.mean.run(exec, flat, mean);
        if let Some(logsigma) = logsigma {
            self.logsigma.run(exec, flat, logsigma);
        }
    }
}
