"""`experiment`: the paper's experiments, from nothing to REPORT.md, resumable.

experiment run --preset small --out runs/exp             # a 2-core CPU machine
experiment run --preset paper --out runs/paper --device cuda --nproc 8
experiment run --preset small --out runs/exp --list      # the steps, and which are done
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from datagen.errors import UserError
from schemas import cli

DEFAULT_PRESET = "small"


def _epilog() -> str:
    from experiments import runner

    names = [s.name for s in runner.steps(runner.PRESETS[DEFAULT_PRESET], Path("OUT"), "cpu", 1)]
    head = (
        f"Steps of the default preset ({DEFAULT_PRESET}), in order (a STEP for --until; --list "
        "prints another preset's, and which are done):"
    )
    wrap = dict(width=90, break_on_hyphens=False)
    return (
        textwrap.fill(head, **wrap)
        + "\n"
        + textwrap.fill(", ".join(names), initial_indent="  ", subsequent_indent="  ", **wrap)
        + "\nA stopped run (Ctrl-C, SIGTERM) resumes when the same command runs again."
    )


def _add_run(r: argparse.ArgumentParser) -> None:
    from experiments import runner

    r.add_argument(
        "--preset",
        default=DEFAULT_PRESET,
        help=f"how big: {', '.join(runner.PRESETS)} (experiments/runner.py PRESETS)",
    )
    r.add_argument("--out", required=True, type=Path, help="experiment directory")
    r.add_argument(
        "--device",
        default="cpu",
        choices=("auto", "cpu", "cuda"),
        help="where train, drive and analyze run; auto: CUDA if present",
    )
    r.add_argument("--nproc", type=int, default=1, help="train fit processes (torchrun, DDP)")
    r.add_argument(
        "--until", default=None, metavar="STEP", help="stop after this step (default: run all)"
    )
    r.add_argument("--list", action="store_true", help="print the steps and exit")


def _run(args) -> int:
    from experiments import runner

    if args.nproc < 1:
        raise UserError(f"--nproc must be >= 1, got {args.nproc}")
    if args.list:
        preset = runner.check_out(args.preset, args.out)
        for step in runner.steps(preset, args.out, args.device, args.nproc):
            done = (args.out / "steps" / f"{step.name}.json").exists()
            print(f"{'done' if done else 'todo'}  {step.name}")
        return 0
    runner.run(args.preset, args.out, args.device, args.nproc, args.until)
    return 0


def _resume_hint(args) -> str:
    return "run the same command again to resume"


def commands() -> tuple[cli.Command, ...]:
    return (
        cli.Command(
            "run",
            "run or resume an experiment, then write OUT/REPORT.md",
            _add_run,
            _run,
            resume=_resume_hint,
            epilog=_epilog(),
        ),
    )


def main(argv: list[str] | None = None) -> int:
    return cli.main("experiment", __doc__, commands(), argv)


if __name__ == "__main__":
    sys.exit(main())
