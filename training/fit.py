"""Train II-DSU: one loop, the same on a laptop CPU and on a GPU box, alone or under DDP.

    train fit --shards data/ --config tiny --epochs 1 --out runs/demo           # CPU, minutes
    train fit --shards data/ --out runs/paper                                   # one GPU
    torchrun --standalone --nproc_per_node 8 -m training.cli fit --shards data/ --out runs/paper
    train fit --shards data/ --out runs/paper --resume                          # continue

Per epoch the loop streams the training episodes (training/data.py), steps AdamW with a
warm-up + cosine learning rate, measures the loss terms and `train eval`'s metrics on the
held-out episodes, appends a line to OUT/metrics.jsonl and writes OUT/last.pt atomically.
Every LOG_EVERY steps it appends the mean of every loss term over those steps, the learning
rate and samples/s to OUT/steps.jsonl. With TensorBoard installed (the `tensorboard` extra)
the same scalars go to OUT/tensorboard/; `train curves --run OUT` draws them to a PNG without
it. A resumed run takes weights, optimizer moments, step, epoch and RNG states from last.pt,
and the data order is a function of (seed, epoch), so it continues exactly (the logs are cut
back to the checkpoint's step first).

With `ema_decay` > 0 (ours) the loop also keeps an exponential moving average of the weights
and buffers (torch.optim.swa_utils.AveragedModel), updated after every optimizer step; the
per-epoch validation scores the average, and last.pt's "model" holds it (what `train eval`,
`drive eval` and every other reader load), its "train_model" the weights AdamW steps.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm import tqdm

from training import cache, data
from training.checkpoint import load_checkpoint, save_checkpoint
from training.config import ModelConfig, TrainConfig
from training.device import Process, autocast, cpu_threads, start_process, to_device, tune_allocator
from training.errors import UserError
from training.evaluate import evaluate, headline
from training.losses import compute_losses, loss_terms
from training.model import IIDSU, INPUTS

CHECKPOINT = "last.pt"
METRICS = "metrics.jsonl"  # one line per epoch
STEPS = "steps.jsonl"  # one line per LOG_EVERY optimizer steps
TENSORBOARD = "tensorboard"
LOG_EVERY = 10  # steps; each log reads the loss from the device (a GPU sync): not every step


def lr_at(step: int, total_steps: int, cfg: TrainConfig) -> float:
    """Learning rate of optimizer step `step` (0-based) of `total_steps`."""
    warmup = int(cfg.warmup_frac * total_steps)
    # 1) linear warm-up from lr / warmup to lr
    if step < warmup:
        return cfg.lr * (step + 1) / warmup
    # 2) cosine decay from lr to lr * min_lr_frac over the remaining steps
    progress = min(1.0, (step - warmup) / max(1, total_steps - warmup))
    min_lr = cfg.lr * cfg.min_lr_frac
    return min_lr + 0.5 * (1.0 + math.cos(math.pi * progress)) * (cfg.lr - min_lr)


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig) -> torch.optim.AdamW:
    """AdamW with weight decay on weight matrices and kernels only, not on norms and biases."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in params if p.ndim >= 2], "weight_decay": cfg.weight_decay},
        {"params": [p for p in params if p.ndim < 2], "weight_decay": 0.0},
    ]
    # fused: one kernel for all the parameters, on CPUs too (tiny config: 2.3 ms a step against
    # 8.4 for the default, docs/speed.md); the same update up to float rounding
    return torch.optim.AdamW(groups, lr=cfg.lr, fused=params[0].device.type in ("cpu", "cuda"))


def _all_sum(values: dict[str, torch.Tensor], proc: Process) -> dict[str, float]:
    """Sum per-process tensors over the process group; the result as floats."""
    keys = sorted(values)
    stacked = torch.stack([values[k].double() for k in keys])
    if proc.world > 1:
        stacked = stacked.to(proc.device if proc.device.type == "cuda" else "cpu")
        dist.all_reduce(stacked)
    return dict(zip(keys, stacked.tolist()))


