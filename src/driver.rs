//! A world's parts apart from it. A driver file holds one policy head (`policy.*`) and the
//! fingerprint of the world it was learnt in, so that a small file can ship a driver learnt
//! in the dream of a large one, and so that it is never driven in another world by mistake
//! (its weights mean nothing there: they read that world's codes and hidden states). A sampler
//! file holds a texture net (`transition.texture.*`) learnt for a world's transition, and may
//! hold a read-out of its own (`transition.A`, `transition.a`), so that a world can be dreamt
//! through another sampler than its own (the rank probe's judge) without a second copy of the
//! world.

use crate::heads::{Head, HeadKind};
use crate::texture::{Texture, TEXTURE};
use crate::transition::Transition;
use crate::weights::{Init, SafetensorsSource, TensorSource, DISCRIMINATOR_PREFIX};
use crate::{Config, Error, Model, Result};
use alloc::format;
use alloc::string::{String, ToString};
use drivesim_kernels::Tensor;
use safetensors::SafeTensors;

/// The metadata key of a driver file that names its world (16 hexadecimal digits).
pub(crate) const WORLD_KEY: &str = "drivesim.world";

/// Tensors that are a driver's, not its world's: the policy and the clone's pace head (which a
/// driver learnt in the dream drops). The discriminator only trains the generator.
fn drivers_own(name: &str) -> bool {
    [HeadKind::Policy.prefix(), HeadKind::Pace.prefix(), DISCRIMINATOR_PREFIX]
        .iter()
        .any(|prefix| name.starts_with(prefix))
}

fn malformed(e: safetensors::SafeTensorError) -> Error {
    Error::Malformed {
        what: "weight file",
        reason: format!("{e:?}"),
    }
}

/// The fingerprint of the world a weight file holds, as 16 hexadecimal digits: 64-bit FNV-1a
/// over its tensors in name order but the drivers' (`policy.*`, `pace.*`) and the
/// discriminator's, each tensor its name's UTF-8 bytes, a zero byte, then its stored data.
/// Metadata is left out, so re-describing a world keeps its drivers. `weights/README.md` states it.
///
/// ```
/// let world = std::fs::read("weights/default.safetensors")?;
/// let fingerprint = drivesim::world_fingerprint(&world)?;
/// assert_eq!(fingerprint.len(), 16);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn world_fingerprint(weight_file: &[u8]) -> Result<String> {
    fingerprint_without(weight_file, drivers_own)
}

/// FNV-1a over the tensors of `weight_file` that `left_out` does not name, as
/// [`world_fingerprint`] defines it.
fn fingerprint_without(weight_file: &[u8], left_out: fn(&str) -> bool) -> Result<String> {
    let file = SafeTensors::deserialize(weight_file).map_err(malformed)?;
    let mut tensors = file.tensors();
    tensors.retain(|(name, _)| !left_out(name));
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let mut hash = Fnv1a::new();
    for (name, view) in &tensors {
        hash.write(name.as_bytes());
        hash.write(&[0]);
        hash.write(view.data());
    }
    Ok(format!("{:016x}", hash.0))
}

/// 64-bit FNV-1a: a checksum that tells worlds apart, not a defence against forgery.
struct Fnv1a(u64);

impl Fnv1a {
    fn new() -> Self {
        Fnv1a(0xcbf2_9ce4_8422_2325)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
}

impl Model {
    /// The world of `weight_file` driven by the driver of `driver_file` (format:
    /// `weights/README.md`): the driver's policy head replaces the file's, and the file's pace
    /// head is left out (a driver learnt in the dream drives at its own speed).
    /// [`Error::OtherWorld`] when the driver was learnt in another world; the driver file is
    /// checked as a weight file is (shapes against the world's config, one dtype, finite values,
    /// nothing but `policy.*`).
    ///
    /// ```
    /// let world = std::fs::read("weights/default.safetensors")?;
    /// let driver = std::fs::read("weights/dreamt.safetensors")?;
    /// let model = drivesim::Model::from_bytes_with_driver(&world, &driver)?;
    /// assert_eq!(model.policy_width(), Some(64));
    /// assert!(model.head_width(drivesim::HeadKind::Pace).is_none());
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn from_bytes_with_driver(weight_file: &[u8], driver_file: &[u8]) -> Result<Model> {
        let mut model = Model::from_bytes(weight_file)?;
        let (config, mut src) = part_of(weight_file, &model, driver_file, "driver")?;
        let policy = Head::load(&config, &mut src, HeadKind::Policy)?.ok_or(Error::MissingTensor {
            name: "policy.hidden.weight".to_string(),
        })?;
        src.finish()?;
        model.policy = Some(policy);
        model.pace = None;
        Ok(model)
    }

