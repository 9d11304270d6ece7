"""Type stubs of the extension module (the crate's Model, Simulator and Environment)."""

import os
from typing import Any, Optional, Union, overload, Literal

import numpy as np
import numpy.typing as npt

Frames = Union[npt.NDArray[np.uint8], npt.NDArray[np.float32]]
F32 = npt.NDArray[np.float32]
DType = Any  # np.uint8 / np.float32 or their names

__version__: str

class Model:
    """Loaded weights: encoder, transition and generator, checked on load."""

    @staticmethod
    def load(
        path: Optional[Union[str, os.PathLike[str]]] = None,
        driver: Optional[Union[str, os.PathLike[str]]] = None,
        sampler: Optional[Union[str, os.PathLike[str]]] = None,
    ) -> Model:
        """A weight file (safetensors), or the built-in default model when ``path`` is None;
        ``driver``, a driver file (``drivesim.driver``), replaces its policy (its pace head left
        out); ``sampler``, a sampler file, its texture net (and read-out, where it has one; not
        both). Raises OSError for a file that cannot be read, ValueError for a bad weight file
        or a part of another world."""
    @staticmethod
    def dreamt() -> Model:
        """The built-in default model driven by the built-in driver learnt in its dream."""
    @staticmethod
    def judge(path: Optional[Union[str, os.PathLike[str]]] = None) -> Model:
        """The world of ``path`` (None: the built-in default) dreamt through the built-in judge's
        sampler and its widened read-out, whose futures rank drivers as the real track does
        (ValueError for another world)."""
    @staticmethod
    def from_bytes(data: bytes) -> Model:
        """A model from a weight file's bytes (TypeError for what is not bytes, ValueError for
        a bad weight file)."""
    @property
    def config(self) -> dict[str, int]:
        """``height``, ``width``, ``channels``, ``base_channels``, ``layers``, ``kernel``,
        ``z_dim``, ``hidden_dim``, ``action_dim``."""
    @property
    def frame_shape(self) -> tuple[int, int, int]:
        """``(height, width, channels)``."""
    @property
    def z_dim(self) -> int: ...
    @property
    def hidden_dim(self) -> int: ...
    @property
    def action_dim(self) -> int: ...
    @property
    def frame_hz(self) -> Optional[float]:
        """Frames per second the model was trained at, or None."""
    @property
    def actions(self) -> Optional[list[dict[str, Any]]]:
        """Each action's ``name``, ``unit``, ``mean``, ``std``, ``min``, ``max``, or None."""
    @property
    def policy_width(self) -> Optional[int]:
        """Units of the policy's hidden layer (the cloned driver ``Simulator.act`` runs), or
        None where the weight file has no policy."""
    @property
    def reward_width(self) -> Optional[int]:
        """Units of the reward head's hidden layer (``Simulator.reward``), or None."""
    @property
    def value_width(self) -> Optional[int]:
        """Units of the value head's hidden layer (``Simulator.value``), or None."""
    @property
    def pace_width(self) -> Optional[int]:
        """Units of the pace head's hidden layer (``Simulator.pace``), or None."""
    @property
    def discount(self) -> Optional[float]:
        """The value head's discount per decision (``drivesim.discount``), or None."""
    @property
    def samples(self) -> bool:
        """Whether the transition can sample its codes (the spread head or the texture net), so
        that rollouts can be sampled (``Simulator.set_sampling``)."""
    @property
    def texture_width(self) -> Optional[int]:
        """Units of the texture net's hidden layer (``transition.texture.*``), or None: an
        adversarially trained sampler that keeps the road's texture; where a file has it,
        sampling draws through it, not the spread head."""
    @property
    def samples_correlated(self) -> bool:
        """Whether sampled noise is correlated across the code's dimensions (the weight file's
        ``transition.L``, fitted by ``train transition``); otherwise each dimension draws alone."""

