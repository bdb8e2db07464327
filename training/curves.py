"""`train curves`: a run's training curves as one PNG, for readers without TensorBoard.

    train curves --run runs/demo                       # runs/demo/curves.png
    train curves --run runs/demo --out curves.png

Reads what `train fit` writes (training/fit.py): OUT/steps.jsonl (the mean of every loss term
over each LOG_EVERY steps, the learning rate, samples/s) and OUT/metrics.jsonl (per epoch: the
train and validation loss terms and the validation metrics of `train eval`). One panel per loss
term (train per step, validation per epoch; log scale), one for the learning rate and
throughput, and one for the validation metrics. Needs matplotlib (the `curves` extra).
"""

from __future__ import annotations

import json
from pathlib import Path

from schemas import outputs
from training.errors import UserError
from training.fit import METRICS, STEPS

# Validation metrics drawn, with their panel label; ADE is drawn against the constant-velocity
# baseline, the rest are fractions in [0, 1].
ERRORS_M = ("ade_m", "cv_ade_m", "fde_m", "cv_fde_m")
SCORES = ("weather_accuracy", "red_light_f1", "stop_sign_f1", "miou", "iou_lane_marking", "det_map")


def _read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not a log written by `train fit` ({e})") from None


def draw(run: Path, out: Path) -> Path:
    """Draw the curves of run directory `run` into the PNG `out` (written atomically)."""
    steps, epochs = _read_jsonl(run / STEPS), _read_jsonl(run / METRICS)
    if not steps and not epochs:
        if (run / STEPS).is_file() or (run / METRICS).is_file():
            raise UserError(
                f"{run}: its logs are empty ({STEPS}, {METRICS}): the fit stopped before its "
                "first logged step"
            )
        raise UserError(f"{run}: no {STEPS} or {METRICS} (not a `train fit` run directory?)")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserError(
            "train curves needs matplotlib: pip install -e '.[curves]' (or use TensorBoard: "
            f"tensorboard --logdir {run / 'tensorboard'})"
        ) from None
    terms = list(dict.fromkeys(k for line in steps + epochs for k in line["train"]))
    n = len(terms) + 2
    cols = 4
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    axes = axes.flatten()
    for ax, term in zip(axes, terms):
        xs = [s["step"] for s in steps if term in s["train"]]
        ax.plot(xs, [s["train"][term] for s in steps if term in s["train"]], lw=0.8, label="train")
        val = [(e["step"], e["val"][term]) for e in epochs if term in e.get("val", {})]
        if val:
            ax.plot(*zip(*val), "o-", ms=3, label="val (epoch)")
        ax.set_title(term)
        ax.set_xlabel("step")
        if all(v > 0 for v in ax.get_lines()[0].get_ydata()):
            ax.set_yscale("log")
        ax.legend(fontsize=7)
    ax = axes[len(terms)]
    if steps:
        ax.plot([s["step"] for s in steps], [s["lr"] for s in steps], color="C2")
        ax.set_ylabel("learning rate", color="C2")
        twin = ax.twinx()
        twin.plot([s["step"] for s in steps], [s["samples_per_s"] for s in steps], "C3", lw=0.6)
        twin.set_ylabel("samples/s", color="C3")
    ax.set_title("schedule and throughput")
    ax.set_xlabel("step")
    ax = axes[len(terms) + 1]
    vm = [(e["epoch"], e["val_metrics"]) for e in epochs if e.get("val_metrics")]
    for key in SCORES:
        pts = [(ep, m[key]) for ep, m in vm if m.get(key) is not None]
        if pts:
            ax.plot(*zip(*pts), "o-", ms=3, label=key)
    if vm:
        twin = ax.twinx()
        for key, style in zip(ERRORS_M, ("k-", "k--", "m-", "m--")):
            pts = [(ep, m[key]) for ep, m in vm if m.get(key) is not None]
            if pts:
                twin.plot(*zip(*pts), style, lw=1, label=key)
        twin.set_ylabel("m (ADE/FDE; dashed: constant velocity)")
        twin.legend(fontsize=6, loc="lower left")
        ax.legend(fontsize=6, loc="upper left")
    ax.set_ylim(0, 1)
    ax.set_title("validation metrics (train eval)")
    ax.set_xlabel("epoch")
    for ax in axes[n:]:
        ax.axis("off")
    fig.suptitle(str(run))
    fig.tight_layout()
    try:
        with outputs.atomic(out) as tmp:
            fig.savefig(tmp, dpi=80, format="png")
    finally:
        plt.close(fig)
    return out


def run(args) -> int:
    run_dir = Path(args.run)
    if run_dir.is_file():
        raise UserError(f"--run {run_dir}: not a run directory (give the --out of `train fit`)")
    if not run_dir.is_dir():
        raise UserError(f"--run {run_dir}: no such run directory")
    out = outputs.check_file(args.out or run_dir / "curves.png", "--out", suffixes=(".png",))
    out = draw(run_dir, out)
    print(f"wrote {out}")
    return 0
