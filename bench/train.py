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

With --profile DIR or --fit-shards DIR only these run (add --all for the sections above too):

5. `--profile DIR`: where one tiny training step goes, on real frames of DIR (batch 8): the
   loader's pieces per frame (Parquet read, JPEG and PNG decoding, targets, zoom-out, the
   decoded-frame cache's read) and per batch (collate, to_device), then the forward and the
   backward of each part of the model measured alone on the inputs a real step gives it, the
   loss, gradient clipping, AdamW and a whole step, at 1 and 2 intra-op threads (medians);
6. `--fit-shards DIR`: `train fit --config tiny --epochs 1` end to end on --fit-episodes of
   DIR's episodes (one per town in turn), as a subprocess per variant: the code of git ref
   --baseline (default main) against this tree (`--variant` adds others: `REF[:ARGS]`, REF a
   git ref or `.` for this tree, ARGS extra fit flags and VAR=VALUE environment settings),
   interleaved over --repeats rounds (the order reversed every other round), so that a busy
   machine slows all alike. Prints per variant the median training-loop samples/s (what
   metrics.jsonl logs), the wall time of the whole command (start-up, cache fill, validation
   included) and its ratio to the first variant, and how far each variant's logged losses are
   from the first's (same seed: the same batches; float rounding only). This tree's decoded-
   frame cache lives in a temporary directory: its first run fills it (the "cold" figure).

    python bench/train.py --profile /work/main/runs/d41
    python bench/train.py --fit-shards /work/main/runs/d41 --fit-episodes 8 --repeats 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `train` sets it (training/cli.py)

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests/ and this tree's code

from tests.synthetic import write_shards  # noqa: E402
from training import data, decode, fit  # noqa: E402
from training.config import PRESETS  # noqa: E402
from training.device import autocast, to_device  # noqa: E402
from training.losses import compute_losses  # noqa: E402
from training.model import IIDSU, INPUTS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

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


def _median_ms(f, reps: int, warmup: int = 2, clock=time.perf_counter) -> float:
    """Median ms of `f()` by `clock`: wall time, or `time.process_time` (CPU time of all the
    process's threads: on a shared machine, the work done, whatever else runs)."""
    for _ in range(warmup):
        f()
    times = []
    for _ in range(reps):
        t0 = clock()
        f()
        times.append(clock() - t0)
    return 1e3 * float(np.median(times))


def profile_loader(root: Path, frames: int = 96, batch: int = 8) -> None:
    """Section 5a: the loader's pieces, CPU ms per frame (per batch for collate and to_device)."""
    import pyarrow.parquet as pq
    from torch.utils.data import default_collate

    from schemas import codecs
    from training.augment import zoom_out
    from training.targets import render_density, visible_boxes

    index = data.scan(root)
    index = index[index.path == index.path.iloc[0]].iloc[:frames]
    model_cfg, train_cfg = PRESETS["tiny"]
    R = model_cfg.output_px
    times: dict[str, list[float]] = {}

    def timed(name, f, *a):
        t0 = time.process_time()
        out = f(*a)
        times.setdefault(name, []).append(1e3 * (time.process_time() - t0))
        return out

    shard = pq.ParquetFile(index.path.iloc[0])
    columns = data.input_columns(index)
    table = timed("Parquet read", lambda: shard.read_row_group(0, columns=columns))
    table = table.slice(0, len(index))
    rows = timed("row arrays", data._row_arrays, table)
    n = table.num_rows
    times = {k: [v[0] / n] for k, v in times.items()}  # per frame
    for i in range(n):
        image = timed("JPEG decode (camera)", codecs.decode_image, rows["image"][i])
        timed("PNG decode (LiDAR)", codecs.decode_lidar_bev, rows["lidar_bev"][i])
        timed(
            f"PNG decode + downsample (BEV, R={R})",
            lambda b: decode.downsample_bev(codecs.decode_bev_semantic(b), R),
            rows["bev_semantic"][i],
        )
        chw = timed(
            "HWC -> CHW copies", lambda x: np.ascontiguousarray(x.transpose(2, 0, 1)), image
        )
        a, b = rows["box_start"][i], rows["box_start"][i + 1]
        boxes = {k: v[a:b] for k, v in rows["boxes"].items()}
        timed("density targets", lambda x: render_density(visible_boxes(x, 8), R), boxes)
        p = train_cfg.zoom_out_probability
        zoomed = timed("zoom-out (one zoomed frame)", zoom_out, chw, 0.8)
        assert zoomed.shape == chw.shape
        times.setdefault(f"zoom-out x {p} (the share zoomed)", []).append(
            p * times["zoom-out (one zoomed frame)"][-1]
        )
    samples = [timed("whole sample (_sample)", data._sample, rows, i, R) for i in range(n)]
    print(f"\n5a. loader, CPU ms per frame (median of {n} frames of {index.path.iloc[0]}):")
    for name, values in times.items():
        if name != "zoom-out (one zoomed frame)":
            print(f"   {name:40s} {np.median(values):7.2f}")
    try:
        from training import cache
    except ImportError:
        cache = None
    if cache is not None:
        with tempfile.TemporaryDirectory() as tmp:
            inputs = cache.Inputs(R)
            entries = cache.prepare([index.path.iloc[0]], inputs, tmp, 1 << 40, log=lambda m: None)
            arrays = data.open_entry(next(iter(entries.values())).dir)
            per = _median_ms(
                lambda: [np.array(arrays[k][7]) for k in cache.ARRAYS], 50, clock=time.process_time
            )
            print(f"   {'decoded-frame cache read (instead of decoding)':40s} {per:7.2f}")
    batches = [samples[j : j + batch] for j in range(0, n - batch + 1, batch)]
    collated = [default_collate(b) for b in batches]
    cpu = torch.device("cpu")
    per_batch = {
        "collate": _median_ms(
            lambda: [default_collate(b) for b in batches], 5, clock=time.process_time
        )
        / len(batches),
        "to_device (channels_last)": _median_ms(
            lambda: [fit.to_device(b, cpu) for b in collated], 5, clock=time.process_time
        )
        / len(batches),
    }
    for name, ms in per_batch.items():
        print(f"   {name + f' (per batch of {batch})':40s} {ms:7.2f}")


