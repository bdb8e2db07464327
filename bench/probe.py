"""Is a head's miss in the features or in the training? A head's score per town, and linear probes.

    python bench/probe.py --ckpt runs/exp/runs/full-s0/last.pt --shards runs/exp/data
    python bench/probe.py --ckpt CKPT --shards DIR --held-out arterial --frames-per-town 160
    python bench/probe.py --ckpt CKPT --shards DIR --head red     # the red-light output
    python bench/probe.py --ckpt CKPT --shards DIR --head red --blank image   # without the camera

For a sample of frames of every town it prints the checkpoint's score per town (weather:
accuracy; red: the traffic head's red-light F1), then fits three linear probes (softmax
regression, full batch, on the seen towns' frames) and scores them on the seen and the held-out
town:
- `fdsu`: the pooled scene feature F_DSU (what the heads read, before their ECA);
- `image`: the pooled output of the camera encoder's last stage, run without the fusion layers;
- `colour`: 15 statistics of the raw image (mean RGB of four 64-row bands, per-channel std) and
  the 1st, 3rd and 10th largest redness (R - max(G, B)) of its pixels, where a lit red lamp of
  2-3 px shows.

`--blank image` (or `lidar`) scores the head with that input blanked. The tiny model of the 16k
check (runs/learn16k, before the camera-only traffic head) scored red-light F1 0.78 on
grid_small and 0.36 on the held-out arterial with a flat image, against 0.96 and 0.42 with the
real one: it read red lights from LiDAR context more than from the lamps.

A head that is as wrong on its own training towns as on the held-out one, while the probes are
right, is under-trained (issue 13: weather after 2 epochs). Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from training import data, evaluate  # noqa: E402
from training.checkpoint import load_checkpoint, model_from_checkpoint  # noqa: E402
from training.errors import UserError  # noqa: E402


def features(
    model, samples: list[dict], head: str, batch: int = 16, blank: str | None = None
) -> tuple[dict, np.ndarray]:
    """Per frame: the three probe inputs and the head's predicted class (weather: its index;
    red: 1 for a red light, p >= 0.5; -1 throughout without that head). With `blank` "image"
    the model sees a camera image of one flat colour (ImageNet's mean: zero after
    normalisation), with "lidar" an empty LiDAR BEV (no hits); the probes' inputs stay real."""
    feats = {"fdsu": [], "image": [], "colour": []}
    preds = []
    with torch.no_grad():
        for k in range(0, len(samples), batch):
            b = samples[k : k + batch]
            img = torch.from_numpy(np.stack([s["image"] for s in b]))
            lid = torch.from_numpy(np.stack([s["lidar"] for s in b]))
            speed = torch.tensor([s["speed"] for s in b])
            flat = (model.mean * 255).round().to(torch.uint8).expand_as(img)
            f = model.encode(
                flat if blank == "image" else img,
                torch.zeros_like(lid) if blank == "lidar" else lid,
                speed,
            )
            name = "weather" if head == "weather" else "traffic"
            if name in model.heads:  # the head as IIDSU.forward applies it
                out = model.heads[name](model.eca[name](f))
                p = out.argmax(1) if head == "weather" else (out[:, 0] >= 0).long()
                preds.append(p.numpy())
            feats["fdsu"].append(f.mean((2, 3)).numpy())
            x = model.image_encoder.stem((img.float() / 255 - model.mean) / model.std)
            for stage in model.image_encoder.stages:
                x = stage(x)
            feats["image"].append(x.mean((2, 3)).numpy())
            rgb = img.float() / 255
            bands = [rgb[:, :, r : r + 64].mean((2, 3)) for r in range(0, 256, 64)]
            redness = (rgb[:, 0] - rgb[:, 1:].amax(1)).flatten(1).topk(10, 1).values
            lamps = redness[:, [0, 2, 9]]
            feats["colour"].append(torch.cat(bands + [rgb.std((2, 3)), lamps], 1).numpy())
    pred = np.concatenate(preds) if preds else np.full(len(samples), -1)
    return {k: np.concatenate(v) for k, v in feats.items()}, pred


