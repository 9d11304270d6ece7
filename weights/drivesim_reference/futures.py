"""The measures of a dream that steers both ways and samples its futures (issue 31), on held-out
episodes (`train eval` reports them under `futures` in eval.json; docs/fidelity.md):

- the steering probe (probe.py): 5 seed codes from real frames, then 30 fed-back steps with
  constant steering, the road's centre in the 30th generated frame (drivesim.carracing.probe_real measures the
  same in the real environment);
- sampled futures (a transition that samples: the spread head or the texture net, temperature 1): windows every 5 frames, 5
  seed codes then 30 steps under the recorded actions, 16 sampled futures each: the best of the
  16 at the 30th step against predicting the held-out codes' mean; the 30th sampled codes' norm
  against real codes'; the Fréchet distance (a Gaussian fit to each set, as FID does on
  features) between the 30th predicted codes and the real codes there, for the mean rollout and
  the sampled one;
- texture: how much of CarRacing's grass patches and kerbs the dream keeps under the recorded
  actions, step by step (held-out episodes in the default colours)."""

import numpy as np
import torch

from drivesim import probe
from drivesim_reference.sequences import TEACHER, predict

HORIZON, FUTURES, TRACKED = 30, 16, 5
# Texture: the fed-back steps read; CarRacing's grass (102, 204, 102) and its patches'
# (102, 230, 102), told apart halfway; a kerb's red (255, 0, 0) as it survives the downscaling.
TEXTURE_STEPS, PATCH_GREEN, GRASS_MARGIN, KERB_MARGIN = (1, 5, 10, HORIZON), 217, 50, 80


@torch.no_grad()
def steering_probe(model, data, codes, actions, decode):
    """The right-way share and the symmetry at each steering of probe.PROBE_STEER, after each
    of probe.READINGS steps: {steps: {steering: figures}}."""
    picks = probe.starts(data)
    if not len(picks):
        return None
    seeds = codes[torch.as_tensor(picks)[:, None] + torch.arange(probe.SEEDS)]
    speed = actions[torch.as_tensor(picks) + probe.SEEDS - 1, 0]
    z = torch.cat([seeds, seeds.new_zeros(len(seeds), probe.PROBE_STEPS, seeds.shape[2])], 1)
    # Between the seed frames the recorded actions, as the real probe drives the recording to the
    # start: the probe's steering fed there too would have the hidden state steer before the car.
    recorded = actions[torch.as_tensor(picks)[:, None] + torch.arange(probe.SEEDS - 1)]

    def centres(steer):
        held = torch.stack([speed, torch.full_like(speed, steer)], 1)[:, None].expand(-1, probe.PROBE_STEPS, -1)
        c = torch.cat([recorded.to(held.dtype), held], 1)
        fed = predict(model.transition, z, c, probe.SEEDS)[:, probe.SEEDS - 2:]  # [:, k]: after k steps
        return {k: [probe.centre(f) for f in decode(fed[:, k])] for k in probe.READINGS}

    straight = centres(0.0)
    turned = {x: (centres(-x), centres(x)) for x in probe.PROBE_STEER}
    return {str(k): {str(x): probe.symmetry(left[k], straight[k], right[k]) for x, (left, right) in turned.items()}
            for k in probe.READINGS}


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
def sampled_futures(model, data, codes, actions, seed=0, reference=None):
    """The mean rollout's and (with a sampler) the sampled rollouts' measures at the 30th
    fed-back step (module docstring); with `reference` (episodes, their codes and actions) also
    `real_futures`' baselines."""
    z, c = futures_windows(data, codes, actions, 5)
    if not len(z):
        return None
    real = z[:, -1]
    base = float((codes.mean(0) - real).square().mean())
    mean = predict(model.transition, z, c, TEACHER)[:, -1]
    out = dict(windows=len(z), mean_code_mse=base, encoded_norm=float(codes.norm(dim=1).mean()))
    if reference is not None:
        ref_data, ref_codes, ref_actions = reference
        ref_z, ref_c = futures_windows(ref_data, ref_codes, ref_actions, 2)
        out["real_futures"] = real_futures(z, c, base, ref_codes, ref_z, ref_c)
    out["mean"] = dict(mse_ratio=float((mean - real).square().mean()) / base,
                       norm_ratio=float(mean.norm(dim=1).mean()) / out["encoded_norm"],
                       frechet=frechet(mean, real))
    if not model.transition.samples:
        return out
    g = torch.Generator().manual_seed(seed)
    drawn = torch.stack([predict(model.transition, z, c, TEACHER, temperature=1.0, generator=g)[:, -1]
                         for _ in range(FUTURES)])  # [futures, windows, z]
    out["sampled"] = dict(best_of(drawn, real, base),
                          norm_ratio=float(drawn[0].norm(dim=1).mean()) / out["encoded_norm"])
    out["sampled"]["frechet_ratio"] = out["sampled"]["frechet"] / out["mean"]["frechet"]
    return out


