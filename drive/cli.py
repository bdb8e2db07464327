"""`drive`: closed-loop evaluation.

    drive routes --standard                                        # the benchmark route files
    drive eval --policy ckpt:runs/demo/last.pt --routes drive/routes/heldout_short.json \\
        --workers 2 --out runs/eval_heldout
    drive swap --policy ckpt:runs/demo/last.pt --town downtown --out runs/swap   # Fig. 6
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# As in `train` (training/cli.py): OpenMP threads that spin while they wait take the cores SUMO,
# the ray caster and the other route workers need; set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from datagen.errors import UserError


def main(argv: list[str] | None = None) -> int:
    from drive import evaluate, routes, swap

    p = argparse.ArgumentParser(prog="drive", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("routes", help="write a deterministic route set (JSON)")
    routes.add_arguments(r)
    e = sub.add_parser("eval", help="drive a route set with a policy and score it")
    e.add_argument("--policy", required=True, help="expert | constant | ckpt:PATH")
    e.add_argument("--routes", required=True, type=Path, help="route file (drive routes)")
    e.add_argument("--out", required=True, type=Path, help="results directory")
    e.add_argument("--workers", type=int, default=1, help="routes driven in parallel")
    e.add_argument(
        "--executor", default="process", choices=("process", "ray"), help="where workers run"
    )
    e.add_argument("--ray-address", default=None, help="an existing Ray cluster")
    e.add_argument("--record", type=int, default=0, help="MP4 videos of the first N routes")
    e.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    e.add_argument("--net", type=Path, default=None, help="the network of a --net route file")
    e.add_argument("--limit", type=int, default=0, help="drive only the first N routes")
    e.add_argument(
        "--max-sim-s",
        type=float,
        default=None,
        help="stop each route after this many simulated seconds, scored as far as it got "
        "(smoke runs; ends 'max_sim_s')",
    )
    e.add_argument(
        "--no-creep",
        action="store_true",
        help="no creep: a policy that stands 55 s is not pushed forward (TransFuser's rule)",
    )
    e.add_argument(
        "--baseline", type=Path, default=None, help="an expert run's --out: traffic delay vs it"
    )
    w = sub.add_parser("swap", help="one scene in two weathers: what the model plans (Fig. 6)")
    swap.add_arguments(w)
    args = p.parse_args(argv)
    try:
        from training.errors import UserError as TrainError
    except ImportError:  # torch not installed: only the checkpoint policy needs it
        TrainError = UserError
    try:
        if args.command == "routes":
            return routes.run(args)
        if args.command == "swap":
            return swap.run(args)
        return evaluate.run(args)
    except (UserError, TrainError) as e:
        print(f"drive: error: {str(e).splitlines()[0] if str(e) else e!r}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
