"""Training throughput of the II-DSU trainer: prints figures, asserts nothing.

    python bench/train.py              # ~1 minute on a 2-core laptop
    python bench/train.py --steps 50   # longer, steadier timings
    python bench/train.py --shards data   # the loader on real frames

1. tiny config on the CPU: training samples/s (forward, backward, AdamW step on an in-memory
   batch) and the process's peak resident memory;
2. the loader: decoded samples/s with 0, 1 and 2 DataLoader workers, per worker, at the tiny
   (R = 64) and paper (R = 256) target resolutions, on synthetic shards (noise images: JPEG
   decoding is slower than for real camera frames, so these are lower bounds) or `--shards`,
   for the shuffling reader with 64 open row groups (the default) and with 1 (whole row groups
   one after another: the frame order of the reader before issue 13);
2b. batch composition: distinct episodes per 32-frame batch on the index of a 146,880-frame
   build (8 towns x 51 episodes x 360 frames, one row group per episode as datagen's 32 MB
   target gives), from the loader's own schedule (`FrameStream.keys`, no decoding), with 2 and
   4 workers (the DataLoader takes batch j from worker j mod W);
3. `train fit --config tiny --epochs 1` end to end on 200 synthetic frames (the demo's size);
4. the paper config's parameter count, its FLOPs per training sample, its CPU training samples/s
   (float32, batch 4) and, where CUDA is available, its training samples/s, MFU and peak GPU
   memory in bf16 at batch 32 and 64 (and compiled, with --gpu-compile); compare with the
   loader's samples/s per worker to see how many workers keep the GPU fed.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `train` sets it (training/cli.py)

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests/

from tests.synthetic import write_shards  # noqa: E402
from training import data, fit  # noqa: E402
from training.config import PRESETS  # noqa: E402
from training.device import autocast, to_device  # noqa: E402
from training.losses import compute_losses  # noqa: E402
from training.model import IIDSU, INPUTS  # noqa: E402

BF16_PEAK_FLOPS = {"H100": 989e12, "H200": 989e12, "A100": 312e12, "L4": 121e12}
"""Dense bf16 tensor-core peaks (vendor data sheets, no sparsity), by a part of the device name."""


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB


def batch_of(root: Path, output_px: int, batch_size: int, device: torch.device) -> dict:
    stream = data.FrameStream(data.scan(root).iloc[:batch_size], output_px)
    batch = next(iter(data.make_loader(stream, batch_size, 0)))
    return to_device(batch, device)


def train_rate(
    preset: str,
    batch: dict,
    device: torch.device,
    steps: int,
    warmup: int = 3,
    compile: bool = False,
) -> float:
    """Training samples/s of `preset` on `batch` (bf16 autocast on CUDA, as `train fit`;
    `compile`: torch.compile'd as `train fit --compile`, its compile time in the warm-up)."""
    model_cfg, train_cfg = PRESETS[preset]
    torch.manual_seed(0)
    model = IIDSU(model_cfg).to(device, memory_format=torch.channels_last)
    optimizer = fit.make_optimizer(model, train_cfg)
    if compile:
        model = torch.compile(model)
    cuda = device.type == "cuda"

    def step():
        with autocast(device):
            out = model(*(batch[k] for k in INPUTS))
        loss = compute_losses(out, batch, train_cfg)["total"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    for _ in range(warmup):  # warm-up: allocator, oneDNN / cuDNN algorithm choice
        step()
    if cuda:
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    if cuda:
        torch.cuda.synchronize()
    return steps * len(batch["speed"]) / (time.perf_counter() - t0)


def train_flops_per_sample(preset: str, batch: dict) -> float:
    """FLOPs of one training step's forward and backward pass per sample (torch's FlopCounterMode:
    matmuls and convolutions, 2 per multiply-add), measured on a CPU batch."""
    torch.manual_seed(0)
    model_cfg, train_cfg = PRESETS[preset]
    model = IIDSU(model_cfg)
    with FlopCounterMode(display=False) as counter:
        out = model(*(batch[k] for k in INPUTS))
        compute_losses(out, batch, train_cfg)["total"].backward()
    return counter.get_total_flops() / len(batch["speed"])


def loader_rate(root: Path, output_px: int, workers: int, n: int, open_units: int) -> float:
    """Samples/s of a whole shuffled epoch over the first `n` frames of `root` (whole epochs, so
    that both readers open every row group once: the many-open reader opens its 64 at the
    start)."""
    stream = data.FrameStream(
        data.scan(root).iloc[:n], output_px, shuffle=True, buffer_size=64, open_units=open_units
    )
    loader = data.make_loader(stream, 8, workers)
    t0 = time.perf_counter()
    count = sum(len(b["speed"]) for b in loader)
    return count / (time.perf_counter() - t0)


def paper_scale_index(towns: int = 8, episodes: int = 51, frames: int = 360) -> pd.DataFrame:
    """A `data.scan` result for a 146,880-frame build: one shard and row group per episode."""
    parts = []
    for t in range(towns):
        for e in range(episodes):
            episode = f"town{t}-0-{e:04d}"
            parts.append(
                pd.DataFrame(
                    {
                        "path": f"/nonexistent/town{t}/{episode}.parquet",
                        "row_group": 0,
                        "row": np.arange(frames),
                        "episode_id": episode,
                        "town": f"town{t}",
                        "frame": np.arange(frames),
                    }
                )
            )
    return pd.concat(parts, ignore_index=True)


def episodes_per_batch(
    index: pd.DataFrame, batch: int, workers: int, open_units: int, buffer: int
) -> np.ndarray:
    """Distinct episodes in each full batch of an epoch, as the DataLoader would cut them."""
    stream = data.FrameStream(index, 256, shuffle=True, buffer_size=buffer, open_units=open_units)
    counts = []
    for w in range(workers):
        keys = [episode for episode, _ in stream.keys(w, workers)]
        for i in range(0, len(keys) - batch + 1, batch):
            counts.append(len(set(keys[i : i + batch])))
    return np.array(counts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="timed training steps")
    parser.add_argument("--shards", type=Path, help="measure the loader on these shards instead")
    parser.add_argument(
        "--paper-cpu-steps",
        type=int,
        default=3,
        help="timed CPU training steps of the paper config at batch 4 (0: skip; ~1 min)",
    )
    parser.add_argument(
        "--gpu-compile",
        action="store_true",
        help="on CUDA, also the paper config under torch.compile (compiling takes minutes)",
    )
    parser.add_argument(
        "--loader-frames", type=int, default=200, help="frames per loader epoch (200)"
    )
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    with tempfile.TemporaryDirectory() as tmp:
        # 200 frames: 2 towns x 4 episodes x 25 frames, row groups of 16 frames.
        root = write_shards(Path(tmp) / "shards", episodes=4, frames=25, row_group=16)

        tiny_model, tiny_train = PRESETS["tiny"]
        rss0 = peak_rss_mb()
        cpu = torch.device("cpu")
        b = tiny_train.batch_size
        rate = train_rate("tiny", batch_of(root, tiny_model.output_px, b, cpu), cpu, args.steps)
        print(
            f"\n1. tiny, CPU, batch {b}: {rate:.1f} training samples/s; peak RSS "
            f"{peak_rss_mb():.0f} MB ({peak_rss_mb() - rss0:.0f} MB above the process before)"
        )

        where = args.shards or root
        print(f"\n2. loader (decode JPEG/PNG + render targets) on {where}, samples/s:")
        for R in (64, 256):
            for workers in (0, 1, 2):
                rates = [loader_rate(where, R, workers, args.loader_frames, k) for k in (64, 1)]
                print(
                    f"   R={R:<3}  workers={workers}: 64 open row groups {rates[0]:6.1f} "
                    f"({rates[0] / max(workers, 1):.1f} per worker); 1 open (previous order) "
                    f"{rates[1]:6.1f} ({rates[1] / max(workers, 1):.1f}); "
                    f"ratio {rates[0] / rates[1]:.2f}"
                )

        paper = PRESETS["paper"][1]
        index = paper_scale_index()
        print(
            f"\n2b. distinct episodes per batch of {paper.batch_size}, {len(index)}-frame index, "
            f"shuffle buffer {paper.shuffle_buffer} (mean, min, max over an epoch's batches):"
        )
        for workers in (2, 4):
            for k in (1, paper.open_row_groups):
                n = episodes_per_batch(index, paper.batch_size, workers, k, paper.shuffle_buffer)
                print(
                    f"   workers={workers}, {k:>2} open row group(s): {n.mean():5.1f}, "
                    f"{n.min()}, {n.max()}  ({len(n)} batches)"
                )

        cfg = dataclasses.replace(
            tiny_train, shards=str(root), out=str(Path(tmp) / "run"), epochs=1
        )
        t0 = time.perf_counter()
        fit.fit(tiny_model, cfg, device="cpu")
        print(
            f"\n3. train fit --config tiny --epochs 1 on 200 frames: {time.perf_counter() - t0:.1f} s"
        )

        with torch.device("meta"):
            n_params = sum(p.numel() for p in IIDSU(PRESETS["paper"][0]).parameters())
        print(f"\n4. paper config: {n_params / 1e6:.2f} M parameters")
        paper_model, paper_train = PRESETS["paper"]
        flops = train_flops_per_sample("paper", batch_of(root, paper_model.output_px, 2, cpu))
        print(
            f"   {flops / 1e9:.1f} GFLOP per training sample (forward + backward, FlopCounterMode)"
        )
        if args.paper_cpu_steps:
            b = 4
            rss0 = peak_rss_mb()
            batch = batch_of(root, paper_model.output_px, b, cpu)
            rate = train_rate("paper", batch, cpu, args.paper_cpu_steps, warmup=1)
            print(
                f"   CPU, float32, batch {b}, {args.paper_cpu_steps} steps: {rate:.2f} training "
                f"samples/s = {rate * flops / 1e9:.0f} GFLOP/s; peak RSS {peak_rss_mb():.0f} MB "
                f"({peak_rss_mb() - rss0:.0f} MB above the process before)"
            )
        if torch.cuda.is_available():
            gpu = torch.device("cuda")
            name = torch.cuda.get_device_name()
            peak = next((v for k, v in BF16_PEAK_FLOPS.items() if k in name), None)
            runs = [(paper_train.batch_size, False), (2 * paper_train.batch_size, False)]
            runs += [(paper_train.batch_size, True)] if args.gpu_compile else []
            for b, compiled in runs:
                batch = batch_of(root, paper_model.output_px, b, gpu)
                torch.cuda.reset_peak_memory_stats()
                t0 = time.perf_counter()
                rate = train_rate("paper", batch, gpu, args.steps, compile=compiled)
                mfu = (
                    f"MFU {rate * flops / peak:.1%} of {peak / 1e12:.0f} TFLOP/s"
                    if peak
                    else "MFU: peak unknown"
                )
                print(
                    f"   {name}, bf16, batch {b}{', torch.compile' if compiled else ''}: "
                    f"{rate:.1f} training samples/s ({mfu}); peak GPU memory "
                    f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB; "
                    f"{time.perf_counter() - t0:.0f} s with warm-up",
                    flush=True,
                )
        else:
            print("   GPU: not measured (no CUDA device)")


if __name__ == "__main__":
    main()