def probe(x: np.ndarray, y: np.ndarray, train: np.ndarray, steps: int = 500) -> np.ndarray:
    """Predicted classes of a softmax regression fitted on the rows `train` (standardised)."""
    x = (x - x[train].mean(0)) / (x[train].std(0) + 1e-6)
    xt, yt = torch.tensor(x, dtype=torch.float32), torch.tensor(y)
    torch.manual_seed(0)
    lin = torch.nn.Linear(x.shape[1], int(y.max()) + 1)
    opt = torch.optim.Adam(lin.parameters(), 1e-2, weight_decay=1e-3)
    for _ in range(steps):
        opt.zero_grad()
        F.cross_entropy(lin(xt[train]), yt[train]).backward()
        opt.step()
    with torch.no_grad():
        return lin(xt).argmax(1).numpy()


def f1(pred: np.ndarray, y: np.ndarray) -> float:
    """F1 of the positive class (1), as `train eval` scores it; 0 without any positive."""
    return evaluate.binary_scores(pred.astype(np.float32), y)["f1"] or 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--shards", required=True)
    ap.add_argument("--held-out", default=None, help="the town to score the probes on "
                    "(default: the checkpoint's validation town, if one town)")  # fmt: skip
    ap.add_argument("--frames-per-town", type=int, default=160)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head", choices=("weather", "red"), default="weather")
    ap.add_argument(
        "--blank",
        choices=("image", "lidar"),
        help="score the head with this input blanked (a flat image, an empty BEV): how much "
        "of what it finds comes from the other one",
    )
    args = ap.parse_args()

    try:
        state = load_checkpoint(args.ckpt)
        index = data.scan(args.shards)
    except UserError as e:
        sys.exit(f"error: {e}")
    model = model_from_checkpoint(state)
    held = args.held_out
    if held is None:
        towns = set(index[index.episode_id.isin(state.get("val_episodes", []))].town)
        held = towns.pop() if len(towns) == 1 else None
    if held is None or held not in set(index.town):
        sys.exit(f"error: give --held-out TOWN (one of {', '.join(sorted(set(index.town)))})")
    rng = np.random.default_rng(args.seed)
    picks = []
    for town in sorted(index.town.unique()):
        rows = np.flatnonzero(index.town.to_numpy() == town)
        picks.append(rng.choice(rows, min(len(rows), args.frames_per_town), replace=False))
    sample = index.iloc[np.sort(np.concatenate(picks))]
    samples = data.read_frames(sample, model.cfg.output_px, model.cfg.single_frame_lidar)
    towns = sample.town.to_numpy()
    if args.head == "weather":
        y = np.array([int(s["weather"]) for s in samples])
        score, what = (lambda p, t: np.mean(p == t)), "weather-head accuracy"
    else:
        y = np.array([int(s["traffic"][0]) for s in samples])
        score, what = f1, "red-light F1"
    feats, pred = features(model, samples, args.head, blank=args.blank)

    blanked = f", {args.blank} blanked" if args.blank else ""
    print(f"{what} per town ({args.ckpt}{blanked}):")
    for town in sorted(set(towns)):
        m = towns == town
        acc = "n/a (no such head)" if pred[0] < 0 else f"{score(pred[m], y[m]):.3f}"
        extra = f", {int(y[m].sum())} red" if args.head == "red" else ""
        print(
            f"  {town:14s} {acc}  ({m.sum()} frames{extra}){'  held out' if town == held else ''}"
        )
    seen, out = towns != held, towns == held
    print(f"linear probes ({what}), fitted on the seen towns, scored on seen / held-out {held}:")
    for name, x in feats.items():
        p = probe(x, y, seen)
        print(f"  {name:7s} ({x.shape[1]:4d}-d): {score(p[seen], y[seen]):.3f} / "
              f"{score(p[out], y[out]):.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