    /// The world of `weight_file` dreamt through the texture net of `sampler_file` (format:
    /// `weights/README.md`) in place of its own: the heads and the policy are the file's, the
    /// sampled futures the sampler's, and the mean dream the file's unless the sampler carries a
    /// read-out of its own (`transition.A` and `transition.a`, both), which then replaces the
    /// world's. [`Error::OtherWorld`] when the sampler was learnt for another world; the sampler
    /// file is checked as a weight file is (shapes against the world's config, one dtype, finite
    /// values, nothing but `transition.texture.*` and the read-out).
    ///
    /// ```
    /// let world = std::fs::read("weights/default.safetensors")?;
    /// let judge = std::fs::read("weights/judge.safetensors")?;
    /// let model = drivesim::Model::from_bytes_with_sampler(&world, &judge)?;
    /// assert_eq!(model.texture_width(), Some(256));
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn from_bytes_with_sampler(weight_file: &[u8], sampler_file: &[u8]) -> Result<Model> {
        let mut model = Model::from_bytes(weight_file)?;
        let (config, mut src) = part_of(weight_file, &model, sampler_file, "sampler")?;
        let texture = Texture::load(&config, &mut src)?.ok_or(Error::MissingTensor {
            name: format!("{TEXTURE}hidden.weight"),
        })?;
        if READ_OUT.iter().any(|name| src.shape(name).is_some()) {
            // The transition built again from the world's tensors but the read-out, so that
            // whatever the world derives from it (an f32 world's folded feedback) follows.
            let (_, _, world) = SafetensorsSource::parse(weight_file)?;
            model.transition = Transition::load(
                &config,
                &mut ReadOutFrom {
                    world,
                    sampler: &mut src,
                },
            )?;
        }
        src.finish()?;
        model.transition.set_texture(texture);
        Ok(model)
    }
}

/// The transition's read-out, `z' = A h' + a`: a sampler file may carry its own (both tensors).
const READ_OUT: [&str; 2] = ["transition.A", "transition.a"];

/// A world's tensors with a sampler file's read-out in place of the world's own.
struct ReadOutFrom<'a, 'b, 'c> {
    world: SafetensorsSource<'a>,
    sampler: &'c mut SafetensorsSource<'b>,
}

impl TensorSource for ReadOutFrom<'_, '_, '_> {
    fn tensor(&mut self, name: &str, shape: &[usize], init: Init) -> Result<Tensor> {
        match READ_OUT.contains(&name) {
            true => self.sampler.tensor(name, shape, init),
            false => self.world.tensor(name, shape, init),
        }
    }

    fn contains(&self, prefix: &str) -> bool {
        self.world.contains(prefix)
    }

    fn shape(&self, name: &str) -> Option<alloc::vec::Vec<usize>> {
        self.world.shape(name)
    }
}

/// The tensors of a part file (`what`: a driver or a sampler file) learnt in the world of
/// `weight_file` (loaded as `model`), and its config; [`Error::OtherWorld`] where its
/// `drivesim.world` is not that world's fingerprint or its config not the world's.
fn part_of<'a>(
    weight_file: &[u8],
    model: &Model,
    part_file: &'a [u8],
    what: &str,
) -> Result<(Config, SafetensorsSource<'a>)> {
    let (config, _, src) = SafetensorsSource::parse(part_file)?;
    let (_, header) = SafeTensors::read_metadata(part_file).map_err(malformed)?;
    let learnt_in = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get(WORLD_KEY))
        .ok_or_else(|| Error::Metadata {
            reason: format!("no `{WORLD_KEY}` key: not a {what} file"),
        })?;
    let world = world_fingerprint(weight_file)?;
    if *learnt_in != world || config != *model.config() {
        return Err(Error::OtherWorld {
            world,
            learnt_in: learnt_in.to_string(),
        });
    }
    Ok((config, src))
}

