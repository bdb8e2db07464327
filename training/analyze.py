"""`train analyze`: how close each auxiliary head's channel attention is to planning's (Table II).

Each head re-weights the channels of F_DSU with its own ECA module (training/model.py). For a
frame, head h's weights are a vector w_h in (0, 1)^C; we report cos(w_h, w_planning), averaged
over frames spread evenly over the shard directory (the weights depend on the frame, through
ECA's global pooling).

    train analyze --ckpt runs/demo/last.pt                 # frames of the fit's --shards
    train analyze --ckpt runs/demo/last.pt --shards data_test/ --frames 1000
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from training import data
from training.checkpoint import load_checkpoint, model_from_checkpoint
from training.errors import UserError
from training.fit import autocast, choose_device, to_device

LABELS = {"detection": "det&pred", "bev": "BEV", "traffic": "traffic", "weather": "weather"}


@torch.no_grad()
def eca_similarity(model, loader, device: torch.device) -> dict[str, float]:
    """Mean over frames of cos(ECA weights of head h, ECA weights of planning), per aux head."""
    aux = [h for h in model.cfg.heads if h != "planning"]
    sums, n = dict.fromkeys(aux, 0.0), 0
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device):
            f = model.encode(batch["image"], batch["lidar"], batch["speed"])
        plan = model.eca["planning"].weights(f.float())  # (B, C)
        for h in aux:
            sims = F.cosine_similarity(model.eca[h].weights(f.float()), plan, dim=1)
            sums[h] += sims.sum().item()
        n += len(f)
    return {h: s / n for h, s in sums.items()}


def run(args) -> int:
    state = load_checkpoint(args.ckpt)
    shards = args.shards or state.get("train_config", {}).get("shards")
    if not shards:
        raise UserError("--shards: the checkpoint does not name its data; give a directory")
    device = choose_device(args.device)
    model = model_from_checkpoint(state, device)
    if len(model.cfg.heads) == 1:
        raise UserError(f"{args.ckpt}: the model has no auxiliary head to compare")
    index = data.scan(shards)
    picks = np.unique(np.linspace(0, len(index) - 1, min(args.frames, len(index))).astype(int))
    stream = data.FrameStream(index.iloc[picks], model.cfg.output_px)
    sims = eca_similarity(model, data.make_loader(stream, args.batch_size, 0), device)
    print(f"cosine similarity of ECA channel weights, mean over {len(picks)} frames of {shards}")
    for h, s in sims.items():
        print(f"  plan x {LABELS[h]:<10}{s:.4f}")
    out = Path(args.out) if args.out else Path(args.ckpt).with_suffix(".analyze.json")
    result = {"checkpoint": str(args.ckpt), "shards": str(shards), "frames": len(picks)}
    out.write_text(json.dumps({**result, "cosine_similarity": sims}, indent=2) + "\n")
    print(f"wrote {out}")
    return 0
