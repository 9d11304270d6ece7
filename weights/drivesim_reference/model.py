"""Reference PyTorch model of comma.ai's "Learning a Driving Simulator" networks.

This file defines the drivesim weight format: module and parameter names here
are the tensor names in the safetensors file, so keep them stable.
Frames are NCHW float tensors in [-1, 1]; codes are [N, z_dim].
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import safe_open
from torch import nn
from safetensors.torch import load_file, save

from drivesim import _files
from drivesim.episodes import sort_metadata

CONFIG_KEY = "drivesim.config"
# What each action input means and the range it was trained on: a JSON array of
# {"name", "unit", "mean", "std", "min", "max"}, one per action (weights/README.md §3).
ACTIONS_KEY = "drivesim.actions"
FRAME_HZ_KEY = "drivesim.frame_hz"  # frames per second the model was trained at, e.g. "12.5"
# A weight file may also carry the VAE-GAN's discriminator (vae_gan.py's `Discriminator`) under
# this prefix, so that training can resume from it; inference ignores those tensors.
DISCRIMINATOR = "discriminator."
DTYPES = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}
LEAK = 0.2  # LeakyReLU slope of the encoder, as in the paper's discriminator-style encoder


@dataclass(frozen=True)
class Config:
    height: int
    width: int
    channels: int
    base_channels: int
    layers: int = 4
    kernel: int = 5
    z_dim: int = 512
    hidden_dim: int = 512
    action_dim: int = 2

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if type(v) is not int or v <= 0:
                raise ValueError(f"config {f.name} must be a positive integer, got {v!r}")
        step = 2**self.layers
        if self.height % step or self.width % step:
            raise ValueError(f"height and width must be multiples of 2**layers = {step}")
        if self.kernel % 2 == 0:
            raise ValueError("kernel must be odd (padding is kernel // 2)")

    @property
    def top_channels(self) -> int:
        """Channels of the smallest feature map (8b for 4 layers)."""
        return self.base_channels * 2 ** (self.layers - 1)

    @property
    def top_shape(self) -> tuple[int, int, int]:
        s = 2**self.layers
        return (self.top_channels, self.height // s, self.width // s)

    @property
    def flat(self) -> int:
        c, h, w = self.top_shape
        return c * h * w

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, text: str) -> "Config":
        d = json.loads(text)
        names = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict) or set(d) != names:
            raise ValueError(f"config must be a JSON object with exactly the keys {sorted(names)}")
        return cls(**d)


def _conv(cfg: Config, cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, cfg.kernel, stride=2, padding=cfg.kernel // 2)


def _deconv(cfg: Config, cin: int, cout: int) -> nn.ConvTranspose2d:
    # output_padding=1 makes each layer exactly double the spatial size.
    return nn.ConvTranspose2d(cin, cout, cfg.kernel, stride=2, padding=cfg.kernel // 2, output_padding=1)


class Encoder(nn.Module):
    """frame [N,C,H,W] -> (mean [N,z], logsigma [N,z]); logsigma is tanh-squashed."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.layers = cfg.layers
        cin = cfg.channels
        for i in range(cfg.layers):
            cout = cfg.base_channels * 2**i
            setattr(self, f"conv{i}", _conv(cfg, cin, cout))
            if i > 0:  # no BN after the first conv
                setattr(self, f"bn{i}", nn.BatchNorm2d(cout))
            cin = cout
        self.mean = nn.Linear(cfg.flat, cfg.z_dim)
        self.logsigma = nn.Linear(cfg.flat, cfg.z_dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        for i in range(self.layers):
            x = getattr(self, f"conv{i}")(x)
            if i > 0:
                x = getattr(self, f"bn{i}")(x)
            x = nn.functional.leaky_relu(x, LEAK)
        x = x.flatten(1)
        return self.mean(x), torch.tanh(self.logsigma(x))


class Generator(nn.Module):
    """code [N,z] -> frame [N,C,H,W] in [-1, 1]."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.layers = cfg.layers
        self.top_shape = cfg.top_shape
        self.fc = nn.Linear(cfg.z_dim, cfg.flat)
        self.bn0 = nn.BatchNorm2d(cfg.top_channels)
        cin = cfg.top_channels
        for i in range(1, cfg.layers + 1):
            last = i == cfg.layers
            cout = cfg.channels if last else cin // 2
            setattr(self, f"deconv{i}", _deconv(cfg, cin, cout))
            if not last:
                setattr(self, f"bn{i}", nn.BatchNorm2d(cout))
            cin = cout

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.fc(z).view(-1, *self.top_shape)
        x = torch.relu(self.bn0(x))
        for i in range(1, self.layers):
            x = torch.relu(getattr(self, f"bn{i}")(getattr(self, f"deconv{i}")(x)))
        return torch.tanh(getattr(self, f"deconv{self.layers}")(x))


class Transition(nn.Module):
    """RNN in code space: h' = tanh(W h + V z + U c + b), z' = A h' + a. With `spread`, also the
    log standard deviation of each dimension of z', `S h' + s` (weights/README.md): the spread
    sampled futures draw from (the crate's `Simulator::set_sampling`). With `texture_width`, the
    texture net (`Texture`), which sampled futures draw from instead."""

    def __init__(self, cfg: Config, spread: bool = False, texture_width: int | None = None):
        super().__init__()
        hd, zd, ad = cfg.hidden_dim, cfg.z_dim, cfg.action_dim
        self.W = nn.Parameter(torch.empty(hd, hd))
        self.V = nn.Parameter(torch.empty(hd, zd))
        self.U = nn.Parameter(torch.empty(hd, ad))
        self.b = nn.Parameter(torch.zeros(hd))
        self.A = nn.Parameter(torch.empty(zd, hd))
        self.a = nn.Parameter(torch.zeros(zd))
        for m in (self.W, self.V, self.U, self.A):
            # std 1/sqrt(fan_in) keeps long rollouts from exploding or vanishing.
            nn.init.normal_(m, std=m.shape[1] ** -0.5)
        if spread:  # zeros: a unit spread to start from, and no draw taken from the other weights'
            self.S = nn.Parameter(torch.zeros(zd, hd))
            self.s = nn.Parameter(torch.zeros(zd))
        if texture_width is not None:
            self.texture = Texture(cfg, texture_width)

    @property
    def spread(self) -> bool:
        return hasattr(self, "S")

    @property
    def samples(self) -> bool:
        """Whether sampled futures can be drawn: the spread head or the texture net."""
        return self.spread or hasattr(self, "texture")

    @property
    def correlated(self) -> bool:
        """Whether sampled noise is correlated across dimensions (`transition.L`)."""
        return hasattr(self, "L")

    def set_noise_factor(self, factor: torch.Tensor) -> None:
        """`transition.L` [z, z]: the Cholesky factor of the noise's correlation
        (sequences.noise_factor); sampled noise is then `L @ eps`."""
        if not self.spread:
            raise ValueError("a noise factor needs the spread head (transition.S, transition.s)")
        if hasattr(self, "L"):
            self.L.copy_(factor)
        else:
            self.register_buffer("L", factor.detach().clone().float())

    def log_sigma(self, h: torch.Tensor) -> torch.Tensor:
        """The log standard deviation of the next code, `S h' + s`, of the hidden state h' a step left."""
        return h @ self.S.T + self.s

    def forward(self, z: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step on [N,z], [N,hd], [N,action] (or unbatched 1-D) -> (z', h')."""
        h = torch.tanh(h @ self.W.T + z @ self.V.T + c @ self.U.T + self.b)
        return h @ self.A.T + self.a, h


# The prefix of the transition's texture net's tensors (`Texture`).
TEXTURE = "transition.texture."
# The optional heads on `[z | h]` (the crate's `HeadKind`), in the order a weight file is read:
# name -> outputs (None: the config's action_dim).
HEADS = {"policy": None, "reward": 2, "value": 1, "pace": 1}
# The discount per decision of a value head's returns: a decimal string above 0 and below 1.
DISCOUNT_KEY = "drivesim.discount"


def head_outputs(cfg: Config, kind: str) -> int:
    """Outputs of the head `kind` ("policy", "reward", "value" or "pace")."""
    if kind not in HEADS:
        raise ValueError(f"unknown head {kind!r}; expected one of {sorted(HEADS)}")
    return cfg.action_dim if HEADS[kind] is None else HEADS[kind]


def check_discount(discount: float) -> float:
    """A value head's discount: a number above 0 and below 1 (the crate reads no other)."""
    d = float(discount)
    if not 0.0 < d < 1.0:
        raise ValueError(f"discount must be above 0 and below 1, got {discount!r}")
    return d


class Head(nn.Module):
    """One of the heads on `[z | h]` (the crate's `heads.rs`): one tanh layer of `width` units,
    then a linear output. Its tensors are `{kind}.hidden.weight [width, z+h]`, `.hidden.bias`,
    `{kind}.output.weight [outputs, width]`, `.output.bias`:
    - "policy": the cloned driver (`Simulator::act`, `train policy`), the action (before the
      crate clips it to the trained ranges);
    - "reward": the env's reward for the decision that led to the state, and the chance that
      the car is off the road there (the crate reads it clamped to [0, 1]);
    - "value": the discounted return from the state (the discount in `drivesim.discount`);
    - "pace": the speed a faster driver would drive at from the state (`Simulator::pace`,
      `train policy --pace`; the crate reads it clamped to at least 0)."""

    def __init__(self, cfg: Config, width: int, kind: str = "policy", outputs: int | None = None):
        super().__init__()
        self.kind = kind
        self.hidden = nn.Linear(cfg.z_dim + cfg.hidden_dim, width)
        self.output = nn.Linear(width, head_outputs(cfg, kind) if outputs is None else outputs)

    @property
    def prefix(self) -> str:
        """Its tensors' prefix in a weight file: "policy.", "reward.", "value." or "pace."."""
        return self.kind + "."

    @property
    def width(self) -> int:
        return self.hidden.out_features

    @property
    def outputs(self) -> int:
        return self.output.out_features

    def forward(self, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        return self.output(torch.tanh(self.hidden(torch.cat([z, h], -1))))


class Texture(Head):
    """The transition's texture net (`transition.texture.*`, the crate's texture.rs): a sampled
    code is `A h' + a + texture(temperature * noise, h')`, the offset from the mean drawn from
    `z_dim` standard normal draws and the hidden state h' the step left by a network of the heads'
    shape (the noise in the code's place). Trained adversarially (train_texture.py) so that
    sampled futures keep the road's kerbs and grass patches. Its output layer starts at zero: the
    mean."""

    def __init__(self, cfg: Config, width: int):
        super().__init__(cfg, width, "texture", cfg.z_dim)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    @property
    def prefix(self) -> str:
        return TEXTURE


class Policy(Head):
    """The cloned driver: the head "policy" (`action_dim` outputs)."""

    def __init__(self, cfg: Config, width: int):
        super().__init__(cfg, width, "policy")


class DriveSim(nn.Module):
    """The three networks; with `spread`, the transition's spread head; with `policy_width`,
    `reward_width`, `value_width`, `pace_width`, the heads of those widths (all optional in a weight file);
    `discount` the value head's (metadata `drivesim.discount`, kept by a load and a save)."""

    def __init__(self, cfg: Config, spread: bool = False, policy_width: int | None = None,
                 reward_width: int | None = None, value_width: int | None = None,
                 discount: float | None = None, texture_width: int | None = None,
                 pace_width: int | None = None):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.generator = Generator(cfg)
        self.transition = Transition(cfg, spread, texture_width)
        if policy_width is not None:
            self.policy = Policy(cfg, policy_width)
        for kind, width in (("reward", reward_width), ("value", value_width), ("pace", pace_width)):
            if width is not None:
                setattr(self, kind, Head(cfg, width, kind))
        self.discount = None if discount is None else check_discount(discount)

    def heads(self) -> dict[str, Head]:
        """The heads the model has, by kind, in file order."""
        return {k: getattr(self, k) for k in HEADS if isinstance(getattr(self, k, None), Head)}

    def rollout(self, seed_frames: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Predict codes from S seed frames [S,C,H,W] and S-1+T actions [S-1+T,action].

        Starting from h = 0, step i maps frame i to frame i+1 with actions[i]. Steps
        0..S-1 take the encoder mean of seed frame i as z input (teacher forcing);
        later steps feed back the previous z'. Returns the T predicted codes [T,z]
        (the z' of steps S-1 .. S-2+T), i.e. the codes of frames S .. S-1+T.
        """
        s = seed_frames.shape[0]
        if s < 1 or actions.shape[0] < s - 1:
            raise ValueError("need at least one seed frame and S-1 actions")
        seeds, _ = self.encoder(seed_frames)
        h = seeds.new_zeros(self.cfg.hidden_dim)
        z = seeds[0]
        codes = []
        for i, c in enumerate(actions):
            if i < s:
                z = seeds[i]
            z, h = self.transition(z, h, c)
            if i >= s - 1:
                codes.append(z)
        return torch.stack(codes)


def state_tensors(model: nn.Module, dtype: str | torch.dtype = "f32") -> dict[str, torch.Tensor]:
    """The tensors of the weight file: the state_dict without BN's num_batches_tracked."""
    dt = DTYPES.get(dtype, dtype)
    return {
        k: v.detach().to("cpu", dt).contiguous().clone()
        for k, v in model.state_dict().items()
        if not k.endswith("num_batches_tracked")
    }


def save_drivesim(model: DriveSim, cfg: Config, path: str | Path, dtype: str | torch.dtype = "f32",
                  actions: list[dict] | None = None, discriminator: nn.Module | None = None,
                  frame_hz: float | None = None, discount: float | None = None) -> None:
    """Write the drivesim safetensors file; dtype is "f32", "f16", "bf16" or a torch dtype;
    `actions`, if given, becomes the `drivesim.actions` metadata (one dict per action);
    `frame_hz`, if given, the `drivesim.frame_hz` metadata (the training data's frame rate);
    `discount` (default: the model's `discount`, if any) the `drivesim.discount` metadata;
    `discriminator`, if given, is stored under the prefix `discriminator.`."""
    if DTYPES.get(dtype, dtype) not in DTYPES.values():
        raise ValueError(f"unsupported dtype {dtype!r}")
    metadata = {CONFIG_KEY: cfg.to_json()}
    if actions is not None:
        if len(actions) != cfg.action_dim:
            raise ValueError(f"{len(actions)} action descriptions for {cfg.action_dim} actions")
        metadata[ACTIONS_KEY] = json.dumps(actions)
    if frame_hz is not None:
        if not (math.isfinite(frame_hz) and frame_hz > 0):
            raise ValueError(f"frame_hz must be a number above zero, got {frame_hz!r}")
        metadata[FRAME_HZ_KEY] = repr(float(frame_hz))
    if discount is None:
        discount = getattr(model, "discount", None)
    if discount is not None:
        metadata[DISCOUNT_KEY] = repr(check_discount(discount))
    tensors = state_tensors(model, dtype)
    if discriminator is not None:
        tensors.update({DISCRIMINATOR + k: v for k, v in state_tensors(discriminator, dtype).items()})
    # Atomic: a crash or a full disk during the save leaves the file that was there whole.
    blob = sort_metadata(save(tensors, metadata=metadata))
    with _files.atomic_write(path) as f:
        f.write(blob)


def load_drivesim(path: str | Path) -> tuple[DriveSim, Config]:
    """Read a drivesim safetensors file into a float32 model in eval mode."""
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
    if CONFIG_KEY not in meta:
        raise ValueError(f"{path}: missing metadata key {CONFIG_KEY!r}")
    cfg = Config.from_json(meta[CONFIG_KEY])
    tensors = load_file(str(path))
    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) != 1 or not dtypes <= set(DTYPES.values()):
        raise ValueError(f"{path}: tensors must all share one of f32/f16/bf16, got {dtypes}")
    tensors = {k: v for k, v in tensors.items() if not k.startswith(DISCRIMINATOR)}
    model = from_state_dict(cfg, tensors)
    if DISCOUNT_KEY in meta:
        model.discount = check_discount(meta[DISCOUNT_KEY])
    return model, cfg


def load_discriminator(path: str | Path) -> dict[str, torch.Tensor]:
    """The `discriminator.*` tensors of a weight file as float32, prefix removed (empty if none)."""
    return {k[len(DISCRIMINATOR):]: v.float() for k, v in load_file(str(path)).items() if k.startswith(DISCRIMINATOR)}


def from_state_dict(cfg: Config, tensors: dict[str, torch.Tensor]) -> DriveSim:
    """Float32 model in eval mode; every tensor must be present except num_batches_tracked (the
    spread head and the heads where the tensors hold them; a head's width is its hidden layer's)."""
    widths = {}
    for kind in HEADS:
        if any(k.startswith(kind + ".") for k in tensors):
            bias = tensors.get(f"{kind}.hidden.bias")
            if bias is None or bias.dim() != 1:
                raise ValueError(f"the {kind} head's tensors lack a 1-D {kind}.hidden.bias")
            widths[f"{kind}_width"] = bias.shape[0]
    texture = tensors.get(TEXTURE + "hidden.bias")
    if texture is not None and texture.dim() != 1:
        raise ValueError(f"{TEXTURE}hidden.bias must be 1-D, got {list(texture.shape)}")
    model = DriveSim(cfg, spread="transition.S" in tensors, texture_width=None if texture is None else texture.shape[0],
                     **widths)
    if "transition.L" in tensors:
        model.transition.set_noise_factor(torch.zeros(cfg.z_dim, cfg.z_dim))
    # Shape mismatches raise here; missing/unexpected names are checked below.
    res = model.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=False)
    missing = [k for k in res.missing_keys if not k.endswith("num_batches_tracked")]
    if missing or res.unexpected_keys:
        raise ValueError(f"missing tensors {missing}, unexpected tensors {res.unexpected_keys}")
    return model.eval()
