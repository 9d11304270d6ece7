//! The three networks' tensors and layers: the [`Table`] of every tensor (name, PyTorch shape,
//! place, layout, initialisation), [`Networks`] and [`build`], which lays them out with every
//! buffer of a step, reading tensors in PyTorch's layout, and [`random_weight_file`].

use super::budget::{mul, Budget, Sizes};
use super::buffers::Buffers;
use super::layers::{Conv, Dense, Order, Scratch, Work};
use super::stack::{stack, stack_grads, PASSES};
use super::table::{Entry, Layout, Norm, Table};
use super::weight_grad::GradSplit;
use super::HALO;
use crate::encoder::LEAKY_SLOPE;
use crate::train::NamedTensor;
use crate::weights::Init;
#[cfg(feature = "std")]
use crate::weights::{RandomSource, TensorSource, WeightDtype};
use crate::{Config, Error, Result};
use alloc::format;
#[cfg(feature = "std")]
use alloc::string::String;
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::norm::sums_len;
use drivesim_kernels::pack::conv_matrix_to_torch;
use drivesim_kernels::{Activation, ConvKind, ConvShape, Matrix, Plane};

/// The planes of a strided stack from `input` through `channels`, each in a border of [`HALO`].
fn down_shapes(input: Plane, channels: [usize; 4], k: usize) -> [ConvShape; 4] {
    let mut plane = input;
    channels.map(|oc| {
        let shape = ConvShape::new(ConvKind::Down, k, plane, oc, HALO);
        plane = shape.output;
        shape
    })
}

/// The encoder's or the discriminator's convolutions on `shapes`: layer `i` named
/// `{conv}{i}`, BatchNorm `{norm}{i}` after all but the first, LeakyReLU after each.
fn strided(
    t: &mut Table,
    budget: &mut Budget,
    sizes: &mut Sizes,
    shapes: &[ConvShape],
    (conv, norm): (&str, &str),
) -> Result<Vec<Conv>> {
    let leaky = Activation::LeakyRelu(LEAKY_SLOPE);
    let layers = shapes.iter().enumerate().map(|(i, &shape)| {
        let norm = (i > 0).then(|| format!("{norm}{i}"));
        Conv::new(t, budget, sizes, &format!("{conv}{i}"), norm.as_deref(), shape, leaky)
    });
    layers.collect()
}

/// The three networks, their tensors and every buffer of a step.
pub(super) struct Networks {
    pub(super) table: Table,
    pub(super) params: Vec<f32>,
    pub(super) grads: Vec<f32>,
    pub(super) moments: [Vec<f32>; 2],
    pub(super) stats: Vec<f32>,
    /// The running statistics as the last update left them: a step whose gradients are not
    /// finite puts them back, so that its forward passes leave no trace.
    pub(super) saved_stats: Vec<f32>,
    /// Where the discriminator's running statistics start (the encoder's and generator's come
    /// first).
    pub(super) dis_stats: usize,
    /// Each network's span of the parameters (encoder, generator, discriminator).
    pub(super) nets: [Range<usize>; 3],
    pub(super) enc: [Conv; 4],
    pub(super) heads: Dense,
    pub(super) fc: Dense,
    pub(super) top_norm: Norm,
    pub(super) top: Plane,
    pub(super) gen: [Conv; 4],
    pub(super) dis: [Conv; 4],
    pub(super) logit: Dense,
    pub(super) buffers: Buffers,
}

