"""Does a checkpoint plan from its speed input? The inertia probe (issue 36 item 4).

    python bench/inertia.py --ckpt runs/m1/last.pt --shards runs/d41r --town downtown

On frames of one town (use the town the fit held out), in three groups: the ego standing while
the expert's label drives off (its 2 s waypoint over 1.5 m away: "stand & go"), standing and
staying (under 0.3 m: a red light, a queue), and moving (over 3 m/s). For each group, up to
--frames frames, the model's plan with the speed input as recorded and with it replaced by
--speed m/s; printed: the median distance of the 2 s waypoint (the label's beside it), the
share of frames planning to move over 1.5 m in 2 s, and the median speed the controller would
aim at (twice the first waypoint step, TransFuser's rule) with the share under its brake
threshold (0.4 m/s). A model whose plan follows the speed input rather than the scene stands
where it stood and goes where it went: the inertia of Codevilla et al. (ICCV 2019).
Asserts nothing.
"""

from __future__ import annotations

import argparse

import numpy as np
import pyarrow.parquet as pq
import torch

from training import data
from training.checkpoint import load_checkpoint, model_from_checkpoint

GO_M, STAY_M, MOVING_MPS, STANDING_MPS, BRAKE_MPS = 1.5, 0.3, 3.0, 0.1, 0.4


def labelled_index(shards: str):
    """The frame index with each frame's speed and its label's 2 s distance."""
    index = data.scan(shards)
    speed, far = [], []
    for path in index.path.unique():  # scan lists a file's rows in file order
        t = pq.read_table(path, columns=["ego_speed", "waypoints"])
        speed.append(t.column("ego_speed").to_numpy())
        wps = np.array(t.column("waypoints").to_pylist(), dtype=np.float64).reshape(-1, 4, 2)
        far.append(np.linalg.norm(wps[:, 3], axis=1))
    index["speed"], index["far"] = np.concatenate(speed), np.concatenate(far)
    return index


def plans(model, frames: list[dict], speed: float | None) -> np.ndarray:
    out = []
    for k in range(0, len(frames), 16):
        b = frames[k : k + 16]
        v = [f["speed"] if speed is None else speed for f in b]
        with torch.no_grad():
            out.append(
                model.plan(
                    torch.from_numpy(np.stack([f["image"] for f in b])),
                    torch.from_numpy(np.stack([f["lidar"] for f in b])),
                    torch.tensor(v, dtype=torch.float32),
                    torch.from_numpy(np.stack([f["target_point"] for f in b])),
                ).numpy()
            )
    return np.concatenate(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--shards", required=True, help="shard directory (or several, comma-separated)")
    p.add_argument("--town", required=True, help="the town whose frames are probed")
    p.add_argument("--frames", type=int, default=120, help="frames per group (default 120)")
    p.add_argument("--speed", type=float, default=3.0, help="the replaced speed input, m/s")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(1)
    model = model_from_checkpoint(load_checkpoint(args.ckpt))
    index = labelled_index(args.shards)
    index = index[index.town == args.town]
    standing = index[index.speed < STANDING_MPS]
    groups = {
        "stand & go": standing[standing.far > GO_M],
        "stand & stay": standing[standing.far < STAY_M],
        "moving": index[index.speed > MOVING_MPS],
    }
    rng = np.random.default_rng(args.seed)
    print(f"{args.ckpt} on {args.town}: speed input as recorded, then {args.speed:g} m/s")
    print("group          n  speed in | 2 s distance (label) | plans > 1.5 m | aim speed, < 0.4")
    for name, sel in groups.items():
        if sel.empty:
            print(f"{name:12s} none")
            continue
        sel = sel.iloc[np.sort(rng.permutation(len(sel))[: args.frames])]
        frames = data.read_frames(sel, model.cfg.output_px)
        label = np.median(sel.far)
        for speed in (None, args.speed):
            w = plans(model, frames, speed)
            far = np.linalg.norm(w[:, 3], axis=1)
            aim = 2.0 * np.linalg.norm(w[:, 1] - w[:, 0], axis=1)
            given = "recorded" if speed is None else f"{speed:g} m/s"
            print(
                f"{name:12s} {len(frames):3d}  {given:8s} | {np.median(far):5.2f} m ({label:5.2f}) "
                f"|    {np.mean(far > GO_M):.2f}     | {np.median(aim):4.2f} m/s, "
                f"{np.mean(aim < BRAKE_MPS):.2f}"
            )


if __name__ == "__main__":
    main()