/// The driver file of a weight file whose policy is a driver (what `weights/tool train driver`
/// writes): its `policy.*` tensors as stored, the `drivesim.config` of the file and the
/// fingerprint of its world under `drivesim.world`. The file is loaded first, so a driver file
/// is only ever written from a valid weight file.
#[cfg(feature = "std")]
pub fn driver_file(weight_file: &[u8]) -> Result<alloc::vec::Vec<u8>> {
    let model = Model::from_bytes(weight_file)?;
    if model.policy.is_none() {
        return Err(Error::NoPolicy);
    }
    part_file(
        weight_file,
        |name| name.starts_with(HeadKind::Policy.prefix()),
        world_fingerprint(weight_file)?,
    )
}

/// The sampler file of `weight_file`'s texture net for the world of `world_file` (what
/// `weights/tool train latent --freeze-transition` learns): its `transition.texture.*` tensors
/// as stored, its read-out (`transition.A`, `transition.a`) where that is not the world's, the
/// `drivesim.config` of the file and the fingerprint of `world_file` under `drivesim.world`.
/// [`Error::OtherWorld`] unless the two files hold the same world but for their texture nets,
/// read-outs (and drivers); [`Error::NoSampling`] when `weight_file` has no texture net.
#[cfg(feature = "std")]
pub fn sampler_file(weight_file: &[u8], world_file: &[u8]) -> Result<alloc::vec::Vec<u8>> {
    let model = Model::from_bytes(weight_file)?;
    if model.texture_width().is_none() {
        return Err(Error::NoSampling);
    }
    Model::from_bytes(world_file)?;
    let apart_from_sampler = |name: &str| drivers_own(name) || name.starts_with(TEXTURE) || READ_OUT.contains(&name);
    if fingerprint_without(weight_file, apart_from_sampler)? != fingerprint_without(world_file, apart_from_sampler)? {
        // Named by the worlds' own fingerprints, the ones a user can look up.
        return Err(Error::OtherWorld {
            world: world_fingerprint(world_file)?,
            learnt_in: world_fingerprint(weight_file)?,
        });
    }
    // The read-out goes in only where it is not the world's: a plain sampler stays four tensors.
    let own_read_out = |name: &str| !READ_OUT.contains(&name);
    let read_out_differs =
        fingerprint_without(weight_file, own_read_out)? != fingerprint_without(world_file, own_read_out)?;
    let in_part = |name: &str| name.starts_with(TEXTURE) || (read_out_differs && READ_OUT.contains(&name));
    part_file(weight_file, in_part, world_fingerprint(world_file)?)
}

/// The tensors of `weight_file` that `in_part` names, as stored, with its `drivesim.config` and
/// `world` under `drivesim.world`: a part file.
#[cfg(feature = "std")]
fn part_file(weight_file: &[u8], in_part: impl Fn(&str) -> bool, world: String) -> Result<alloc::vec::Vec<u8>> {
    let file = SafeTensors::deserialize(weight_file).map_err(malformed)?;
    let mut part = file.tensors();
    part.retain(|(name, _)| in_part(name));
    part.sort_by(|a, b| a.0.cmp(&b.0));
    let (_, header) = SafeTensors::read_metadata(weight_file).map_err(malformed)?;
    let config = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get(Config::METADATA_KEY))
        .cloned();
    let metadata = [
        (Config::METADATA_KEY.to_string(), config.unwrap_or_default()),
        (WORLD_KEY.to_string(), world),
    ];
    let bytes = safetensors::serialize(part, Some(metadata.into_iter().collect())).map_err(malformed)?;
    Ok(crate::weights::sort_metadata(bytes))
}
