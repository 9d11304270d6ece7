//! The generator: a latent code to a frame.

use crate::layers::{for_each_item, run_convs, ConvLayer, DenseLayer};
use crate::plan::StackBuffers;
use crate::pool::Exec;
use crate::weights::{read_batch_norm, Init, TensorSource};
use crate::{Config, Result};
use alloc::format;
use alloc::vec::Vec;
use drivesim_kernels::pack::permute_rows_chw_to_hwc;
use drivesim_kernels::{Activation, Tensor};

pub(crate) struct Generator {
    /// `fc` with `bn0` folded in and ReLU fused; rows permuted to HWC order.
    fc: DenseLayer,
    deconvs: Vec<ConvLayer>,
}

impl Generator {
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Self> {
        let (z, flat) = (config.z_dim, config.flat_len());
        let (c, (h, w)) = (config.top_channels(), config.top_size());
        // fc is followed by a reshape to CHW and bn0: fold bn0 in, reorder rows to HWC. The
        // fold changes the values, so this matrix is kept in f32 whatever the file stores.
        let weight = src.f32("generator.fc.weight", &[flat, z], Init::FanIn(z))?;
        let bias = src.f32("generator.fc.bias", &[flat], Init::FanIn(z))?;
        let bn0 = read_batch_norm(src, "generator.bn0", c)?;
        let (weight, bias) = permute_rows_chw_to_hwc(&weight, &bias, z, c, h, w, Some(bn0.view()));
        let fc = DenseLayer::new(Tensor::F32(weight), bias, flat, z, Activation::Relu);

        let deconvs = config
            .generator_convs()
            .enumerate()
            .map(|(i, shape)| {
                let last = i + 1 == config.layers;
                let bn = (!last).then(|| format!("generator.bn{}", i + 1));
                let act = if last { Activation::Tanh } else { Activation::Relu };
                ConvLayer::load(src, &format!("generator.deconv{}", i + 1), bn.as_deref(), shape, act)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Generator { fc, deconvs })
    }

    /// Generates one frame per code of `z` (at most the planned batch, already validated).
    pub fn forward(&self, exec: Exec<'_>, buf: &mut StackBuffers, z: &[f32], frames: &mut [f32]) {
        let flat = &mut buf.flat[..z.len() / self.fc.cols * self.fc.rows];
        self.fc.run(exec, z, flat);
        let frame_len = self.deconvs.last().map_or(0, |d| d.shape.output.len());
        for_each_item(
            exec,
            &mut buf.planes,
            flat,
            self.fc.rows,
            frames,
            frame_len,
            |exec, planes, features, frame| {
                self.deconvs[0].shape.input.write_interior(planes.input(), features);
                run_convs(exec, &self.deconvs, planes, frame);
            },
        );
    }
}
