//! The generator: a latent code to a frame.

use crate::layers::{
    for_each_item, plane_sets, read_batch_norm, run_convs, ConvLayer, DenseLayer, DenseWeights, Planes,
};
use crate::pool::Exec;
use crate::weights::{Init, TensorSource};
use crate::{Config, Result};
use alloc::format;
use alloc::vec::Vec;
use drivesim_kernels::pack::permute_rows_chw_to_hwc;
use drivesim_kernels::{Activation, ConvKind, ConvShape, Plane};

pub(crate) struct Generator {
    /// `fc` with `bn0` folded in and ReLU fused; rows permuted to HWC order.
    fc: DenseLayer,
    deconvs: Vec<ConvLayer>,
}

/// Per-simulator scratch of the generator, sized once.
pub(crate) struct GeneratorBuffers {
    /// `fc`'s output for each code of a batch.
    flat: Vec<f32>,
    /// The padded input plane of every transposed convolution: one set, or one per thread
    /// when threads take whole codes of a batch.
    planes: Vec<Planes>,
}

impl GeneratorBuffers {
    /// Floats held.
    pub fn len(&self) -> usize {
        self.planes.iter().map(Planes::len).sum::<usize>() + self.flat.len()
    }
}

impl Generator {
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Self> {
        let (k, z, flat) = (config.kernel, config.z_dim, config.flat_len());
        let (c, (h, w)) = (config.top_channels(), config.top_size());
        // fc is followed by a reshape to CHW and bn0: fold bn0 in, reorder rows to HWC. The
        // fold changes the values, so this matrix is kept in f32 whatever the file stores.
        let weight = src.f32("generator.fc.weight", &[flat, z], Init::FanIn(z))?;
        let bias = src.f32("generator.fc.bias", &[flat], Init::FanIn(z))?;
        let bn0 = read_batch_norm(src, "generator.bn0", c)?;
        let (weight, bias) = permute_rows_chw_to_hwc(&weight, &bias, z, c, h, w, Some(bn0.view()));
        let fc = DenseLayer::new(DenseWeights::F32(weight), bias, flat, z, Activation::Relu);

        let halo = ConvKind::Up.input_halo(k);
        let mut input = Plane::new(h, w, c, halo);
        let mut deconvs = Vec::with_capacity(config.layers);
        for i in 1..=config.layers {
            let last = i == config.layers;
            let (out_channels, out_halo, act) = if last {
                (config.channels, 0, Activation::Tanh)
            } else {
                (c >> i, halo, Activation::Relu)
            };
            let shape = ConvShape::new(ConvKind::Up, k, input, out_channels, out_halo);
            let bn = (!last).then(|| format!("generator.bn{i}"));
            deconvs.push(ConvLayer::load(
                src,
                &format!("generator.deconv{i}"),
                bn.as_deref(),
                shape,
                act,
            )?);
            input = shape.output;
        }
        Ok(Generator { fc, deconvs })
    }

    /// Scratch for batches of up to `max_batch` codes, with `sets` sets of
    /// planes, the first shared by `threads` threads.
    pub fn buffers(&self, max_batch: usize, sets: usize, threads: usize) -> GeneratorBuffers {
        GeneratorBuffers {
            flat: alloc::vec![0.0; max_batch * self.fc.rows],
            planes: plane_sets(&self.deconvs, sets, threads),
        }
    }

    /// Generates one frame per code of `z` (at most the planned batch, already validated).
    pub fn forward(&self, exec: Exec<'_>, buf: &mut GeneratorBuffers, z: &[f32], frames: &mut [f32]) {
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