def futures_windows(data, codes, actions, every):
    """Windows of 5 seed codes and 30 more, `every` frames apart: codes [B,35,z], actions [B,34,a]."""
    idx = torch.as_tensor(window_starts(data, every))[:, None] + torch.arange(TEACHER + HORIZON)
    return codes[idx], actions[idx[:, :-1]]


def window_starts(data, every):
    """The first frames of `futures_windows`' windows."""
    return data.windows(TEACHER + HORIZON)[::every]


@torch.no_grad()
def real_futures(z, c, base, ref_codes, ref_z, ref_c, seed=0):
    """Best-of-16 and Fréchet figures at the 30th step for futures made of real codes (module
    docstring): held-out windows z [B,35,z], c [B,34,a] and their mean-code error `base`; the
    reference's codes [N,z] and its windows ref_z, ref_c (every other start); None if the
    reference has fewer than 16 windows. `one_mse_ratio` is the first draw's: for the
    neighbours, the nearest window's."""
    real = z[:, -1]
    if len(ref_z) < FUTURES:
        return None
    g = torch.Generator().manual_seed(seed)
    drawn = ref_codes[torch.randint(len(ref_codes), (FUTURES, len(real)), generator=g)]  # [16, B, z]

    def key(zz, cc):  # the last two seed codes over the codes' spread, the actions over each one's,
        # the actions weighted to count as much as the codes
        codes_part = zz[:, TEACHER - 2:TEACHER].flatten(1) / ref_codes.std()
        acts = cc.flatten(1) / ref_c.flatten(0, 1).std(0).clamp_min(1e-6).repeat(cc.shape[1])
        return torch.cat([codes_part, acts * (codes_part.shape[1] / acts.shape[1]) ** 0.5], 1)

    near = torch.cdist(key(z, c), key(ref_z, ref_c)).topk(FUTURES, largest=False).indices  # [B, 16]
    neighbours = ref_z[near, -1].transpose(0, 1)  # [16, B, z]

    return dict(reference_windows=len(ref_z), random_codes=best_of(drawn, real, base),
                nearest_windows=best_of(neighbours, real, base))


def best_of(futures, real, base):
    """Futures [16, B, z] against the real codes [B, z]: the best of the 16 and the first alone,
    each window's mean squared error averaged and over the mean code's `base`, and the first's
    Fréchet distance to the real codes."""
    errors = (futures - real).square().mean(2)  # [16, B]
    return dict(best_of_16_mse_ratio=float(errors.min(0).values.mean()) / base,
                one_mse_ratio=float(errors[0].mean()) / base, frechet=frechet(futures[0], real))


def through_zero(real, other):
    """The least-squares slope of `other` on `real` through the origin: 1 where moves match."""
    scale = float((real * real).sum())
    return float((real * other).sum()) / scale if scale > 0 else None


@torch.no_grad()
def road_tracking(model, data, codes, actions, decode, recon_frames):
    """The road's centre (probe.centre) after TRACKED recorded steps from windows every other
    frame, in the recorded frames, their reconstructions `recon_frames` (uint8) and the mean
    rollout: the recorded frames' mean absolute move (px), and the slopes of the reconstructions'
    and the rollout's moves on it."""
    starts = data.windows(TEACHER + TRACKED)[::2]
    if not len(starts):
        return None
    idx = torch.as_tensor(starts)[:, None] + torch.arange(TEACHER + TRACKED)
    dreamt = decode(predict(model.transition, codes[idx], actions[idx[:, :-1]], TEACHER)[:, -1])
    first, last = starts + TEACHER - 1, starts + TEACHER - 1 + TRACKED
    # The recorded frames' and the reconstructions' centres at the first and the last frame,
    # and the mean rollout's at the last.
    centres = [[probe.centre(f) for f in frames[i]] for frames in (data.frames, recon_frames) for i in (first, last)]
    centres.append([probe.centre(f) for f in dreamt])
    moves = torch.tensor([(r1 - r0, c1 - c0, d - c0) for r0, r1, c0, c1, d in zip(*centres)
                          if None not in (r0, r1, c0, c1, d)], dtype=torch.float64).reshape(-1, 3)
    real, recon, dream = moves.T
    return dict(steps=TRACKED, windows=len(moves), real_move_px=float(real.abs().mean()) if len(moves) else None,
                reconstruction_slope=through_zero(real, recon), dream_slope=through_zero(real, dream))