def _model_parts(model: IIDSU) -> dict[str, torch.nn.Module]:
    """The model's parts in forward order (those this config has)."""
    parts = {
        "image stem": model.image_encoder.stem,
        "LiDAR stem": model.lidar_encoder.stem,
        "pixel lamp maps": getattr(model, "pixel_lamp", None),
    }
    for k in range(len(model.fusion)):
        parts[f"image stage {k + 1}"] = model.image_encoder.stages[k]
        if k == 0:
            parts["lamp maps"] = getattr(model, "lamp", None)
        parts[f"LiDAR stage {k + 1}"] = model.lidar_encoder.stages[k]
        parts[f"fusion {k + 1}"] = model.fusion[k]
    parts["to F_DSU (1x1 conv)"] = model.to_dsu
    for name in model.heads:
        parts[f"ECA {name}"] = model.eca[name]
        parts[f"head {name}"] = model.heads[name]
    parts["camera-only traffic head"] = getattr(model, "camera_traffic", None)
    return {k: v for k, v in parts.items() if v is not None}


def profile_model(batch: dict, threads: int, reps: int, clock) -> dict[str, tuple[float, float]]:
    """Section 5b: (forward ms, backward ms) of each part alone, of the loss, clipping and
    AdamW, and of a whole step, at `threads` intra-op threads, timed by `clock`."""
    torch.set_num_threads(threads)
    median_ms = lambda f, reps: _median_ms(f, reps, clock=clock)  # noqa: E731
    model_cfg, train_cfg = PRESETS["tiny"]
    torch.manual_seed(0)
    model = IIDSU(model_cfg).to(memory_format=torch.channels_last)
    optimizer = fit.make_optimizer(model, train_cfg)
    parts = _model_parts(model)
    captured: dict[str, list] = {}

    def grab(name):
        def hook(module, args):
            captured.setdefault(name, []).append(
                [
                    a.detach().clone().requires_grad_(a.requires_grad)
                    if isinstance(a, torch.Tensor)
                    else a
                    for a in args
                ]
            )

        return hook

    hooks = [m.register_forward_pre_hook(grab(k)) for k, m in parts.items()]
    model(*(batch[k] for k in INPUTS))
    for h in hooks:
        h.remove()
    out: dict[str, tuple[float, float]] = {}
    for name, module in parts.items():
        fwd = bwd = 0.0
        for args in captured.get(name, []):  # a part may run more than once per step

            def forward(module=module, args=args):
                with torch.no_grad():
                    module(*args)

            def forward_backward(module=module, args=args):
                y = module(*args)
                ys = [t for t in (y if isinstance(y, tuple) else (y,)) if t.requires_grad]
                torch.autograd.backward(ys, [torch.ones_like(t) for t in ys])

            f = median_ms(forward, reps)
            fwd += f
            bwd += median_ms(forward_backward, reps) - f
        out[name] = (fwd, bwd)
    outputs = {
        k: v.detach().requires_grad_() for k, v in model(*(batch[k] for k in INPUTS)).items()
    }

    def loss_forward():
        with torch.no_grad():
            compute_losses(outputs, batch, train_cfg)

    def loss_backward():
        compute_losses(outputs, batch, train_cfg)["total"].backward()

    f = median_ms(loss_forward, reps)
    out["losses"] = (f, median_ms(loss_backward, reps) - f)
    compute_losses(model(*(batch[k] for k in INPUTS)), batch, train_cfg)["total"].backward()
    clip = lambda: torch.nn.utils.clip_grad_norm_(model.parameters(), train_cfg.grad_clip)  # noqa: E731
    out["clip_grad_norm_"] = (median_ms(clip, reps), 0.0)
    out["AdamW step"] = (median_ms(optimizer.step, reps), 0.0)
    out["zero_grad"] = (median_ms(lambda: optimizer.zero_grad(set_to_none=True), reps), 0.0)

    def step():
        outputs = model(*(batch[k] for k in INPUTS))
        loss = compute_losses(outputs, batch, train_cfg)["total"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), train_cfg.grad_clip)
        optimizer.step()

    def forward_only():
        with torch.no_grad():
            model(*(batch[k] for k in INPUTS))

    out["whole model forward (no_grad)"] = (median_ms(forward_only, reps), 0.0)
    out["WHOLE STEP"] = (median_ms(step, reps), 0.0)
    return out


