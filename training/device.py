"""Where a run computes: the device, this process's place under DDP, bf16 autocast, and moving
a batch there, the CPU threads and the allocator. Shared by `train fit`, `train eval`, `train analyze` and `drive`'s model policy."""

from __future__ import annotations

import ctypes
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


def cpu_threads(requested: int = 0) -> int:
    """Intra-op threads for this process: `requested`; else $OMP_NUM_THREADS if set (the
    user's); else the cores its CPU affinity allows divided by the training processes on this
    machine (torchrun's LOCAL_WORLD_SIZE). torch's own default counts the machine's cores, also
    those a container or a sibling rank uses."""
    if requested:
        return requested
    if os.environ.get("OMP_NUM_THREADS", "").isdigit():
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    return max(1, len(os.sched_getaffinity(0)) // local_world)


def tune_allocator() -> None:
    """Let glibc's malloc keep freed memory for the next step instead of handing it back to
    the kernel: a training step frees and reallocates the same few-MB tensors, and each fresh
    mapping costs a page fault per 4 kB. Tiny config, one thread: ~10,000 faults and 30-40 ms
    of system time a step before, ~1,500 and 11-17 ms after (docs/speed.md). No-op off glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # glibc's <malloc.h>
    libc.mallopt(m_mmap_threshold, 32 << 20)  # glibc's largest: below it, from the heap
    libc.mallopt(m_trim_threshold, 1 << 30)  # keep up to 1 GB of free heap
    libc.mallopt(m_top_pad, 64 << 20)  # grow the heap 64 MB at a time
