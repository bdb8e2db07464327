"""`drive`: closed-loop evaluation.

    drive routes --standard                                        # the benchmark route files
    drive eval --policy ckpt:runs/demo/last.pt --routes drive/routes/heldout_short.json \\
        --workers 2 --out runs/eval_heldout
    drive swap --policy ckpt:runs/demo/last.pt --town downtown --out runs/swap   # Fig. 6
    drive collect --policy ckpt:runs/demo/last.pt --towns 8 --frames 4000 --out runs/dagger1
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# As in `train` (training/cli.py): OpenMP threads that spin while they wait take the cores SUMO,
# the ray caster and the other route workers need; set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from schemas import cli  # noqa: E402


def _add_eval(e: argparse.ArgumentParser) -> None:
    e.add_argument(
        "--policy",
        required=True,
        help="expert | expert-plan (the expert's waypoints through the model's controller) | "
        "constant | ckpt:PATH",
    )
    e.add_argument("--routes", required=True, type=Path, help="route file (drive routes)")
    e.add_argument("--out", required=True, type=Path, help="results directory")
    e.add_argument("--workers", type=int, default=1, help="routes driven in parallel")
    e.add_argument(
        "--executor", default="process", choices=("process", "ray"), help="where workers run"
    )
    e.add_argument(
        "--ray-address", default=None, help="an existing Ray cluster (default: a local one)"
    )
    e.add_argument("--record", type=int, default=0, help="MP4 videos of the first N routes")
    e.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="where a ckpt: policy runs; auto: CUDA if present",
    )
    e.add_argument("--net", type=Path, default=None, help="the network file of a --net route file")
    e.add_argument(
        "--limit",
        type=int,
        default=None,
        metavar="N",
        help="drive only the first N routes of the file (N >= 1; default: all)",
    )
    e.add_argument(
        "--repetitions",
        type=int,
        default=1,
        help="drive every route N times with different traffic seeds (the leaderboard's "
        "--repetitions); the summary averages a route's repetitions first",
    )
    e.add_argument(
        "--max-sim-s",
        type=float,
        default=None,
        help="stop each route after this many simulated seconds, scored as far as it got "
        "(smoke runs; ends 'max_sim_s'; default: the whole route)",
    )
    e.add_argument(
        "--no-creep",
        action="store_true",
        help="no creep: a policy that stands 55 s is not pushed forward (TransFuser's rule)",
    )
    e.add_argument(
        "--lateral",
        choices=("pursuit", "pid"),
        default="pursuit",
        help="how the controller steers a non-privileged policy along its waypoints: pure "
        "pursuit on the planned trajectory, or TransFuser's PID on the first two waypoints "
        "(default: %(default)s; drive/controller.py)",
    )
    e.add_argument(
        "--baseline", type=Path, default=None, help="an expert run's --out: traffic delay vs it"
    )


def _routes(args) -> int:
    from drive import routes

    return routes.run(args)


def _eval(args) -> int:
    from drive import evaluate

    return evaluate.run(args)


def _swap(args) -> int:
    from drive import swap

    return swap.run(args)


def _add_routes(p: argparse.ArgumentParser) -> None:
    from drive import routes

    routes.add_arguments(p)


def _add_collect(p: argparse.ArgumentParser) -> None:
    from drive import collect

    collect.add_arguments(p)


def _collect(args) -> int:
    from drive import collect

    return collect.run(args)


def _add_swap(p: argparse.ArgumentParser) -> None:
    from drive import swap

    swap.add_arguments(p)


COMMANDS = (
    cli.Command("routes", "write a deterministic route set (JSON)", _add_routes, _routes),
    cli.Command("eval", "drive a route set with a policy and score it", _add_eval, _eval),
    cli.Command(
        "swap", "one scene in two weathers: what the model plans (Fig. 6)", _add_swap, _swap
    ),
    cli.Command(
        "collect",
        "on-policy data: a policy drives, the expert labels every frame (DAgger, DART)",
        _add_collect,
        _collect,
    ),
)


def main(argv: list[str] | None = None) -> int:
    return cli.main("drive", __doc__.splitlines()[0], COMMANDS, argv)


if __name__ == "__main__":
    sys.exit(main())