def profile(root: Path, reps: int) -> None:
    profile_loader(root)
    model_cfg, train_cfg = PRESETS["tiny"]
    b = train_cfg.batch_size
    index = data.scan(root)
    batch = batch_of(root, model_cfg.output_px, b, torch.device("cpu"))
    assert len(index) >= b
    # 1 thread in CPU time (the work, robust to other load), 2 threads in wall time
    runs = {"cpu@1": (1, time.process_time), "wall@2": (2, time.perf_counter)}
    results = {k: profile_model(batch, t, reps, clock) for k, (t, clock) in runs.items()}
    head = "".join(f"  fwd {k} bwd" for k in runs)
    print(f"\n5b. tiny model, batch {b}, ms (median of {reps}; parts measured alone){head}:")
    for name in results["cpu@1"]:
        cells = "".join(f" {results[k][name][0]:7.1f} {results[k][name][1]:7.1f}" for k in runs)
        print(f"   {name:32s}{cells}")
    for k in runs:
        parts = [v for n, v in results[k].items() if not n.isupper() and "whole" not in n]
        step = results[k]["WHOLE STEP"][0]
        print(
            f"   {k}: parts sum to {sum(f + g for f, g in parts):.0f} ms; a whole step "
            f"{step:.0f} ms = {b / step * 1e3:.1f} samples/s (no loader)"
        )
    torch.set_num_threads(os.cpu_count())


def _subset(shards: Path, episodes: int, where: Path) -> Path:
    """A directory of symlinks to `episodes` shard files of `shards`, one town after another."""
    files = [Path(p) for p in sorted(data.scan(shards).path.unique())]
    by_town: dict[str, list[Path]] = {}
    for f in files:
        by_town.setdefault(f.parent.name, []).append(f)
    picked, k = [], 0
    while len(picked) < min(episodes, len(files)):
        for town in sorted(by_town):
            if k < len(by_town[town]) and len(picked) < episodes:
                picked.append(by_town[town][k])
        k += 1
    where.mkdir(parents=True)
    for f in picked:
        (where / f.parent.name).mkdir(exist_ok=True)
        (where / f.parent.name / f.name).symlink_to(f.resolve())
    return where


def _tree(ref: str, tmp: Path) -> tuple[Path, str]:
    """The code of git ref `ref` (`.`: this working tree) and its name with the commit."""
    if ref == ".":
        return ROOT, "this tree"
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", ref], capture_output=True, text=True
    ).stdout.strip()
    where = tmp / f"tree-{commit}"
    if not where.exists():
        where.mkdir()
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", ref], capture_output=True, check=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    return where, f"{ref} ({commit})"


