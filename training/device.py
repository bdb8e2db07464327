"""Where a run computes: the device, this process's place under DDP, bf16 autocast, and moving
a batch there. Shared by `train fit`, `train eval`, `train analyze` and `drive`'s model policy."""

from __future__ import annotations

import os
from contextlib import nullcontext
from dataclasses import dataclass

import torch
import torch.distributed as dist

from training.errors import UserError


@dataclass(frozen=True)
class Process:
    """This process's place in a (possibly one-process) data-parallel run."""

    rank: int
    world: int
    device: torch.device

    @property
    def master(self) -> bool:
        return self.rank == 0


def choose_device(device: str = "auto") -> torch.device:
    """ "auto" (CUDA if present), "cpu" or "cuda"; UserError if CUDA is asked for but absent."""
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda: no CUDA device is available")
    use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if use_cuda:
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return torch.device("cpu")


def start_process(device: str = "auto") -> Process:
    """Join the process group when started by torchrun (WORLD_SIZE > 1): NCCL on GPUs, gloo on
    CPUs. `device` as in `choose_device`; under torchrun, process LOCAL_RANK takes GPU LOCAL_RANK."""
    dev = choose_device(device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    return Process(dist.get_rank() if world > 1 else 0, world, dev)


def autocast(device: torch.device):
    """bf16 autocast on GPUs (no loss scaling needed, unlike fp16); plain float32 on CPUs."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return nullcontext()


def to_device(batch: dict, device: torch.device) -> dict:
    """Tensors of a batch onto `device` (the camera and LiDAR in channels_last, the layout the
    convolutions run fastest in, on CPU too: see training/convnext.py); other values as is."""
    moved = {}
    for k, v in batch.items():
        if isinstance(v, torch.Tensor):
            fmt = torch.channels_last if v.ndim == 4 else torch.preserve_format
            v = v.to(device, non_blocking=True, memory_format=fmt)
        moved[k] = v
    return moved