pub(super) fn build(config: &Config, batch: usize, threads: usize, budget: &mut Budget) -> Result<Networks> {
    config.validate()?;
    if batch == 0 {
        return Err(Error::Config {
            field: "batch",
            expected: "at least 1 frame",
            found: 0,
        });
    }
    let c = config;
    let (k, b, z) = (c.kernel, c.base_channels, c.z_dim);
    let (flat, top_c, (top_h, top_w)) = (c.flat_len(), c.top_channels(), c.top_size());
    let mut t = Table::default();
    let mut sizes = Sizes::default();
    let image = Plane::new(c.height, c.width, c.channels, HALO);
    let down = down_shapes(image, [b, 2 * b, 4 * b, 8 * b], k);

    // Encoder: its dense heads are one layer of 2z rows, mean then logsigma (their tensors
    // side by side in the table).
    let enc = strided(&mut t, budget, &mut sizes, &down, ("encoder.conv", "encoder.bn"))?;
    let fan = Init::FanIn(flat);
    let heads_weight = t.packed(
        0,
        &[("encoder.mean.weight", z), ("encoder.logsigma.weight", z)],
        flat,
        fan,
    );
    let (mb, lb) = (
        t.param("encoder.mean.bias".into(), &[z], fan),
        t.param("encoder.logsigma.bias".into(), &[z], fan),
    );
    let heads = Dense::new(
        budget,
        (heads_weight, mb.start..lb.end),
        2 * z,
        flat,
        Order::Columns(top_c, top_h, top_w),
    )?;
    let enc_end = t.params;

    // Generator.
    let fc_tensors = (
        t.packed(1, &[("generator.fc.weight", flat)], z, Init::FanIn(z)),
        t.param("generator.fc.bias".into(), &[flat], Init::FanIn(z)),
    );
    let fc = Dense::new(budget, fc_tensors, flat, z, Order::Rows(top_c, top_h, top_w))?;
    let top_norm = t.norm("generator.bn0", top_c);
    let top = Plane::new(top_h, top_w, top_c, HALO);
    let mut gen = Vec::new();
    let mut plane = top;
    for i in 1..=4 {
        let last = i == 4;
        let oc = if last { c.channels } else { plane.channels / 2 };
        let shape = ConvShape::new(ConvKind::Up, k, plane, oc, HALO);
        let norm = (!last).then(|| format!("generator.bn{i}"));
        let act = if last { Activation::Tanh } else { Activation::Relu };
        let name = format!("generator.deconv{i}");
        gen.push(Conv::new(
            &mut t,
            budget,
            &mut sizes,
            &name,
            norm.as_deref(),
            shape,
            act,
        )?);
        plane = shape.output;
    }
    let gen_end = t.params;
    let dis_stats = t.stats;

    // Discriminator.
    let names = ("discriminator.convs.", "discriminator.bns.");
    let dis = strided(&mut t, budget, &mut sizes, &down, names)?;
    let logit_tensors = (
        t.packed(2, &[("discriminator.out.weight", 1)], flat, Init::FanIn(flat)),
        t.param("discriminator.out.bias".into(), &[1], Init::FanIn(flat)),
    );
    let logit = Dense::new(budget, logit_tensors, 1, flat, Order::Columns(top_c, top_h, top_w))?;
    let params = t.params;
    let [enc, gen, dis]: [[Conv; 4]; 3] = [enc, gen, dis].map(|v| v.try_into().ok().expect("four layers"));

    let pair = mul(2, batch)?;
    // A backward pass runs over one batch or two (reconstructions and prior samples).
    let partials = [&enc, &gen, &dis]
        .iter()
        .flat_map(|net| net.iter())
        .flat_map(|l| {
            [batch, pair].map(|items| GradSplit::new(&l.grad_shape(), items, threads).partials_len(&l.grad_shape()))
        })
        .max()
        .unwrap_or(0);
    let act = "activations";
    let buffers = Buffers {
        batch,
        real: budget.take(act, mul(batch, image.len())?)?,
        enc: stack(budget, &enc, batch, act)?,
        enc_flat: budget.take(act, mul(batch, flat)?)?,
        heads: budget.take(act, mul(batch, 2 * z)?)?,
        codes: budget.take(act, mul(pair, z)?)?,
        eps: budget.take(act, mul(batch, z)?)?,
        fc_out: budget.take(act, mul(pair, flat)?)?,
        top_z: budget.take(act, mul(pair, top.len())?)?,
        top_y: budget.take(act, mul(pair, top.len())?)?,
        top_mean: budget.take(act, PASSES * top_c)?,
        top_var: budget.take(act, PASSES * top_c)?,
        gen: stack(budget, &gen, pair, act)?,
        dis_real: stack(budget, &dis, batch, act)?,
        dis_fake: stack(budget, &dis, pair, act)?,
        flat_real: budget.take(act, mul(batch, flat)?)?,
        flat_fake: budget.take(act, mul(pair, flat)?)?,
        logits_real: budget.take(act, batch)?,
        logits_fake: budget.take(act, pair)?,
        enc_grads: stack_grads(budget, &enc, batch)?,
        gen_grads: stack_grads(budget, &gen, pair)?,
        dis_grads: stack_grads(budget, &dis, pair)?,
        top_g: budget.take("activation gradients", mul(pair, top.len())?)?,
        dx: budget.take("activation gradients", mul(pair, image.len())?)?,
        dfeature: budget.take("activation gradients", mul(pair, down[2].output.len())?)?,
        dlogits: budget.take("activation gradients", pair)?,
        dflat: budget.take("activation gradients", mul(pair, flat)?)?,
        dheads: budget.take("activation gradients", mul(batch, 2 * z)?)?,
        dcodes: budget.take("activation gradients", mul(batch, z)?)?,
        work: Work {
            scratch: (0..threads)
                .map(|_| {
                    Ok(Scratch {
                        v: budget.take("scratch", sizes.winograd_v)?,
                        products: budget.take("scratch", sizes.winograd_products)?,
                    })
                })
                .collect::<Result<_>>()?,
            weight_scratch: budget.take("scratch", mul(threads, sizes.weight_scratch)?)?,
            partials: budget.take("partial weight gradients", partials)?,
            channel_tmp: budget.take("scratch", 2 * sizes.channels.max(top_c))?,
            zero: budget.take("scratch", sizes.channels)?,
            item_sums: budget.take_f64("scratch", mul(pair, sums_len(sizes.channels.max(top_c)))?)?,
            sums: budget.take_f64("scratch", sums_len(sizes.channels.max(top_c)))?,
        },
    };
    Ok(Networks {
        params: budget.take("parameters", params)?,
        grads: budget.take("gradients", params)?,
        moments: [
            budget.take("Adam moments", params)?,
            budget.take("Adam moments", params)?,
        ],
        stats: budget.take("running statistics", t.stats)?,
        saved_stats: budget.take("running statistics", t.stats)?,
        dis_stats,
        nets: [0..enc_end, enc_end..gen_end, gen_end..params],
        table: t,
        enc,
        heads,
        fc,
        top_norm,
        top,
        gen,
        dis,
        logit,
        buffers,
    })
}