def fit_compare(shards: Path, episodes: int, variants: list[str], repeats: int, tmp: Path) -> None:
    """Section 6 (see the module docstring)."""
    subset = _subset(shards, episodes, tmp / "subset")
    index = data.scan(subset)
    runs = []
    for v in variants:
        ref, _, extra = v.partition(":")
        tree, name = _tree(ref, tmp)
        tokens = shlex.split(extra)
        env = dict(t.split("=", 1) for t in tokens if "=" in t and not t.startswith("-"))
        flags = [t for t in tokens if t.split("=", 1)[0] not in env]
        if ref == ".":
            flags = ["--cache-dir", str(tmp / "cache"), *flags]
        runs.append({"name": f"{name} {extra}".strip(), "tree": tree, "flags": flags, "env": env})
    print(
        f"\n6. train fit --config tiny --epochs 1 on {len(index)} frames ({episodes} episodes of "
        f"{shards}), {repeats} round(s):",
        flush=True,
    )
    results: dict[int, list[dict]] = {i: [] for i in range(len(runs))}
    for r in range(repeats):
        order = range(len(runs)) if r % 2 == 0 else reversed(range(len(runs)))
        for i in order:
            run = runs[i]
            out = tmp / f"run{i}-{r}"
            command = [sys.executable, "-m", "training.cli", "fit", "--shards", str(subset)]
            command += ["--config", "tiny", "--epochs", "1", "--device", "cpu", "--out", str(out)]
            env = {**os.environ, "PYTHONPATH": str(run["tree"]), **run["env"]}
            t0, cpu0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
            done = subprocess.run(
                [*command, *run["flags"]], cwd=run["tree"], env=env, capture_output=True, text=True
            )
            wall = time.perf_counter() - t0
            cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # its DataLoader workers too
            cpu = cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime
            if done.returncode:
                print(f"   {run['name']}: failed\n{done.stderr[-2000:]}")
                return
            (metrics,) = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
            steps = [json.loads(x) for x in (out / "steps.jsonl").read_text().splitlines()]
            results[i].append(
                {
                    "wall": wall,
                    "cpu": cpu,
                    "rate": metrics["samples_per_s"],
                    "frames": metrics["samples_per_s"] * metrics["time_s"],
                    "losses": [s["train"]["total"] for s in steps],
                }
            )
            print(
                f"   round {r + 1} {run['name']}: {metrics['samples_per_s']:.1f} samples/s "
                f"in the loop, {wall:.0f} s in all, {cpu:.0f} CPU s; load {os.getloadavg()[0]:.1f}",
                flush=True,
            )
    base_rate = np.median([x["rate"] for x in results[0]])
    base_wall = np.median([x["wall"] for x in results[0]])
    reference = np.array(results[0][0]["losses"])
    base_cpu = np.median([x["cpu"] for x in results[0]])
    print(
        "   variant: loop samples/s (median; ratio), whole command s (median, first run; ratio "
        "of medians), its CPU s (median; ratio), logged losses vs the first variant's (first "
        "log, largest relative difference)"
    )
    for i, run in enumerate(runs):
        rate = np.median([x["rate"] for x in results[i]])
        wall = np.median([x["wall"] for x in results[i]])
        cpu = np.median([x["cpu"] for x in results[i]])
        losses = np.array(results[i][0]["losses"])
        diff = np.abs(losses - reference) / np.abs(reference)
        print(
            f"   {run['name']:40s} {rate:6.1f} ({rate / base_rate:4.2f}x)  {wall:5.0f} s, first "
            f"{results[i][0]['wall']:4.0f} s ({base_wall / wall:4.2f}x)  {cpu:5.0f} CPU s "
            f"({base_cpu / cpu:4.2f}x)  losses {diff[0]:.1e}, max {diff.max():.1e} over "
            f"{len(diff)} logs"
        )


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
    parser.add_argument("--profile", type=Path, metavar="DIR", help="section 5 on these shards")
    parser.add_argument("--profile-reps", type=int, default=10, help="timings per figure (10)")
    parser.add_argument("--fit-shards", type=Path, metavar="DIR", help="section 6 on these")
    parser.add_argument("--fit-episodes", type=int, default=8, help="episodes for section 6")
    parser.add_argument("--repeats", type=int, default=2, help="rounds of section 6")
    parser.add_argument("--baseline", default="main", help="git ref section 6 compares with")
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="REF[:ARGS]",
        help="another section-6 variant, e.g. '.:--cache-gb 0' or '.:OMP_NUM_THREADS=1'",
    )
    parser.add_argument("--all", action="store_true", help="sections 1-4 too")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    if args.profile:
        profile(args.profile, args.profile_reps)
    if args.fit_shards:
        with tempfile.TemporaryDirectory() as tmp:
            variants = [args.baseline, ".", *args.variant]
            fit_compare(args.fit_shards, args.fit_episodes, variants, args.repeats, Path(tmp))
    if (args.profile or args.fit_shards) and not args.all:
        return
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
