"""`experiment`: the paper's experiments, from nothing to REPORT.md, resumable.

experiment run --preset small --out runs/exp             # a 2-core CPU machine, ~1 h
experiment run --preset paper --out runs/paper --device cuda --nproc 8
experiment run --preset small --out runs/exp --list      # the steps, and which are done
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from datagen.errors import UserError


def main(argv: list[str] | None = None) -> int:
    from experiments import runner

    p = argparse.ArgumentParser(prog="experiment", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run or resume an experiment, then write OUT/REPORT.md")
    r.add_argument("--preset", default="small", help=f"one of {', '.join(runner.PRESETS)}")
    r.add_argument("--out", required=True, type=Path, help="experiment directory")
    r.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"))
    r.add_argument("--nproc", type=int, default=1, help="train fit processes (torchrun, DDP)")
    r.add_argument("--until", default=None, metavar="STEP", help="stop after this step")
    r.add_argument("--list", action="store_true", help="print the steps and exit")
    args = p.parse_args(argv)
    try:
        if args.nproc < 1:
            raise UserError(f"--nproc must be >= 1, got {args.nproc}")
        if args.list:
            preset = runner.PRESETS.get(args.preset)
            if preset is None:
                raise UserError(f"unknown preset {args.preset!r}; expected one of "
                                f"{tuple(runner.PRESETS)}")  # fmt: skip
            for step in runner.steps(preset, args.out, args.device, args.nproc):
                done = (args.out / "steps" / f"{step.name}.json").exists()
                print(f"{'done' if done else 'todo'}  {step.name}")
            return 0
        runner.run(args.preset, args.out, args.device, args.nproc, args.until)
        return 0
    except UserError as e:
        print(f"experiment: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