class Simulator:
    """Encodes frames, steps the transition, generates frames, rolls out dreams.

    Frames: ``(N, H, W, 3)`` or ``(H, W, 3)``, uint8 (0-255) or float32 (in [-1, 1]); codes,
    hidden states and actions: float32, finite, one row per item, N at most ``batch`` (a
    rollout's steps and ``rollout_candidates``' T are not limited). Inputs must be numpy
    arrays of exactly that dtype, C-ordered (``np.ascontiguousarray``); they are borrowed for
    the call, not copied, and another thread cannot resize them meanwhile (its ``resize``
    raises ValueError).

    Every method raises ValueError for a wrong type, dtype, shape, order or value of an
    argument (NaN, an infinity, a frame outside [-1, 1]), or a result that would overflow
    float32; MemoryError when a result (or the plan, at construction) cannot be allocated;
    RuntimeError when another thread is using this simulator. Results are new arrays, always
    finite; a call that raised leaves the simulator as it was, usable."""

    def __init__(self, model: Model, batch: int = 1, threads: int = 1) -> None:
        """``batch``: the most frames or codes one call takes, an integer >= 1; ``threads``:
        threads that share each call, the caller's included, 1 to 1024. ValueError for a
        value out of range (a negative one included), TypeError for a non-integer,
        MemoryError when the plan cannot be allocated, RuntimeError when the system will not
        start the threads."""
    @property
    def batch(self) -> int:
        """The most frames or codes one call takes."""
    @property
    def threads(self) -> int: ...
    @property
    def isa(self) -> str:
        """``"avx512"``, ``"avx2"``, ``"neon"`` or ``"scalar"``."""
    @property
    def buffer_bytes(self) -> int: ...
    def encode(self, frames: Frames) -> F32:
        """Frames to codes: ``(N, z_dim)``, or ``(z_dim,)`` for one frame."""
    def generate(self, z: F32, dtype: DType = ...) -> Frames:
        """Codes to frames, uint8 by default (``dtype=np.float32``: in [-1, 1])."""
    def transition(self, z: F32, h: F32, action: F32) -> tuple[F32, F32]:
        """One step from given codes: ``(z_next, h_next)``."""
    def transition_fed_back(self, h: F32, action: F32) -> tuple[F32, F32]:
        """One step from the code ``h`` predicts: ``(z_next, h_next)``."""
    def set_sampling(self, temperature: float, seed: int) -> None:
        """Samples every later rollout: each predicted code ``mean + temperature * sigma *
        noise``, the noise from ``seed``, the step and the item alone. Temperature 0: the mean.
        ValueError for a temperature below 0 or not finite, or above 0 for a model that cannot
        sample, and for a seed outside 0 to 2**64 - 1; TypeError for a non-integer seed."""
    @property
    def sampling(self) -> tuple[float, int]:
        """``(temperature, seed)``; temperature 0: off."""
    def sample(self, h: F32, step: int, codes: F32) -> F32:
        """For a controller stepping the transition itself, what the rollouts do after each
        step: the mean codes ``codes`` ``(N, z_dim)`` a step predicted, with the hidden states
        ``h`` ``(N, hidden_dim)`` it left (one of each without the leading N), sampled as rollout
        step ``step`` (an integer >= 0; items numbered from 0). A new array; with sampling off,
        the codes as given. ValueError for shapes that differ or more items than the batch."""
    def act(self, z: F32, h: F32) -> F32:
        """The cloned driver's actions ``(N, 2)`` (speed to drive at, steering) for the codes
        ``z`` of the frames seen now and the hidden states ``h`` after the drive so far; ValueError
        for a model without a policy."""
    def reward(self, z: F32, h: F32) -> F32:
        """The reward head on states a decision led to: ``(N, 2)`` (reward, off-road chance in
        [0, 1]); ValueError for a model without the head."""
    def value(self, z: F32, h: F32) -> F32:
        """The value head's discounted returns ``(N, 1)`` from states ``z``, ``h``; ValueError
        for a model without the head."""
    def pace(self, z: F32, h: F32) -> F32:
        """The pace head's speeds ``(N, 1)`` (at least 0) from the states ``act`` reads;
        ValueError for a model without the head."""
    def rollout(self, seed_frames: Frames, actions: F32, frames: bool = False, dtype: DType = ...) -> Any:
        """``(S, H, W, 3)`` seeds and ``(S - 1 + T, 2)`` actions: codes ``(T, z_dim)``, or
        ``(codes, frames)`` with ``frames=True``."""
    def rollout_candidates(
        self, h: F32, actions: F32, z: Optional[F32] = None, frames: bool = False, dtype: DType = ...
    ) -> Any:
        """``actions`` ``(T, N, 2)`` from one state (``h`` ``(hidden_dim,)`` or
        ``(N, hidden_dim)``; ``z`` ``(z_dim,)``, ``(N, z_dim)`` or None): codes
        ``(T, N, z_dim)``, or ``(codes, frames)`` with frames ``(T, N, H, W, 3)``. ValueError
        names the shapes that disagree; MemoryError when T is too long to allocate."""
    def rollout_candidates_scored(
        self, h: F32, actions: F32, z: Optional[F32] = None
    ) -> tuple[F32, F32, F32]:
        """``rollout_candidates`` with the heads read after every step: ``(codes (T, N, z_dim),
        rewards (T, N, 2), values (T, N))``; ValueError for a model without both heads."""

