"""`train eval`: the checkpoint's heads measured on a shard directory.

    train eval --ckpt runs/demo/last.pt --shards data_test/           # a held-out directory
    train eval --ckpt runs/demo/last.pt --shards data/ --split val    # the fit's val episodes

- planning: waypoint L1 (mean absolute coordinate error), ADE (mean Euclidean error over the
  four waypoints) and FDE (at +2 s), in metres; the same for a constant-velocity baseline
  (the ego keeps its speed straight ahead) on the same frames.
- detection: average precision of the density map's peaks (training/targets.py) against the
  centres of the agents the LiDAR sees (>= MIN_LIDAR_POINTS returns at t, the training targets'
  rule), matched greedily by score within 0.5, 1, 2 and 4 m (nuScenes' centre-distance
  thresholds), 101-point interpolated, per timestep (t, t+0.5 s, t+1.0 s), and their mean.
- BEV map: IoU per class and their mean, at the head's resolution R.
- traffic rules: accuracy and F1 of "red light" and "stop sign" (probability >= 0.5).
- weather: accuracy and the confusion matrix (rows: truth, columns: prediction).

Prints a table and writes the numbers as JSON (default: beside the checkpoint).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from schemas import BEV_CLASSES, WAYPOINT_TIMES_S, WEATHERS, outputs
from training import data
from training.checkpoint import check_sensors, load_checkpoint, model_from_checkpoint
from training.device import autocast, choose_device, to_device
from training.errors import UserError
from training.model import INPUTS
from training.targets import N_T, centres_to_objects, decode_centres, split_density

DISTANCES_M = (0.5, 1.0, 2.0, 4.0)
TIMESTEP_NAMES = ("t", "t+0.5s", "t+1.0s")


def average_precision(
    predictions: list[np.ndarray], truths: list[np.ndarray], max_distance_m: float
) -> float | None:
    """AP of scored centre predictions against true centres, over many frames.

    Args:
        predictions, truths: per frame, (N, >=3) arrays of (score, x m, y m, ...).
        max_distance_m: a prediction is a true positive if an unmatched true centre of its
            frame lies within this distance (highest scores match first).
    Returns:
        101-point interpolated AP in [0, 1], or None when there is no true centre at all.
    """
    n_true = sum(len(t) for t in truths)
    if n_true == 0:
        return None
    scores, hits = [], []
    for pred, true in zip(predictions, truths):
        taken = np.zeros(len(true), bool)
        for obj in pred[np.argsort(-pred[:, 0], kind="stable")]:
            hit = False
            if len(true):
                d = np.hypot(true[:, 1] - obj[1], true[:, 2] - obj[2])
                d[taken] = np.inf
                j = int(np.argmin(d))
                hit = bool(d[j] <= max_distance_m)
                taken[j] |= hit
            scores.append(obj[0])
            hits.append(hit)
    if not scores:
        return 0.0
    hits = np.array(hits)[np.argsort(-np.array(scores), kind="stable")]
    tp = np.cumsum(hits)
    recall = tp / n_true
    precision = tp / np.arange(1, len(hits) + 1)
    # Interpolated precision: the best precision at this recall or higher.
    best = np.maximum.accumulate(precision[::-1])[::-1]
    levels = np.linspace(0, 1, 101)
    at = np.searchsorted(recall, levels, side="left")
    return float(np.mean([best[i] if i < len(best) else 0.0 for i in at]))


def binary_scores(prob: np.ndarray, truth: np.ndarray) -> dict:
    """Accuracy and F1 of `prob >= 0.5` against 0/1 `truth`; F1 is None without any positive
    in truth or prediction."""
    pred, truth = prob >= 0.5, truth > 0.5
    tp = int((pred & truth).sum())
    denominator = int(pred.sum() + truth.sum())
    return {
        "accuracy": float((pred == truth).mean()) if len(truth) else None,
        "f1": 2 * tp / denominator if denominator else None,
        "positives": int(truth.sum()),
    }


@torch.no_grad()
def evaluate(model, loader, device: torch.device, proc=None) -> dict:
    """Every metric of the module docstring for the heads `model` has (in eval mode: BatchNorm
    uses its running statistics; the model's mode is restored after).

    Under DDP (`proc`: training.device.Process with world > 1) every rank must call it: each
    measures its own share of the loader's frames and the metrics are of all shares together
    (the raw errors, detections and counts are gathered, then scored once)."""
    was_training = model.training
    model.eval()
    try:
        raw = _collect(model, loader, device)
    finally:
        model.train(was_training)
    if proc is not None and proc.world > 1:
        import torch.distributed as dist

        parts = [None] * proc.world
        dist.all_gather_object(parts, raw)
        raw = {k: [x for part in parts for x in part[k]] for k in raw}
    return _score(raw, model.cfg.heads)


def headline(result: dict) -> dict[str, float | None]:
    """The figures of an `evaluate` result that `train fit` logs per epoch, flat: ade_m, fde_m,
    cv_ade_m, cv_fde_m, det_map (mean over timesteps), miou, iou_<class>, red_light_f1,
    stop_sign_f1, weather_accuracy."""
    p, cv = result["planning"], result["constant_velocity"]
    out = {
        "frames": result["frames"],
        "ade_m": p["ade_m"],
        "fde_m": p["fde_m"],
        "cv_ade_m": cv["ade_m"],
        "cv_fde_m": cv["fde_m"],
    }
    if "detection" in result:
        maps = [t["map"] for t in result["detection"].values() if t["map"] is not None]
        out["det_map"] = float(np.mean(maps)) if maps else None
    if "bev" in result:
        out["miou"] = result["bev"]["miou"]
        out.update({f"iou_{c}": v for c, v in result["bev"]["iou"].items()})
    if "traffic" in result:
        out.update({f"{k}_f1": v["f1"] for k, v in result["traffic"].items()})
    if "camera_traffic" in result:
        out["camera_red_light_f1"] = result["camera_traffic"]["red_light"]["f1"]
    if "weather" in result:
        out["weather_accuracy"] = result["weather"]["accuracy"]
    return out


def _collect(model, loader, device: torch.device) -> dict[str, list]:
    """What the metrics are computed from, per batch or frame, as lists of numpy arrays (lists
    of several ranks concatenate): waypoint and constant-velocity errors, m; per timestep t the
    decoded peaks and true centres per frame; the BEV confusion; traffic and weather outputs."""
    R = model.cfg.output_px
    times = torch.tensor(WAYPOINT_TIMES_S)
    raw: dict[str, list] = {k: [] for k in ("wp_err", "cv_err", "confusion")}
    raw.update({f"preds_{t}": [] for t in range(N_T)})
    raw.update({f"truths_{t}": [] for t in range(N_T)})
    keys = ("traffic_prob", "camera_traffic_prob", "traffic_true", "weather_pred", "weather_true")
    raw.update({k: [] for k in keys})
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device):
            out = model(*(batch[k] for k in INPUTS))
        gt_wp = batch["waypoints"].cpu()
        raw["wp_err"].append((out["planning"].float().cpu() - gt_wp).numpy())
        cv = torch.stack([batch["speed"].cpu()[:, None] * times, torch.zeros(len(gt_wp), 4)], 2)
        raw["cv_err"].append((cv - gt_wp).numpy())
        if "detection" in out:
            heat, reg = split_density(out["detection"].float())
            heat = heat.sigmoid()
            centres = [
                batch[k].cpu().numpy() for k in ("centre_index", "centre_reg", "centre_mask")
            ]
            for t in range(N_T):
                raw[f"preds_{t}"] += decode_centres(heat[:, t], reg[:, t], threshold=0.05)
                raw[f"truths_{t}"] += [
                    centres_to_objects(idx[t], r[t], m[t], R) for idx, r, m in zip(*centres)
                ]
        if "bev" in out:
            pred = out["bev"].argmax(1).flatten().cpu().numpy()
            true = batch["bev"].long().flatten().cpu().numpy()
            raw["confusion"].append(np.bincount(true * 3 + pred, minlength=9).reshape(3, 3))
        if "traffic" in out:
            raw["traffic_prob"].append(out["traffic"].float().sigmoid().cpu().numpy())
            raw["traffic_true"].append(batch["traffic"].cpu().numpy())
        if "camera_traffic" in out:  # ours: the camera encoder's own traffic-rule output
            raw["camera_traffic_prob"].append(out["camera_traffic"].float().sigmoid().cpu().numpy())
        if "weather" in out:
            raw["weather_pred"].append(out["weather"].argmax(1).cpu().numpy())
            raw["weather_true"].append(batch["weather"].cpu().numpy())
    return raw


def _score(raw: dict[str, list], heads) -> dict:
    """The metrics of `_collect`'s lists (of one rank or all)."""
    if not raw["wp_err"]:
        raise UserError("no frames to evaluate")

    def planning(err: torch.Tensor) -> dict:
        dist = err.norm(dim=2)  # (N, 4)
        return {
            "l1_m": err.abs().mean().item(),
            "ade_m": dist.mean().item(),
            "fde_m": dist[:, -1].mean().item(),
        }

    wp_err = torch.from_numpy(np.concatenate(raw["wp_err"]))
    cv_err = torch.from_numpy(np.concatenate(raw["cv_err"]))
    result = {
        "frames": len(wp_err),
        "planning": planning(wp_err),
        "constant_velocity": planning(cv_err),
    }
    if "detection" in heads:
        result["detection"] = {}
        for t, name in enumerate(TIMESTEP_NAMES):
            pt, tt = raw[f"preds_{t}"], raw[f"truths_{t}"]
            aps = {f"ap@{d:g}m": average_precision(pt, tt, d) for d in DISTANCES_M}
            valid = [v for v in aps.values() if v is not None]
            aps["map"] = float(np.mean(valid)) if valid else None
            result["detection"][name] = aps
    if "bev" in heads:
        confusion = np.sum(raw["confusion"], axis=0)
        inter = np.diag(confusion)
        union = confusion.sum(0) + confusion.sum(1) - inter
        iou = {c: (float(i / u) if u else None) for c, i, u in zip(BEV_CLASSES, inter, union)}
        valid = [v for v in iou.values() if v is not None]
        result["bev"] = {"iou": iou, "miou": float(np.mean(valid)) if valid else None}
    if "traffic" in heads:
        prob, true = np.concatenate(raw["traffic_prob"]), np.concatenate(raw["traffic_true"])
        rule = lambda p: {  # noqa: E731
            "red_light": binary_scores(p[:, 0], true[:, 0]),
            "stop_sign": binary_scores(p[:, 1], true[:, 1]),
        }
        result["traffic"] = rule(prob)
        if raw.get("camera_traffic_prob"):  # the camera-only head (ModelConfig.camera_traffic)
            result["camera_traffic"] = rule(np.concatenate(raw["camera_traffic_prob"]))
    if "weather" in heads:
        pred, true = np.concatenate(raw["weather_pred"]), np.concatenate(raw["weather_true"])
        matrix = np.bincount(true * 4 + pred, minlength=16).reshape(4, 4)
        result["weather"] = {
            "accuracy": float((pred == true).mean()),
            "classes": list(WEATHERS),
            "confusion": matrix.tolist(),
        }
    return result


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def format_table(result: dict) -> str:
    """The metrics as an aligned text table."""
    lines = [f"frames: {result['frames']}", "", "planning           L1 m    ADE m   FDE m"]
    for name, key in (("model", "planning"), ("constant velocity", "constant_velocity")):
        p = result[key]
        lines.append(
            f"  {name:<17}{_fmt(p['l1_m']):>6}  {_fmt(p['ade_m']):>6}  {_fmt(p['fde_m']):>6}"
        )
    if "detection" in result:
        cols = "  ".join(f"{'AP@' + format(d, 'g') + 'm':>7}" for d in DISTANCES_M)
        lines += ["", f"detection   {cols}      mAP"]
        for t, aps in result["detection"].items():
            vals = "  ".join(f"{_fmt(v):>7}" for v in aps.values())
            lines.append(f"  {t:<10}{vals}")
    if "bev" in result:
        ious = "  ".join(f"{c} {_fmt(v)}" for c, v in result["bev"]["iou"].items())
        lines += ["", f"BEV map     mIoU {_fmt(result['bev']['miou'])}   ({ious})"]
    if "traffic" in result:
        lines += ["", "traffic     accuracy  F1     positives"]
        for name, s in result["traffic"].items():
            lines.append(
                f"  {name:<10}{_fmt(s['accuracy']):>8}  {_fmt(s['f1']):>5}  {s['positives']:>6}"
            )
        for name, s in result.get("camera_traffic", {}).items():  # the camera-only head
            lines.append(f"  {name:<10}{_fmt(s['accuracy']):>8}  {_fmt(s['f1']):>5}  camera alone")
    if "weather" in result:
        w = result["weather"]
        lines += ["", f"weather     accuracy {_fmt(w['accuracy'])}; confusion (rows truth):"]
        lines.append("            " + " ".join(f"{c:>7}" for c in w["classes"]))
        for c, row in zip(w["classes"], w["confusion"]):
            lines.append(f"  {c:<10}" + " ".join(f"{n:>7}" for n in row))
    return "\n".join(lines)


def run(args) -> int:
    out = Path(args.out) if args.out else Path(args.ckpt).with_suffix(".eval.json")
    outputs.check_file(out, "--out", suffixes=(".json",))  # before the computing
    state = load_checkpoint(args.ckpt)
    device = choose_device(args.device)
    model = model_from_checkpoint(state, device)
    index = data.scan(args.shards)
    check_sensors(state, data.sensor_config(index), args.shards, args.ckpt)
    if args.split == "val":
        index = index[index.episode_id.isin(state.get("val_episodes", []))]
        if index.empty:
            raise UserError(f"{args.shards}: none of the checkpoint's validation episodes")
    stream = data.FrameStream(
        index, model.cfg.output_px, single_frame_lidar=model.cfg.single_frame_lidar
    )
    result = evaluate(model, data.make_loader(stream, args.batch_size, args.workers), device)
    result = {
        "checkpoint": str(args.ckpt),
        "shards": str(args.shards),
        "split": args.split,
        **result,
    }
    outputs.write_json(out, result, indent=2)
    print(format_table(result))
    print(f"\nwrote {out}")
    return 0
