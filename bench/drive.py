"""Benchmark closed-loop driving: simulated seconds per wall second per policy, and where the
time goes.

    python bench/drive.py                        # expert, constant, tiny and paper models, CPU
    python bench/drive.py --seconds 60 --device cuda

Drives the first route of drive/routes/heldout_short.json (the held-out town, real traffic) for
at most --seconds simulated seconds with each policy, one worker, and prints per policy the
simulated seconds, the wall seconds of the drive (set-up apart) and their ratio (the speed-up
over real time), and the wall seconds per simulated second of each stage: the world (SUMO and
the controller), the sensors (scene, LiDAR, camera, encoding; 2 Hz), the policy (decoding and
the model's forward pass; 2 Hz) and the judge (infractions, TTC). The model policies use
untrained weights of the `tiny` and `paper` presets: speed does not depend on the weights,
though how far an untrained model drives does (a route may end early: that is reported).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as drive/cli.py: before torch is imported

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drive.evaluate import Task, drive_route  # noqa: E402
from drive.policy import PolicySpec  # noqa: E402
from drive.routes import ROUTES_DIR, load_routes  # noqa: E402


def _checkpoint(preset: str, out: Path) -> Path:
    import torch

    from datagen.sensors.config import SensorConfig
    from training.config import PRESETS
    from training.model import IIDSU

    cfg = PRESETS[preset][0]
    torch.manual_seed(0)
    path = out / f"{preset}.pt"
    state = {
        "model": IIDSU(cfg).state_dict(),
        "model_config": cfg.to_dict(),
        "sensor_config": SensorConfig().to_dict(),
    }
    torch.save(state, path)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--routes", type=Path, default=ROUTES_DIR / "heldout_short.json")
    ap.add_argument("--seconds", type=float, default=40.0, help="simulated seconds per policy")
    ap.add_argument("--policies", default="expert,constant,tiny,paper")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    _, routes = load_routes(args.routes)
    route = routes[0]
    tmp = Path(tempfile.mkdtemp(prefix="iidsu-bench-drive-"))
    head = (
        f"{'policy':<9} {'sim s':>6} {'wall s':>7} {'x real':>7} | wall s per sim s: "
        f"{'world':>6} {'sensors':>8} {'policy':>7} {'judge':>6} | ended"
    )
    print(f"route {route.route_id} ({route.length_m:.0f} m, {route.weather}), device {args.device}")
    print(head)
    print("-" * len(head))
    for name in args.policies.split(","):
        if name in ("expert", "constant"):
            spec = PolicySpec(name, device=args.device)
        else:
            spec = PolicySpec("ckpt", str(_checkpoint(name, tmp)), args.device)
        doc = drive_route(Task(route, spec, str(tmp / name), False, max_sim_s=args.seconds))
        t = doc["timing"]
        sim = max(doc["sim_s"], 1e-6)
        wall = t["total"] - t["setup"]
        print(
            f"{name:<9} {sim:>6.1f} {wall:>7.1f} {sim / wall:>7.2f} | {'':17}"
            f"{t['sim'] / sim:>6.3f} {t['sensors'] / sim:>8.3f} {t['policy'] / sim:>7.3f} "
            f"{t['judge'] / sim:>6.3f} | {doc['ended']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
