"""`train eval`: how well a weight file simulates held-out episodes (weights/TRAINING_FILES.md §5)."""

import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from drivesim import episodes
from drivesim import probe
from drivesim.carracing import probe_real
from drivesim_reference.model import load_drivesim
from drivesim_reference.futures import road_tracking, sampled_futures, steering_probe, texture
from drivesim_reference.sequences import SEQ, TEACHER, encode, predict
from drivesim_reference.vae_gan import psnr, to_image, to_input

STEER = 0.6  # constant steering of the steering-response test, well inside the recorded range


def sheet(rows, gap=2):
    """Grid of uint8 HWC frames (a list of rows of frames) on a white background."""
    h, w, _ = rows[0][0].shape
    cols = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + gap) - gap, cols * (w + gap) - gap, 3), 255, np.uint8)
    for i, row in enumerate(rows):
        for j, f in enumerate(row):
            out[i * (h + gap):i * (h + gap) + h, j * (w + gap):j * (w + gap) + w] = f
    return Image.fromarray(out)


@torch.no_grad()
def rollout(model, seed_codes, actions):
    """Codes of the frames after the seeds: seed_codes [S,z], actions [S-1+T,2] -> [T,z].
    Batched twin of DriveSim.rollout that starts from codes."""
    z = torch.cat([seed_codes, seed_codes.new_zeros(len(actions) + 1 - len(seed_codes), seed_codes.shape[1])])
    return predict(model.transition, z[None], actions[None], len(seed_codes))[0, len(seed_codes) - 1:]


