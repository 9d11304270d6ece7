"""Training on several processes (torchrun): each process takes an equal share of every global
batch, gradients and batch-norm statistics are averaged over all of them, so that a run on any
number of processes is the run of one process on the global batch (within float tolerance)."""

import os

import torch
import torch.distributed as dist
import torch.distributed.nn.functional as dist_nn
from torch import nn


def world() -> int:
    """Processes training together: torchrun's WORLD_SIZE once `start_distributed` ran, else 1."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def start_distributed(device: str) -> tuple[int, torch.device]:
    """Under torchrun (WORLD_SIZE set): joins the process group (NCCL on GPUs, gloo on the CPU)
    and returns this process's rank and device; otherwise rank 0 and `device`."""
    if "WORLD_SIZE" not in os.environ:
        return 0, torch.device(device)
    dev = torch.device(device)
    if dev.type == "cuda":
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(dev)
    dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return dist.get_rank(), dev


def average_gradients(grads):
    """The mean over the processes of each process's gradients, in place (each process's loss is
    the mean over its equal share of the global batch, so this is the global batch's gradient)."""
    if world() > 1:
        for g in grads:
            dist.all_reduce(g)
            g /= world()


def share(t: torch.Tensor) -> torch.Tensor:
    """This process's equal share of a global batch (all of it in a single process)."""
    if world() == 1:
        return t
    if len(t) % world():
        raise ValueError(f"a batch of {len(t)} does not split over {world()} processes")
    n = len(t) // world()
    return t[dist.get_rank() * n:(dist.get_rank() + 1) * n]


def global_var(t: torch.Tensor) -> torch.Tensor:
    """The unbiased variance of every value of `t` on every process (no gradient needed)."""
    if world() == 1:
        return t.var()
    stats = torch.stack([t.sum(), t.square().sum(), torch.tensor(float(t.numel()), device=t.device, dtype=t.dtype)])
    dist.all_reduce(stats)
    total, squares, n = stats
    return (squares - total * total / n) / (n - 1)


class GlobalBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are those of the global batch, over every process
    (differentiably, through `all_reduce`), so that a run on several processes trains as one
    process with the global batch would. Runs on the CPU's gloo too (nn.SyncBatchNorm needs
    GPUs). In one process, or in eval mode, it is BatchNorm2d; same tensors, same names."""

    def forward(self, x):
        if not (self.training and world() > 1):
            return super().forward(x)
        count = torch.tensor(float(x.numel() // x.shape[1]), device=x.device, dtype=x.dtype)
        dist.all_reduce(count)
        sums = dist_nn.all_reduce(torch.stack([x.sum((0, 2, 3)), x.square().sum((0, 2, 3))]))
        mean = sums[0] / count
        var = sums[1] / count - mean.square()
        with torch.no_grad():
            m = self.momentum
            self.running_mean.mul_(1 - m).add_(m * mean)
            self.running_var.mul_(1 - m).add_(m * var * count / (count - 1))
            self.num_batches_tracked += 1
        shape = (1, -1, 1, 1)
        scale = self.weight * torch.rsqrt(var + self.eps)
        return (x - mean.view(shape)) * scale.view(shape) + self.bias.view(shape)


def globalise_batch_norms(module: nn.Module) -> nn.Module:
    """Every BatchNorm2d of `module` as a GlobalBatchNorm holding the same tensors."""
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm2d:
            g = GlobalBatchNorm(child.num_features, child.eps, child.momentum).to(child.weight.device)
            g.load_state_dict(child.state_dict())
            setattr(module, name, g)
        else:
            globalise_batch_norms(child)
    return module