@torch.no_grad()
def estimate_loss(model: IIDSU, loader, cfg: TrainConfig, proc: Process) -> dict[str, float]:
    """Mean of every loss term over the frames of `loader` (all ranks' shares together).

    Runs the bare model, not the DDP wrapper: ranks hold different numbers of validation
    batches, and DDP's forward would wait for the others."""
    model.eval()
    sums: dict[str, torch.Tensor] = {}
    for batch in loader:
        batch = to_device(batch, proc.device)
        with autocast(proc.device):
            out = model(*(batch[k] for k in INPUTS))
        n = len(batch["speed"])
        for k, v in compute_losses(out, batch, cfg).items():
            sums[k] = sums.get(k, torch.zeros((), device=proc.device)) + v.detach() * n
        sums["n"] = sums.get("n", torch.zeros((), device=proc.device)) + n
    model.train()
    # Every rank joins the reduction with the same keys, also one that had no frames.
    zero = torch.zeros((), device=proc.device)
    sums = {
        k: sums.get(k, zero)
        for k in (*loss_terms(model.cfg.heads, model.cfg.has_camera_traffic), "n")
    }
    total = _all_sum(sums, proc)
    n = total.pop("n")
    return {k: v / n for k, v in total.items()} if n else {}


def _rng_state(device: torch.device) -> dict:
    state = {"torch": torch.get_rng_state()}
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def _set_rng_state(state: dict, device: torch.device) -> None:
    torch.set_rng_state(state["torch"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


def _tensorboard(out: Path, step: int):
    """A SummaryWriter when TensorBoard is installed, else None. `purge_step` drops events a
    crashed run logged after its checkpoint, so a resumed run's curves do not double back."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / TENSORBOARD), purge_step=step or None)


def _cut_log(path: Path, step: int) -> None:
    """Keep the lines of a JSON-lines log up to optimizer step `step` (what a resumed run
    redoes is logged again)."""
    if path.exists():
        lines = [ln for ln in path.read_text().splitlines() if json.loads(ln)["step"] <= step]
        path.write_text("".join(ln + "\n" for ln in lines))


def scalars(metrics: dict) -> dict[str, float]:
    """An epoch's metrics.jsonl line as flat TensorBoard tags: train/<term>, val/<term> (loss
    terms), val_metrics/<name> (`train eval`'s, see `evaluate.headline`), lr, samples_per_s."""
    flat = {f"{split}/{k}": v for split in ("train", "val") for k, v in metrics[split].items()}
    flat.update({f"val_metrics/{k}": v for k, v in metrics.get("val_metrics", {}).items()})
    flat.update(lr=metrics["lr"], samples_per_s=metrics["samples_per_s"])
    return {k: v for k, v in flat.items() if v is not None}


def _log_step(out: Path, writer, line: dict) -> None:
    """One steps.jsonl line, and its scalars to TensorBoard (tags step/train/<term>, step/lr,
    step/samples_per_s)."""
    with open(out / STEPS, "a") as f:
        f.write(json.dumps(line) + "\n")
    if writer is not None:
        for k, v in line["train"].items():
            writer.add_scalar(f"step/train/{k}", v, line["step"])
        writer.add_scalar("step/lr", line["lr"], line["step"])
        writer.add_scalar("step/samples_per_s", line["samples_per_s"], line["step"])


def _prepare_cache(index, model_cfg: ModelConfig, cfg: TrainConfig, proc: Process) -> dict:
    """The decoded-frame cache's entries for the shards of `index` (filled first where
    missing, training/cache.py); {} with `cache_gb` 0, or when the default directory cannot
    be written (a note says so; a --cache-dir that cannot be is a UserError)."""
    if cfg.cache_gb <= 0:
        return {}
    root = Path(cfg.cache_dir) if cfg.cache_dir else cache.default_root()
    try:
        return cache.prepare(
            sorted(index.path.unique()),
            cache.Inputs(model_cfg.output_px, model_cfg.single_frame_lidar),
            root,
            int(cfg.cache_gb * 1e9),
            processes=cpu_threads(),
            rank=proc.rank,
            world=proc.world,
            barrier=dist.barrier if proc.world > 1 else None,
            log=print if proc.master else lambda line: None,
        )
    except OSError as e:
        if cfg.cache_dir:
            raise UserError(f"--cache-dir {cfg.cache_dir}: {e.strerror or e}") from None
        if proc.master:
            print(f"train fit: no decoded-frame cache ({root}: {e.strerror or e})")
        return {}


def fit(model_cfg: ModelConfig, cfg: TrainConfig, resume: bool = False, device: str = "auto"):
    """Train for `cfg.epochs` epochs (from the last completed one with `resume`); returns the
    path of the checkpoint, OUT/last.pt."""
    proc = start_process(device)
    tune_allocator()
    torch.set_num_threads(cpu_threads(cfg.threads))
    out = Path(cfg.out)
    ckpt_path = out / CHECKPOINT
    state = load_checkpoint(ckpt_path) if resume else None
    try:
        return _fit(model_cfg, cfg, proc, out, state)
    finally:
        if proc.world > 1:
            dist.destroy_process_group()


def _fit(model_cfg: ModelConfig, cfg: TrainConfig, proc: Process, out: Path, state: dict | None):
    # Data: every rank scans and splits the same way (both are deterministic).
    index = data.scan(cfg.shards)
    sensors = data.sensor_config(index)
    is_val = data.split(index, cfg.val_fraction, cfg.val_towns, cfg.seed)
    cached = _prepare_cache(index, model_cfg, cfg, proc)
    stream = data.FrameStream(
        index[~is_val],
        model_cfg.output_px,
        shuffle=True,
        seed=cfg.seed,
        buffer_size=cfg.shuffle_buffer,
        open_units=cfg.open_row_groups,
        rank=proc.rank,
        world=proc.world,
        single_frame_lidar=model_cfg.single_frame_lidar,
        zoom_out=(cfg.zoom_out, cfg.zoom_out_probability) if cfg.zoom_out < 1 else None,
        cache=cached,
    )
    val_stream = data.FrameStream(
        index[is_val],
        model_cfg.output_px,
        rank=proc.rank,
        world=proc.world,
        single_frame_lidar=model_cfg.single_frame_lidar,
        cache=cached,
    )
    if stream.frames_per_rank() == 0:
        raise UserError(f"{cfg.shards}: no training frames for {proc.world} process(es)")
    loader = data.make_loader(stream, cfg.batch_size, cfg.num_workers)
    val_loader = data.make_loader(val_stream, cfg.batch_size, cfg.num_workers)
    # Every rank takes the same number of steps (DDP all-reduces in each one).
    steps_per_epoch = math.ceil(stream.frames_per_rank() / cfg.batch_size)
    total_steps = cfg.epochs * steps_per_epoch

    # Model and optimizer; the same initial weights on every rank (DDP also broadcasts them).
    torch.manual_seed(cfg.seed)
    model = IIDSU(model_cfg).to(proc.device, memory_format=torch.channels_last)
    optimizer = make_optimizer(model, cfg)
    first_epoch, step = 0, 0
    if state is not None:
        if state["epoch"] >= cfg.epochs:
            raise UserError(
                f"{out / CHECKPOINT} has finished {state['epoch']} of {cfg.epochs} epochs; "
                "give a larger --epochs to train on"
            )
        model.load_state_dict(state.get("train_model", state["model"]))
        optimizer.load_state_dict(state["optimizer"])
        first_epoch, step = state["epoch"], state["step"]
        rng = state["rng"]
        _set_rng_state(rng[proc.rank] if len(rng) == proc.world else rng[0], proc.device)
    else:
        if cfg.init:  # fine-tuning: the weights of another run, a fresh optimizer
            start = load_checkpoint(cfg.init)
            if ModelConfig.from_dict(start["model_config"]) != model_cfg:
                raise UserError(f"--init {cfg.init}: its model is not this --config's")
            model.load_state_dict(start["model"])
        torch.manual_seed(cfg.seed + proc.rank)  # stochastic depth differs between ranks
    raw_model = model
    ema = None  # the averaged weights; the weights evaluated and saved as "model"
    if cfg.ema_decay > 0:
        ema = AveragedModel(
            raw_model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay), use_buffers=True
        )
        if state is not None and "train_model" in state:
            ema.module.load_state_dict(state["model"])
            ema.n_averaged.fill_(state["step"])  # not 0: the next update averages, not copies
    if cfg.compile:
        model = torch.compile(model)
    if proc.world > 1:
        ids = [proc.device.index] if proc.device.type == "cuda" else None
        model = DistributedDataParallel(model, device_ids=ids)

    writer = None
    if proc.master:
        out.mkdir(parents=True, exist_ok=True)
        for log in (METRICS, STEPS):
            if state is None:  # a fresh run replaces an old one's logs
                (out / log).write_text("")
            else:
                _cut_log(out / log, step)
        writer = _tensorboard(out, step)
        print(
            f"train fit: {len(index)} frames, {int((~is_val).sum())} for training and "
            f"{int(is_val.sum())} held out ({index.episode_id[is_val].nunique()} of "
            f"{index.episode_id.nunique()} episodes); {steps_per_epoch} steps/epoch x "
            f"{proc.world} process(es); "
            f"{sum(p.numel() for p in raw_model.parameters()) / 1e6:.2f} M parameters; "
            f"{proc.device}; epochs {first_epoch + 1}..{cfg.epochs}; "
            f"{int(index.path.isin(cached).sum())} frames in the decoded-frame cache"
        )

    for epoch in range(first_epoch, cfg.epochs):
        stream.set_epoch(epoch)
        model.train()
        sums: dict[str, torch.Tensor] = {}
        window: dict[str, torch.Tensor] = {}  # sums over the steps since the last log line
        seen, t0 = 0, time.perf_counter()
        t_log, seen_log = t0, 0
        bar = tqdm(
            total=steps_per_epoch,
            desc=f"epoch {epoch + 1}/{cfg.epochs}",
            disable=not proc.master,
            dynamic_ncols=True,
        )
        for i, batch in zip(range(steps_per_epoch), loader):
            lr = lr_at(step, total_steps, cfg)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = to_device(batch, proc.device)
            with autocast(proc.device):
                outputs = model(*(batch[k] for k in INPUTS))
            terms = compute_losses(outputs, batch, cfg)
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            if ema is not None:
                ema.update_parameters(raw_model)
            step += 1
            n = len(batch["speed"])
            seen += n
            for k, v in terms.items():  # summed on the device: no sync per step
                sums[k] = sums.get(k, 0.0) + v.detach() * n
                window[k] = window.get(k, 0.0) + v.detach() * n
            bar.update()
            if step % LOG_EVERY == 0 or i == steps_per_epoch - 1:  # .item() syncs: not often
                now = time.perf_counter()
                rate = (seen - seen_log) * proc.world / (now - t_log)
                line = {
                    "step": step,
                    "epoch": round(epoch + (i + 1) / steps_per_epoch, 4),  # fractional
                    "lr": lr,
                    "samples_per_s": round(rate, 2),
                    "train": {k: v.item() / (seen - seen_log) for k, v in window.items()},
                }
                bar.set_postfix(loss=f"{line['train']['total']:.3f}", samples_s=f"{rate:.1f}")
                if proc.master:
                    _log_step(out, writer, line)
                window, t_log, seen_log = {}, now, seen
        bar.close()
        elapsed = time.perf_counter() - t0
        sums["n"] = torch.tensor(float(seen), device=proc.device)
        train = _all_sum(sums, proc)
        n_train = train.pop("n")
        scored = raw_model if ema is None else ema.module  # what validation and readers see
        metrics = {
            "epoch": epoch + 1,
            "step": step,
            "lr": lr,
            "time_s": round(elapsed, 3),
            "samples_per_s": round(n_train / elapsed, 2),
            "train": {k: v / n_train for k, v in train.items()},
            "val": estimate_loss(scored, val_loader, cfg, proc),
        }
        if cfg.val_metrics and len(val_stream.units):
            # every rank measures its share; the metrics are of all the held-out frames
            metrics["val_metrics"] = headline(evaluate(scored, val_loader, proc.device, proc))
        rngs = [None] * proc.world
        if proc.world > 1:
            dist.all_gather_object(rngs, _rng_state(proc.device))
        else:
            rngs = [_rng_state(proc.device)]
        if proc.master:
            checkpoint = {
                "model": scored.state_dict(),
                **({} if ema is None else {"train_model": raw_model.state_dict()}),
                "optimizer": optimizer.state_dict(),
                "model_config": model_cfg.to_dict(),
                "train_config": cfg.to_dict(),
                "epoch": epoch + 1,
                "step": step,
                "rng": rngs,
                "val_episodes": sorted(index.episode_id[is_val].unique()),
                "sensor_config": sensors,  # what `drive eval` checks the world against
                "metrics": metrics,
            }
            save_checkpoint(out / CHECKPOINT, checkpoint)
            with open(out / METRICS, "a") as f:
                f.write(json.dumps(metrics) + "\n")
            if writer is not None:
                for tag, v in scalars(metrics).items():  # per epoch, at its last step
                    writer.add_scalar(f"epoch/{tag}", v, step)
                writer.flush()
            val = metrics["val"].get("total")
            print(
                f"epoch {epoch + 1}: train loss {metrics['train']['total']:.4f}, val loss "
                + (f"{val:.4f}" if val is not None else "n/a (no validation episodes)")
                + f", {metrics['samples_per_s']:.1f} samples/s -> {out / CHECKPOINT}"
            )
    if writer is not None:
        writer.close()
    return out / CHECKPOINT
