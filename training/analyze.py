"""`train analyze`: how close each auxiliary head's channel attention is to planning's (Table II).

Each head re-weights the channels of F_DSU with its own ECA module (training/model.py): for a
frame, head h's weights are a vector w_h = sigmoid(conv1d_h(pool(F_DSU))) in (0, 1)^C. The
paper (Sec. IV-C, Table II) reports "the cosine similarity of each auxiliary task's channel
weights and the planning head's channel weights", without saying how it was averaged or
normalised. Three forms, each averaged over frames spread evenly over the shard directory:

- raw: cos(w_h, w_planning), the literal reading. All weights are positive, so two unrelated
  weight vectors already score high (for i.i.d. uniform weights, E cos = 0.75): a raw figure
  near 0.7 means nothing by itself.
- centred: the cosine of the weights minus their mean over channels, i.e. Pearson's correlation
  across channels. Unrelated weights score 0 and opposite ones -1, as the paper's 0.22-0.65
  suggest theirs did.
- kernel: the cosine of the two heads' learnt ECA kernels (k = 5 numbers each; frame-independent).

The same figures for an untrained model of the same config are printed beside them as the
reference line: built with the fit's seed, it is the run's own starting point (`train fit`
seeds torch with it before building the model), so the difference is what training changed.
Measured on a 6-epoch tiny run: plan x BEV's centred cosine was 0.87 before training and 0.86
after, i.e. ECA's five kernel weights per head had barely moved from their initialisation.

    train analyze --ckpt runs/demo/last.pt                 # frames of the fit's --shards
    train analyze --ckpt runs/demo/last.pt --shards data_test/ --frames 1000
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from schemas import outputs
from training import data
from training.checkpoint import check_sensors, load_checkpoint, model_from_checkpoint
from training.device import autocast, choose_device, to_device
from training.errors import UserError
from training.model import IIDSU

LABELS = {"detection": "det&pred", "bev": "BEV", "traffic": "traffic", "weather": "weather"}
FORMS = ("raw", "centred", "kernel")


@torch.no_grad()
def eca_similarity(
    model, loader, device: torch.device, per_frame: dict | None = None
) -> dict[str, dict[str, float]]:
    """Per auxiliary head, each of FORMS (module docstring) against the planning head; the
    per-frame raw and centred values are appended to `per_frame[head][form]` if given (the
    report's bootstrap interval over frames)."""
    aux = [h for h in model.cfg.heads if h != "planning"]
    sums, n = {h: {"raw": 0.0, "centred": 0.0} for h in aux}, 0
    if per_frame is not None:
        for h in aux:
            per_frame.setdefault(h, {"raw": [], "centred": []})
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device):
            f = model.encode(batch["image"], batch["lidar"], batch["speed"])
        plan = model.eca["planning"].weights(f.float())  # (B, C)
        for h in aux:
            w = model.eca[h].weights(f.float())
            raw = F.cosine_similarity(w, plan, dim=1)
            sums[h]["raw"] += raw.sum().item()
            centred = F.cosine_similarity(
                w - w.mean(1, keepdim=True), plan - plan.mean(1, keepdim=True), dim=1
            )
            sums[h]["centred"] += centred.sum().item()
            if per_frame is not None:
                per_frame[h]["raw"] += [round(v, 6) for v in raw.tolist()]
                per_frame[h]["centred"] += [round(v, 6) for v in centred.tolist()]
        n += len(f)
    kernel = model.eca["planning"].conv.weight.flatten()
    out = {}
    for h in aux:
        k = F.cosine_similarity(model.eca[h].conv.weight.flatten(), kernel, dim=0).item()
        out[h] = {"raw": sums[h]["raw"] / n, "centred": sums[h]["centred"] / n, "kernel": k}
    return out


def run(args) -> int:
    out = Path(args.out) if args.out else Path(args.ckpt).with_suffix(".analyze.json")
    outputs.check_file(out, "--out", suffixes=(".json",))  # before the computing
    state = load_checkpoint(args.ckpt)
    shards = args.shards or state.get("train_config", {}).get("shards")
    if not shards:
        raise UserError("--shards: the checkpoint does not name its data; give a directory")
    device = choose_device(args.device)
    model = model_from_checkpoint(state, device)
    if len(model.cfg.heads) == 1:
        raise UserError(f"{args.ckpt}: the model has no auxiliary head to compare")
    index = data.scan(shards)
    check_sensors(state, data.sensor_config(index), shards, args.ckpt)
    picks = np.unique(np.linspace(0, len(index) - 1, min(args.frames, len(index))).astype(int))

    def measure(m, per_frame=None) -> dict:
        stream = data.FrameStream(
            index.iloc[picks], m.cfg.output_px, single_frame_lidar=m.cfg.single_frame_lidar
        )
        loader = data.make_loader(stream, args.batch_size, 0)
        return eca_similarity(m, loader, device, per_frame)

    frames: dict = {}
    trained = measure(model, frames)
    torch.manual_seed(state.get("train_config", {}).get("seed", 0))  # as train fit builds it
    untrained = measure(IIDSU(model.cfg).to(device).eval())
    print(f"ECA channel weights vs planning's, mean over {len(picks)} frames of {shards}")
    print(
        f"  {'':<18}"
        + "".join(f"{f:>9}" for f in FORMS)
        + "   | untrained:"
        + "".join(f"{f:>9}" for f in FORMS)
    )
    for h in trained:
        row = "".join(f"{trained[h][f]:9.4f}" for f in FORMS)
        ref = "".join(f"{untrained[h][f]:9.4f}" for f in FORMS)
        print(f"  plan x {LABELS[h]:<10}{row}   |           {ref}")
    print("  raw: cosine of sigmoid weights (unrelated ~0.75); centred: across-channel")
    print("  correlation (unrelated 0); kernel: cosine of the ECA conv kernels")
    result = {"checkpoint": str(args.ckpt), "shards": str(shards), "frames": len(picks)}
    result["cosine_similarity"] = {h: v["raw"] for h, v in trained.items()}
    result["trained"], result["untrained"] = trained, untrained
    result["trained_per_frame"] = frames  # raw and centred per frame, in the frames' order
    outputs.write_json(out, result, indent=2)
    print(f"wrote {out}")
    return 0
