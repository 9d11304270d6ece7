"""Export weights to the drivesim safetensors format and/or to ONNX.

    weights/tool export CKPT.pt --config CONFIG.json --out MODEL.safetensors [--dtype f16]
    weights/tool export MODEL.safetensors --onnx DIR

The input is either a PyTorch checkpoint (a bare DriveSim state_dict, or a dict
{"state_dict": ..., "config": {...}}) or an existing drivesim safetensors file.
--onnx writes DIR/encoder.onnx (frame [1,C,H,W] -> mean [1,z]),
DIR/generator.onnx (z [1,z] -> frame [1,C,H,W]) and DIR/transition.onnx
((z [1,z], h [1,hd], c [1,action]) -> (z', h')), float32, opset 17.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import torch
from safetensors import safe_open
from torch import nn

from drivesim_reference.model import (ACTIONS_KEY, DTYPES, FRAME_HZ_KEY, Config, DriveSim, from_state_dict,
                                      load_drivesim, save_drivesim)

OPSET = 17


def load_any(path: Path, config: Path | None) -> tuple[DriveSim, Config]:
    if path.suffix == ".safetensors":
        return load_drivesim(path)
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    state = ckpt.get("state_dict", ckpt)
    if config is not None:
        cfg = Config.from_json(config.read_text())
    elif "config" in ckpt:
        cfg = Config(**ckpt["config"])
    else:
        raise SystemExit(f"{path}: no config in the checkpoint, pass --config")
    return from_state_dict(cfg, state), cfg


class EncoderMean(nn.Module):
    """The encoder without the logsigma head: all that simulation needs."""

    def __init__(self, model: DriveSim):
        super().__init__()
        self.encoder = model.encoder

    def forward(self, frame: torch.Tensor) -> torch.Tensor:
        return self.encoder(frame)[0]


def export_onnx(model: DriveSim, cfg: Config, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    z = torch.zeros(1, cfg.z_dim)
    graphs = {
        # eval(): the exporter restores each wrapper's train flag recursively afterwards,
        # which would switch a fresh (training) wrapper's encoder to batch statistics.
        "encoder": (EncoderMean(model).eval(), (torch.zeros(1, cfg.channels, cfg.height, cfg.width),), ["frame"], ["mean"]),
        "generator": (model.generator, (z,), ["z"], ["frame"]),
        "transition": (
            model.transition,
            (z, torch.zeros(1, cfg.hidden_dim), torch.zeros(1, cfg.action_dim)),
            ["z", "h", "c"],
            ["z_next", "h_next"],
        ),
    }
    for name, (module, args, inputs, outputs) in graphs.items():
        # dynamo=False: the TorchScript exporter needs no onnxscript dependency;
        # its deprecation warning is noise here.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(
                module, args, str(out / f"{name}.onnx"),
                input_names=inputs, output_names=outputs, opset_version=OPSET, dynamo=False,
            )


def source_metadata(source: Path) -> dict:
    """The source drivesim file's metadata ({} for a checkpoint)."""
    if source.suffix != ".safetensors":
        return {}
    with safe_open(str(source), framework="pt") as f:
        return dict(f.metadata() or {})


def actions_of(source: Path, given: Path | None) -> list[dict] | None:
    """The action descriptions to write: `given`'s, else the source drivesim file's."""
    if given is not None:
        return json.loads(given.read_text())
    text = source_metadata(source).get(ACTIONS_KEY)
    return json.loads(text) if text else None


def frame_hz_of(source: Path) -> float | None:
    """The source drivesim file's frame rate, kept in what is written from it."""
    text = source_metadata(source).get(FRAME_HZ_KEY)
    return float(text) if text else None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", type=Path, help="checkpoint .pt or drivesim .safetensors")
    p.add_argument("--config", type=Path, help="config JSON (nine integer keys), for a .pt without one")
    p.add_argument("--out", type=Path, help="drivesim safetensors file to write")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32", help="dtype of --out (default f32)")
    p.add_argument("--onnx", type=Path, metavar="DIR", help="also write ONNX graphs into DIR")
    p.add_argument("--actions", type=Path, metavar="JSON",
                   help="what the actions mean and their trained range, written as drivesim.actions "
                        "(a JSON array, weights/README.md §3; default: the input file's, if any)")
    args = p.parse_args(argv)
    if args.out is None and args.onnx is None:
        p.error("nothing to do: give --out and/or --onnx")

    model, cfg = load_any(args.input, args.config)
    if args.out is not None:
        save_drivesim(model, cfg, args.out, args.dtype, actions=actions_of(args.input, args.actions),
                      frame_hz=frame_hz_of(args.input))
        print(f"wrote {args.out} ({args.dtype}, config {json.loads(cfg.to_json())})")
    if args.onnx is not None:
        export_onnx(model, cfg, args.onnx)
        print(f"wrote encoder/generator/transition .onnx to {args.onnx}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
