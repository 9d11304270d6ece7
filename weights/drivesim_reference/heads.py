"""PyTorch reference of the crate's head training (`drivesim::train::HeadTrainer`,
src/train/heads.rs) and of the value head's targets (`drivesim::train::lambda_returns`,
src/train/returns.rs); tests/heads_parity.rs checks the crate against these (fixtures.py's
`heads_f32.train.safetensors`).

A head (model.Head) is trained by mean squared error in "scaled units": each output k has a
(mean_k, std_k); the trained parameters hold the output layer scaled, W2'[k] = W2[k] / std_k,
b2'[k] = (b2[k] - mean_k) / std_k, the loss is the mean over a batch's n * outputs entries of
(out'_k - (y_k - mean_k) / std_k)^2, and torch.optim.Adam (PyTorch's defaults) steps the
scaled parameters [W1, b1, W2', b2']. The head's own tensors are the unscaled ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from drivesim_reference.model import Head


def lambda_returns(rewards, next_values, discount: float, lam: float):
    """The λ-returns of one drive of T decisions: G_t = r_t + γ((1 - λ) v_{t+1} + λ G_{t+1}),
    computed backwards from G_T = v_T (`next_values[-1]`), where `next_values[t]` is v_{t+1},
    the value of the state decision t led to. In float32, each operation rounded as the
    crate's are. A torch tensor in gives a torch tensor out, anything else a numpy array."""
    for name, value in (("discount", discount), ("lambda", lam)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be from 0 to 1, got {value!r}")
    as_torch = isinstance(rewards, torch.Tensor)

    def array(x):
        x = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x
        return np.asarray(x, dtype=np.float32).reshape(-1)

    r, v = array(rewards), array(next_values)
    if r.shape != v.shape:
        raise ValueError(f"{len(v)} next values for {len(r)} rewards")
    if not (np.isfinite(r).all() and np.isfinite(v).all()):
        raise ValueError("rewards and next values must be finite")
    g, one = np.float32(discount), np.float32(1.0)
    lam = np.float32(lam)
    out = np.empty_like(r)
    nxt = v[-1] if len(v) else None
    for t in range(len(r) - 1, -1, -1):
        nxt = r[t] + g * ((one - lam) * v[t] + lam * nxt)
        out[t] = nxt
    return torch.from_numpy(out) if as_torch else out


class HeadTrainer:
    """The crate's HeadTrainer: trains `head` (a model.Head, changed in place after each step)
    in `units`, one (mean, std) per output."""

    def __init__(self, head: Head, units: Sequence[tuple[float, float]]):
        if len(units) != head.outputs:
            raise ValueError(f"{len(units)} units for the head's {head.outputs} outputs")
        mean, std = (torch.tensor(u, dtype=torch.float32) for u in zip(*units))
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all() and (std > 0).all()):
            raise ValueError(f"units must be finite with deviations above 0, got {list(units)}")
        self.head, self.units, self.mean, self.std = head, [tuple(u) for u in units], mean, std
        with torch.no_grad():
            w2 = head.output.weight.detach().float() / std[:, None]
            b2 = (head.output.bias.detach().float() - mean) / std
            self.params = [p.detach().float().clone().requires_grad_(True)
                           for p in (head.hidden.weight, head.hidden.bias, w2, b2)]
        self.optimizer = torch.optim.Adam(self.params, lr=1e-3)  # PyTorch's defaults
        self.steps = 0

    def _loss(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        w1, b1, w2, b2 = self.params
        inputs = torch.as_tensor(inputs, dtype=torch.float32)
        targets = torch.as_tensor(targets, dtype=torch.float32).reshape(inputs.shape[0], -1)
        out = torch.tanh(inputs @ w1.T + b1) @ w2.T + b2
        return ((out - (targets - self.mean) / self.std) ** 2).mean()

    def loss(self, inputs, targets) -> float:
        """The batch's loss (the mean squared error in the scaled units), without a step."""
        with torch.no_grad():
            return self._loss(inputs, targets).item()

    def step(self, inputs, targets, lr: float) -> float:
        """One Adam step at `lr` on a batch (`inputs` [n, z+h], `targets` [n, outputs]); returns
        the loss before the step."""
        if not (math.isfinite(lr) and lr > 0):
            raise ValueError(f"lr must be a finite number above 0, got {lr!r}")
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.optimizer.zero_grad()
        loss = self._loss(inputs, targets)
        loss.backward()
        self.optimizer.step()
        self.steps += 1
        with torch.no_grad():
            for name, value in self.tensors().items():
                self.head.get_parameter(name.removeprefix(self.head.prefix)).copy_(value)
        return loss.item()

    def tensors(self) -> dict[str, torch.Tensor]:
        """The head's tensors, unscaled (W2 = W2' std, b2 = b2' std + mean), named as in a
        weight file: `{kind}.hidden.weight`, `.hidden.bias`, `{kind}.output.weight`, `.bias`."""
        w1, b1, w2, b2 = (p.detach() for p in self.params)
        p = self.head.prefix
        return {f"{p}hidden.weight": w1.clone(), f"{p}hidden.bias": b1.clone(),
                f"{p}output.weight": w2 * self.std[:, None], f"{p}output.bias": b2 * self.std + self.mean}


def train_step(head: Head, units: Sequence[tuple[float, float]], inputs, targets, lr: float) -> float:
    """One HeadTrainer step on `head` in `units`, returning the loss before it. The trainer
    (parameters in scaled units, Adam's moments) is kept on the head between calls with the same
    units; other units start a new one from the head's current tensors."""
    trainer = head.__dict__.get("_trainer")
    if trainer is None or trainer.units != [tuple(u) for u in units]:
        trainer = HeadTrainer(head, units)
        head.__dict__["_trainer"] = trainer
    return trainer.step(inputs, targets, lr)