def road_offset(frame):
    """The road's centre in a band just ahead of the car minus the car's column, in pixels, or
    None where no road shows (grey pixels against grass, as examples/drive.rs measures it)."""
    h, w, _ = frame.shape
    xs = np.nonzero(probe.road.road_mask(frame[h * 6 // 10:h * 3 // 4]))[1]
    return float(xs.mean() - w // 2) if len(xs) else None


def mean_offset(frames):
    """The mean of `road_offset` over the frames that show road, or None if none does."""
    seen = [o for o in map(road_offset, frames) if o is not None]
    return float(np.mean(seen)) if seen else None


FED_BACK = (10, 30)  # fed-back steps at which the latent error is reported
DIRECTION_SEEDS, DIRECTION_STEPS, DIRECTION_STEER = 50, 30, (0.3, 0.6)


@torch.no_grad()
def fidelity(model, data, codes, recon, frames, actions, decode):
    """The fidelity figures of issue 19 on held-out episodes: reconstruction PSNR (mean and 10th
    percentile over frames); the latent error after 10 and 30 fed-back steps (and over all of the
    first 10 and 30) against predicting the data's mean code; how often the road sits further left
    under constant right steering than under left (road centre in the band ahead, 30 steps, 50
    starts); and the norm of rolled-out codes against encoded frames. The road's offset is averaged
    over every 3rd generated frame that shows road (a road the car turns away from leaves the
    band)."""
    per_frame = ((recon.clamp(-1, 1) - to_input(frames)) * 127.5).square().flatten(1).mean(1)
    per_frame = 10 * torch.log10(255.0**2 / per_frame.clamp_min(1e-10))
    out = dict(psnr_db=float(per_frame.mean()), psnr_p10_db=float(per_frame.quantile(0.1)))

    horizon = max(FED_BACK)
    starts = data.windows(TEACHER + horizon)
    if len(starts):
        starts = starts[::5]
        idx = torch.as_tensor(starts)[:, None] + torch.arange(TEACHER + horizon)
        z, c = codes[idx], actions[idx[:, :-1]]
        pred = predict(model.transition, z, c, TEACHER)  # pred[:, t]: the code of frame t+1
        mean_code = codes.mean(0)
        latent = dict(windows=len(starts))
        for k in FED_BACK:
            t = TEACHER - 1 + k  # the k-th fed-back prediction
            # After the k-th fed-back step, and (the other reading of "after k steps") over all
            # of the first k.
            readings = ((k, pred[:, t - 1], z[:, t]), (f"1_to_{k}", pred[:, TEACHER - 1:t], z[:, TEACHER:t + 1]))
            for name, p, true in readings:
                err, base = float((p - true).square().mean()), float((mean_code - true).square().mean())
                latent[f"mse_{name}"], latent[f"mean_code_mse_{name}"], latent[f"ratio_{name}"] = err, base, err / base
        out["latent"] = latent
        fed = pred[:, TEACHER - 1:]
        out["code_norm"] = dict(rollout=float(fed.norm(dim=2).mean()), encoded=float(codes.norm(dim=1).mean()))
        out["code_norm"]["ratio"] = out["code_norm"]["rollout"] / out["code_norm"]["encoded"]

    starts = data.windows(TEACHER)
    if len(starts):
        picks = starts[np.linspace(0, len(starts) - 1, DIRECTION_SEEDS).astype(int)]
        seeds = codes[torch.as_tensor(picks)[:, None] + torch.arange(TEACHER)]
        speed = actions[torch.as_tensor(picks) + TEACHER - 1, 0]
        direction = {}
        for steer in DIRECTION_STEER:
            offsets = {}
            for sign in (-1, 1):
                c = torch.stack([speed, torch.full_like(speed, sign * steer)], 1)[:, None]
                c = c.expand(-1, TEACHER - 1 + DIRECTION_STEPS, -1)
                z = torch.cat([seeds, seeds.new_zeros(len(seeds), DIRECTION_STEPS, seeds.shape[2])], 1)
                # Every 3rd step: a road that turns out of the band late still counts its way.
                fed = predict(model.transition, z, c, TEACHER)[:, TEACHER - 1 + 2::3]
                frames_of = decode(fed.flatten(0, 1)).reshape(len(seeds), fed.shape[1], *frames.shape[1:])
                offsets[sign] = [mean_offset(rollout) for rollout in frames_of]
            # Steering right (positive) turns the car right: the road moves left in the image.
            right_way = [l is not None and r is not None and r < l for l, r in zip(offsets[-1], offsets[1])]
            direction[str(steer)] = float(np.mean(right_way))
        out["road_moves_right_way"] = direction
    return out


@torch.no_grad()
def evaluate(args):
    model, cfg = load_drivesim(args.weights)
    data = episodes.read(args.data)
    figs = Path(args.figures)
    figs.mkdir(parents=True, exist_ok=True)
    frames = torch.from_numpy(data.frames)
    actions = torch.from_numpy(data.actions)
    decode = lambda z: to_image(model.generator(z))  # noqa: E731
    result = dict(weights=str(args.weights), data=str(args.data), episodes=len(data), frames=len(frames))

    # Reconstruction: encoder mean -> generator.
    codes = encode(model, frames, 256)
    recon = torch.cat([model.generator(codes[i:i + 256]) for i in range(0, len(codes), 256)])
    result["reconstruction_psnr_db"] = psnr(recon, to_input(frames))
    pick = np.linspace(0, len(frames) - 1, 8).astype(int)
    sheet([list(data.frames[pick]), list(to_image(recon[pick]))]).save(figs / "reconstruction.png")

    # Latent prediction: 5 true codes, then 10 steps fed back, from windows 5 frames apart.
    starts = data.windows(SEQ)[::5]
    idx = torch.as_tensor(starts)[:, None] + torch.arange(SEQ)
    z, c = codes[idx], actions[idx[:, :-1]]
    pred = predict(model.transition, z, c, TEACHER)  # pred[:, t] is the code of frame t+1
    first, last = TEACHER - 1, SEQ - 2
    mse = lambda a, b: float((a - b).square().mean())  # noqa: E731
    result["latent"] = dict(
        windows=len(starts),
        mse_1_step=mse(pred[:, first], z[:, first + 1]),
        mse_10_step=mse(pred[:, last], z[:, last + 1]),
        copy_last_1_step=mse(z[:, first], z[:, first + 1]),  # baseline: nothing moves
        copy_last_10_step=mse(z[:, first], z[:, last + 1]),
        code_variance=float(codes.var(0).mean()),  # baseline: predict the mean code
    )

    result["fidelity"] = fidelity(model, data, codes, recon, frames, actions, decode)
    reference = None
    if args.reference:
        ref = episodes.read(args.reference)
        reference = (ref, encode(model, torch.from_numpy(ref.frames), 256), torch.from_numpy(ref.actions))
    recon_frames = to_image(recon)
    result["futures"] = dict(steering_probe=steering_probe(model, data, codes, actions, decode),
                             at_30_steps=sampled_futures(model, data, codes, actions, reference=reference),
                             road_tracking=road_tracking(model, data, codes, actions, decode, recon_frames),
                             texture=texture(model, data, codes, actions, decode, recon_frames, reference=reference))
    if args.probe_real:  # the real car's probe on the same starts (cached beside the data), and the gaps
        real = probe_real.cached(args.data, args.workers)
        result["futures"]["steering_probe_real"] = real
        result["futures"]["steering_against_real"] = probe.against_real(
            result["futures"]["steering_probe"], {k: real[k] for k in map(str, probe.READINGS)})

    # Steering response: same seed frames, constant actions, 30 steps.
    s0, _ = data.bounds()[0]
    seed_codes = codes[s0:s0 + TEACHER]
    speed = float(actions[s0:s0 + 30, 0].mean())
    steps = 30

    def constant(steer):
        return rollout(model, seed_codes, torch.tensor([[speed, steer]]).repeat(TEACHER - 1 + steps, 1))

    left, right, left_again = constant(-STEER), constant(STEER), constant(-STEER)
    img = {k: decode(v).astype(np.float32) for k, v in (("l", left), ("r", right), ("l2", left_again))}
    result["steering"] = dict(
        speed=speed, steps=steps, steering=[-STEER, STEER],
        left_vs_right_pixel_mad=float(np.abs(img["l"] - img["r"]).mean()),
        left_vs_right_latent_mse=mse(left, right),
        identical_actions_pixel_mad=float(np.abs(img["l"] - img["l2"]).mean()),
        identical_actions_latent_mse=mse(left, left_again),
    )
    straight = decode(constant(0.0))
    every = list(range(2, steps, 3))
    rows = [img["l"][every].astype(np.uint8), straight[every], img["r"][every].astype(np.uint8)]
    sheet([list(row) for row in rows]).save(figs / "steering.png")  # left, straight, right

    # Contact sheet: 5 seed frames, then every 10th frame of a 100-step rollout driven by
    # the recorded actions; the row below shows the recorded frames at the same steps.
    n = 100
    if data.bounds()[0][1] - s0 >= TEACHER + n:
        pred = rollout(model, seed_codes, actions[s0:s0 + TEACHER - 1 + n])
        shown = list(range(9, n, 10))
        top = list(data.frames[s0:s0 + TEACHER]) + list(decode(pred[shown]))
        bottom = list(data.frames[s0:s0 + TEACHER]) + list(data.frames[[s0 + TEACHER + i for i in shown]])
        sheet([top, bottom]).save(figs / "contact_sheet.png")
        if model.transition.samples:
            # The same drive sampled (temperature 1) between the mean rollout and the recording.
            g = torch.Generator().manual_seed(0)
            z = torch.cat([seed_codes, seed_codes.new_zeros(n, seed_codes.shape[1])])[None]
            drawn = predict(model.transition, z, actions[None, s0:s0 + TEACHER - 1 + n], TEACHER,
                            temperature=1.0, generator=g)[0, TEACHER - 1:]
            sampled = list(data.frames[s0:s0 + TEACHER]) + list(decode(drawn[shown]))
            sheet([top, sampled, bottom]).save(figs / "contact_sheet_sampled.png")

    if args.seed_clip:
        clip = episodes.Episodes(data.frames[s0:s0 + 8].copy(), data.actions[s0:s0 + 8].copy(),
                                 np.zeros(1, dtype=np.int64))
        episodes.write(args.seed_clip, clip, {"source": f"first 8 frames of {args.data}"})
    (figs / "eval.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    for steps, by_steer in result["futures"].get("steering_against_real", {}).items():
        for x, g in by_steer.items():
            f = [f"{v:.2f}" if v is not None else "-" for v in (g["symmetry"], g["symmetry_real"],
                                                                 g["moves_left_steering"], g["moves_right_steering"])]
            print(f"against the real car, {steps} steps at ±{x}: right way {g['right_way_gap_points']:+.0f} points, "
                  f"symmetry {f[0]} (real {f[1]}), moves {f[2]} (left) and {f[3]} (right) of the real ones")