impl Networks {
    /// Dense layer `layer`: the encoder's heads, the generator's first layer, the logit.
    pub(super) fn dense(&self, layer: usize) -> &Dense {
        [&self.heads, &self.fc, &self.logit][layer]
    }

    /// Tensor `e` of `values` (the parameters, their gradients or the statistics) in
    /// PyTorch's layout.
    pub(super) fn torch(&self, e: &Entry, values: &[f32]) -> NamedTensor {
        let tensor = match e.layout {
            Layout::Torch => values[e.at.clone()].to_vec(),
            Layout::Conv(shape) => {
                let mut out = alloc::vec![0.0; e.shape.iter().product()];
                conv_matrix_to_torch(&shape, &values[e.at.clone()], &mut out);
                out
            }
            Layout::Dense(layer, first) => {
                let dense = self.dense(layer);
                let (cols, rows) = (dense.cols, first..first + e.shape[0]);
                let (w, mut out) = (&values[e.at.clone()], alloc::vec![0.0; rows.len() * cols]);
                dense.order.for_each(dense.rows, cols, |r, c, t| {
                    if rows.contains(&(t / cols)) {
                        out[t - rows.start * cols] = w[Matrix::packed_index(r, c, cols)];
                    }
                });
                out
            }
        };
        (e.name.clone(), e.shape.clone(), tensor)
    }
}

/// A drivesim weight file (f32) with seeded random weights for `config` (PyTorch's default
/// initialisation ranges, BatchNorm at identity), discriminator included: where training from
/// scratch starts.
#[cfg(feature = "std")]
pub fn random_weight_file(config: &Config, seed: u64) -> Result<Vec<u8>> {
    let mut budget = Budget {
        allocate: false,
        floats: Vec::new(),
    };
    let parts = build(config, 1, 1, &mut budget)?;
    let (h, z, a) = (config.hidden_dim, config.z_dim, config.action_dim);
    let transition = [
        ("transition.W", alloc::vec![h, h], Init::FanIn(h)),
        ("transition.V", alloc::vec![h, z], Init::FanIn(z)),
        ("transition.U", alloc::vec![h, a], Init::FanIn(a)),
        ("transition.b", alloc::vec![h], Init::Zeros),
        ("transition.A", alloc::vec![z, h], Init::FanIn(h)),
        ("transition.a", alloc::vec![z], Init::Zeros),
    ];
    let specs = parts
        .table
        .entries
        .iter()
        .map(|e| (e.name.as_str(), e.shape.clone(), e.init));
    let specs: Vec<_> = specs
        .chain(transition.iter().map(|(n, s, i)| (*n, s.clone(), *i)))
        .collect();
    let mut random = RandomSource::new(seed, WeightDtype::F32);
    let mut data = Vec::new();
    for (name, shape, init) in &specs {
        let values = random.f32(name, shape, *init)?;
        data.push(bytemuck::cast_slice::<f32, u8>(&values).to_vec());
    }
    let views = specs
        .iter()
        .zip(&data)
        .map(|((name, shape, _), bytes)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), bytes)
                .map(|view| (String::from(*name), view))
        })
        .collect::<core::result::Result<Vec<_>, _>>();
    let malformed = |e| Error::Malformed {
        what: "weight file",
        reason: format!("{e:?}"),
    };
    let mut metadata = std::collections::HashMap::new();
    metadata.insert(String::from(Config::METADATA_KEY), config.to_json());
    safetensors::serialize(views.map_err(malformed)?, Some(metadata)).map_err(malformed)
}