class Environment:
    """``drives`` dreamed drives stepping together in one batch. Arrays and errors as
    ``Simulator``'s; before a successful reset (and after a failed one) ``step``, ``frames``,
    ``codes``, ``hidden`` and ``rollout_candidates`` raise ValueError."""

    def __init__(self, model: Model, drives: int = 1, candidates: int = 64, threads: int = 1) -> None:
        """``drives`` and ``candidates`` (the most sequences one ``rollout_candidates`` takes)
        integers >= 1, ``threads`` 1 to 1024: ValueError otherwise, TypeError for a
        non-integer, MemoryError when the plan cannot be allocated."""
    @property
    def drives(self) -> int: ...
    def reset(self, frames: Frames, actions: F32) -> None:
        """``frames`` ``(S, drives, H, W, 3)``, ``actions`` ``(S - 1, drives, 2)``."""
    def reset_from_codes(self, codes: F32, actions: F32) -> None:
        """``codes`` ``(S, drives, z_dim)``, ``actions`` ``(S - 1, drives, 2)``."""
    def set_sampling(self, temperature: float, seed: int) -> None:
        """Samples every later step and rollout (``Simulator.set_sampling``); a step's noise is
        that of the steps since the reset and the drive."""
    def step(self, actions: F32) -> None:
        """``actions`` ``(drives, 2)``: (speed, steering) each. Bad actions raise ``ValueError``
        and change nothing; a step that fails after that (a prediction that is not finite)
        raises ``ValueError`` too and leaves the drives to be reset (``ValueError`` until then), never half
        a step."""
    @property
    def codes(self) -> F32:
        """``(drives, z_dim)``, a copy."""
    @property
    def hidden(self) -> F32:
        """``(drives, hidden_dim)``, a copy."""
    def frames(self, dtype: DType = ...) -> Frames:
        """``(drives, H, W, 3)``, uint8 by default."""
    def rollout_candidates(self, drive: int, actions: F32, frames: bool = False, dtype: DType = ...) -> Any:
        """``actions`` ``(T, N, 2)`` from drive ``drive``'s state (``0 <= drive < drives``,
        ValueError otherwise): codes ``(T, N, z_dim)``, or ``(codes, frames)``."""

def world_fingerprint(path: Union[str, os.PathLike[str]]) -> str:
    """The fingerprint of the world a weight file holds (16 hexadecimal digits)."""

def driver_file(path: Union[str, os.PathLike[str]]) -> bytes:
    """The driver file's bytes of a weight file whose policy is a learnt driver."""

def sampler_file(path: Union[str, os.PathLike[str]], world: Union[str, os.PathLike[str]]) -> bytes:
    """The sampler file's bytes of a weight file's texture net (and read-out, where it is not the
    world's), for the world of ``world`` (the same world but for those; ValueError otherwise)."""

def load_episodes(
    path: Optional[Union[str, os.PathLike[str]]] = None,
) -> list[tuple[npt.NDArray[np.uint8], F32]]:
    """``(frames (T, H, W, 3) uint8, actions (T, 2) float32)`` per episode of an episodes file,
    or of the built-in seed clip when ``path`` is None."""

def box_shrink(image: npt.NDArray[np.uint8], height: int, width: int, channels: list[int]) -> npt.NDArray[np.uint8]:
    """``image`` (uint8, C-ordered, ``(H, W, C)``) shrunk to ``(height, width, len(channels))``
    byte for byte as Pillow's ``Image.resize((width, height), Image.BOX)`` shrinks it (RGB,
    not premultiplied), keeping the channels ``channels`` (1 to 4 indices below C) in that
    order. ``ValueError`` for another dtype, shape or layout, a size of zero or larger than the
    image's, or channels out of range. ``carracing.observe``'s fast path."""
