"""Is a head's miss in the features or in the training? Weather accuracy per town, and linear probes.

    python bench/probe.py --ckpt runs/exp/runs/full-s0/last.pt --shards runs/exp/data
    python bench/probe.py --ckpt CKPT --shards DIR --held-out arterial --frames-per-town 160

For a sample of frames of every town it prints the checkpoint's weather-head accuracy per town,
then fits three linear probes (softmax regression, full batch, on the seen towns' frames) and
scores them on the seen and the held-out town:
- `fdsu`: the pooled scene feature F_DSU (what the weather head reads, before its ECA);
- `image`: the pooled output of the camera encoder's last stage, run without the fusion layers;
- `colour`: 15 statistics of the raw image (mean RGB of four 64-row bands, per-channel std).

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

from training import data  # noqa: E402
from training.checkpoint import load_checkpoint, model_from_checkpoint  # noqa: E402
from training.errors import UserError  # noqa: E402


def features(model, samples: list[dict], batch: int = 16) -> tuple[dict, np.ndarray]:
    """Per frame: the three probe inputs and the weather head's predicted class."""
    feats = {"fdsu": [], "image": [], "colour": []}
    preds = []
    with torch.no_grad():
        for k in range(0, len(samples), batch):
            b = samples[k : k + batch]
            img = torch.from_numpy(np.stack([s["image"] for s in b]))
            lid = torch.from_numpy(np.stack([s["lidar"] for s in b]))
            speed = torch.tensor([s["speed"] for s in b])
            f = model.encode(img, lid, speed)
            if "weather" in model.heads:  # the weather head as IIDSU.forward applies it
                preds.append(model.heads["weather"](model.eca["weather"](f)).argmax(1).numpy())
            feats["fdsu"].append(f.mean((2, 3)).numpy())
            x = model.image_encoder.stem((img.float() / 255 - model.mean) / model.std)
            for stage in model.image_encoder.stages:
                x = stage(x)
            feats["image"].append(x.mean((2, 3)).numpy())
            rgb = img.float() / 255
            bands = [rgb[:, :, r : r + 64].mean((2, 3)) for r in range(0, 256, 64)]
            feats["colour"].append(torch.cat(bands + [rgb.std((2, 3))], 1).numpy())
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--shards", required=True)
    ap.add_argument("--held-out", default=None, help="the town to score the probes on "
                    "(default: the checkpoint's validation town, if one town)")  # fmt: skip
    ap.add_argument("--frames-per-town", type=int, default=160)
    ap.add_argument("--seed", type=int, default=0)
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
    y = np.array([int(s["weather"]) for s in samples])
    feats, pred = features(model, samples)

    print(f"weather head accuracy per town ({args.ckpt}):")
    for town in sorted(set(towns)):
        m = towns == town
        acc = "n/a (no weather head)" if pred[0] < 0 else f"{np.mean(pred[m] == y[m]):.3f}"
        print(f"  {town:14s} {acc}  ({m.sum()} frames){'  held out' if town == held else ''}")
    seen, out = towns != held, towns == held
    print(f"linear probes, fitted on the seen towns, scored on seen / held-out {held}:")
    for name, x in feats.items():
        p = probe(x, y, seen)
        print(f"  {name:7s} ({x.shape[1]:4d}-d): {np.mean(p[seen] == y[seen]):.3f} / "
              f"{np.mean(p[out] == y[out]):.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
