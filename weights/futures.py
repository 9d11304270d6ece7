"""The measures of a dream that steers both ways and samples its futures (issue 31), on held-out
episodes (`train eval` reports them under `futures` in eval.json; docs/fidelity.md):

- the steering probe: 50 starts evenly spaced over the episodes, 5 seed codes from real frames,
  then 30 steps at the seed's speed with constant steering -x, 0 and +x; in the 30th generated
  frame, the road's centre (the mean column of the grey road pixels of the top 60 rows). The
  road moves the right way where left steering's centre is right of right steering's;
  symmetry is (centre at 0 - centre at +x) / (centre at -x - centre at 0), means over the starts
  that show road in all three frames;
- sampled futures (a transition with the spread head, temperature 1): windows every 5 frames, 5
  seed codes then 30 steps under the recorded actions, 16 sampled futures each: the best of the
  16 at the 30th step against predicting the held-out codes' mean; the 30th sampled codes' norm
  against real codes'; the Fréchet distance (a Gaussian fit to each set, as FID does on
  features) between the 30th predicted codes and the real codes there, for the mean rollout and
  the sampled one."""

import numpy as np
import torch

from sequences import TEACHER, predict, windows

PROBE_STARTS, PROBE_STEPS, PROBE_STEER, PROBE_ROWS = 50, 30, (0.3, 0.6), 60
HORIZON, FUTURES = 30, 16


def road_centre(frame, rows=PROBE_ROWS):
    """The mean column of the grey road pixels of the top `rows` rows, or None without road."""
    band = frame[:rows].astype(np.int16)
    lo, hi = band.min(2), band.max(2)
    grey = (hi - lo < 25) & (hi < 170) & (hi > 60)
    xs = np.nonzero(grey)[1]
    return float(xs.mean()) if len(xs) else None


@torch.no_grad()
def steering_probe(model, data, codes, actions, decode):
    """The right-way share and the symmetry at each steering of PROBE_STEER (module docstring)."""
    starts = windows(data, TEACHER)
    if not len(starts):
        return None
    picks = starts[np.linspace(0, len(starts) - 1, PROBE_STARTS).astype(int)]
    seeds = codes[torch.as_tensor(picks)[:, None] + torch.arange(TEACHER)]
    speed = actions[torch.as_tensor(picks) + TEACHER - 1, 0]
    z = torch.cat([seeds, seeds.new_zeros(len(seeds), PROBE_STEPS, seeds.shape[2])], 1)

    def centres(steer):
        c = torch.stack([speed, torch.full_like(speed, steer)], 1)[:, None].expand(-1, TEACHER - 1 + PROBE_STEPS, -1)
        last = predict(model.transition, z, c, TEACHER)[:, -1]
        return [road_centre(f) for f in decode(last)]

    out = {}
    straight = centres(0.0)
    for x in PROBE_STEER:
        left, right = centres(-x), centres(x)
        seen = [(l, s, r) for l, s, r in zip(left, straight, right) if None not in (l, s, r)]
        right_way = np.mean([l is not None and r is not None and l > r for l, r in zip(left, right)])
        # None where no start shows road in all three frames (or the road never moves left).
        moved_right = float(np.mean([s - r for _, s, r in seen])) if seen else None
        moved_left = float(np.mean([l - s for l, s, _ in seen])) if seen else None
        symmetry = moved_right / moved_left if seen and moved_left else None
        out[str(x)] = dict(right_way=float(right_way), symmetry=symmetry, road_moves_px_right_steering=moved_right,
                           road_moves_px_left_steering=moved_left, starts_with_road=len(seen))
    return out


def frechet(a, b):
    """Fréchet distance between Gaussians fitted to the rows of a and b (float64)."""
    a, b = a.double(), b.double()
    mu = (a.mean(0) - b.mean(0)).square().sum()
    ca, cb = torch.cov(a.T), torch.cov(b.T)
    # tr sqrt(ca cb) = tr sqrt(sqrt(ca) cb sqrt(ca)), a symmetric matrix's.
    w, v = torch.linalg.eigh(ca)
    root = v @ torch.diag(w.clamp_min(0).sqrt()) @ v.T
    cross = torch.linalg.eigvalsh(root @ cb @ root).clamp_min(0).sqrt().sum()
    return float(mu + ca.trace() + cb.trace() - 2 * cross)


@torch.no_grad()
def sampled_futures(model, data, codes, actions, seed=0):
    """The mean rollout's and (with the spread head) the sampled rollouts' measures at the 30th
    fed-back step (module docstring)."""
    starts = windows(data, TEACHER + HORIZON)
    if not len(starts):
        return None
    starts = starts[::5]
    idx = torch.as_tensor(starts)[:, None] + torch.arange(TEACHER + HORIZON)
    z, c = codes[idx], actions[idx[:, :-1]]
    real = z[:, -1]
    mean_code = codes.mean(0)
    base = float((mean_code - real).square().mean())
    mean = predict(model.transition, z, c, TEACHER)[:, -1]
    out = dict(windows=len(starts), mean_code_mse=base, encoded_norm=float(codes.norm(dim=1).mean()))
    out["mean"] = dict(mse_ratio=float((mean - real).square().mean()) / base,
                       norm_ratio=float(mean.norm(dim=1).mean()) / out["encoded_norm"],
                       frechet=frechet(mean, real))
    if not model.transition.spread:
        return out
    g = torch.Generator().manual_seed(seed)
    drawn = torch.stack([predict(model.transition, z, c, TEACHER, temperature=1.0, generator=g)[:, -1]
                         for _ in range(FUTURES)])  # [futures, windows, z]
    errors = (drawn - real).square().mean(2)  # [futures, windows]
    out["sampled"] = dict(best_of_16_mse_ratio=float(errors.min(0).values.mean()) / base,
                          one_mse_ratio=float(errors[0].mean()) / base,
                          norm_ratio=float(drawn[0].norm(dim=1).mean()) / out["encoded_norm"],
                          frechet=frechet(drawn[0], real))
    out["sampled"]["frechet_ratio"] = out["sampled"]["frechet"] / out["mean"]["frechet"]
    return out