def texture_figures(frames):
    """The texture of uint8 frames [N,H,W,3] in their top probe.PROBE_ROWS rows (no car): the
    share of grass pixels (green above red and blue by GRASS_MARGIN) in the patches' lighter
    green, over the frames with grass; and red pixels (red above green and blue by KERB_MARGIN),
    the kerbs, per thousand pixels."""
    f = frames[:, :probe.PROBE_ROWS].astype(np.int16)
    red, green, blue = f[..., 0], f[..., 1], f[..., 2]
    grass = green - np.maximum(red, blue) > GRASS_MARGIN
    patch = grass & (green >= PATCH_GREEN)
    with_grass = grass.any((1, 2))
    share = patch.sum((1, 2))[with_grass] / grass.sum((1, 2))[with_grass]
    kerbs = red - np.maximum(green, blue) > KERB_MARGIN
    return dict(patch_share=float(share.mean()) if len(share) else None, kerb_per_mille=1e3 * float(kerbs.mean()))


@torch.no_grad()
def texture(model, data, codes, actions, decode, recon_frames, seed=0, reference=None):
    """Texture kept under the recorded actions: windows every 10 frames, 5 seed codes, then
    after each of TEXTURE_STEPS fed-back steps, `texture_figures` of the recorded frames, their
    reconstructions `recon_frames` (uint8), the mean rollout's and (with a sampler) one rollout's sampled at
    temperature 1; with `reference` (episodes, codes, actions) also two baselines: `linear`, a
    least-squares predictor fitted on the reference (`linear_predictor`), and `copy`, the last
    seed code again. {source: {figure: [one per step]}}."""
    z, c = futures_windows(data, codes, actions, 10)
    if not len(z):
        return None
    starts = window_starts(data, 10)
    rollouts = dict(mean=predict(model.transition, z, c, TEACHER))
    if model.transition.samples:
        g = torch.Generator().manual_seed(seed)
        rollouts["sampled"] = predict(model.transition, z, c, TEACHER, temperature=1.0, generator=g)
    fitted = linear_predictor(*reference) if reference is not None else None
    if fitted is not None:
        rollouts["linear"] = linear_rollout(fitted, z, c)
        rollouts["copy"] = z[:, TEACHER - 1:TEACHER].expand(-1, z.shape[1] - 1, -1)
    # After k fed-back steps: frame TEACHER - 1 + k of a window, prediction TEACHER - 2 + k.
    sources = dict(recorded=lambda k: data.frames[starts + TEACHER - 1 + k],
                   reconstruction=lambda k: recon_frames[starts + TEACHER - 1 + k],
                   **{name: (lambda k, p=p: decode(p[:, TEACHER - 2 + k])) for name, p in rollouts.items()})
    out = dict(steps=list(TEXTURE_STEPS), windows=len(z))
    for name, frames in sources.items():
        readings = [texture_figures(frames(k)) for k in TEXTURE_STEPS]
        out[name] = {key: [r[key] for r in readings] for key in readings[0]}
    return out


def linear_predictor(data, codes, actions, ridge=1e-2):
    """The least-squares linear predictor of the next code, `z' = [z, z_prev, c, 1] M`, fitted
    (float64, a ridge of `ridge` per window) on every window of 3 frames of the episodes: a
    predictor of the mean next code that keeps a code by a near-identity map as easily as it
    moves it. None if the episodes have no such window."""
    t = torch.as_tensor(data.windows(3)) + 1
    if not len(t):
        return None
    z, a = codes.double(), actions.double()
    x = torch.cat([z[t], z[t - 1], a[t], z.new_ones(len(t), 1)], 1)
    gram = x.T @ x + ridge * len(t) * torch.eye(x.shape[1], dtype=torch.float64)
    return torch.linalg.solve(gram, x.T @ z[t + 1])


def linear_rollout(m, z, c):
    """`predict`'s outputs for the predictor `m` (linear_predictor): windows z [B,T,z], c [B,T-1,a],
    the first TEACHER codes given, then fed back (its outputs before them are the given codes)."""
    z, c = z.double(), c.double()
    out = [z[:, t + 1] for t in range(TEACHER - 1)]
    prev, cur = z[:, TEACHER - 2], z[:, TEACHER - 1]
    for t in range(TEACHER - 1, z.shape[1] - 1):
        prev, cur = cur, torch.cat([cur, prev, c[:, t], z.new_ones(len(z), 1)], 1) @ m
        out.append(cur)
    return torch.stack(out, 1).float()
