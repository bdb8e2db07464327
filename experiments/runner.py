"""The paper's experiments as one resumable pipeline of the project's own commands.

    experiment run --preset small --out runs/exp        # ~85 min on 2 CPU cores
    experiment run --preset paper --out runs/paper --device cuda --nproc 8
    experiment run --preset small --out runs/exp --until fit-full   # stop after that step

Steps, in order (each a real command; its log in OUT/logs/STEP.log):
1. build: `datagen build --towns N` into OUT/data; the preset's held-out town (`val_town`) is in
   the data but never trained on (`train fit --val-towns`), as the paper holds Town05 out;
2. per variant and seed: `train fit` (the paper's full model and its Table III ablations, and
   ours: the full model plus our additions, `--arch ours`), then `train eval --split val` (open
   loop, on the held-out town);
3. per variant and seed: `drive eval` on the seen-town routes (OUT/routes/seen.json: routes of
   drive/routes/training_towns.json in the towns the model trained on, the preset's val_town
   excluded, taken in turn from each town) and the held-out ones (heldout_short.json, the unseen
   town `boulevard`, every route recorded as a video), each with and without the creep
   (`--no-creep`: what the model does alone);
4. `train analyze` of every full model (Table II), `drive swap` of the full and the no-weather
   model (Fig. 6);
5. OUT/REPORT.md (experiments/report.py), from the JSON files the steps wrote.

A finished step leaves OUT/steps/STEP.json (its command, wall time, the time it finished);
rerunning the same command skips finished steps, resumes an interrupted `datagen build` (its
own resume) and an interrupted `train fit` (`--resume` from its last.pt), and redoes the rest.
The preset is recorded in OUT/experiment.json; rerunning with another preset is refused.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from datagen.errors import UserError
from schemas import outputs
from schemas.cli import sigterm_received
from schemas.errors import Terminated

ROOT = Path(__file__).resolve().parents[1]
ROUTES = ROOT / "drive" / "routes"

# Table III's rows: the flags of `train fit` that make each variant (paper Sec. IV-B), all of
# the paper's architecture (`--arch paper`, nothing of ours); the ablations remove heads from
# it, as the paper does. "none" is our reading of the paper's "None" row: planning alone, no
# auxiliary head, one LiDAR sweep. "ours", one extra row beside "full", is the full model plus
# our additions (`--arch ours`, training/lamps.py), not in the paper.
PAPER = ("--arch", "paper")
VARIANTS = {
    "full": PAPER,
    "ours": ("--arch", "ours"),
    "no_multiframe": (*PAPER, "--single-frame-lidar"),
    "no_detection": (*PAPER, "--no-detection"),
    "no_bev": (*PAPER, "--no-bev"),
    "no_traffic": (*PAPER, "--no-traffic"),
    "no_weather": (*PAPER, "--no-weather"),
    "none": (
        *PAPER,
        "--no-detection",
        "--no-bev",
        "--no-traffic",
        "--no-weather",
        "--single-frame-lidar",
    ),
}


@dataclass(frozen=True)
class Preset:
    """How big an experiment is.

    Attributes:
        towns, frames, episode_seconds: the build (`datagen build`).
        val_town: the town held out of training (open-loop evaluation).
        config, epochs: `train fit --config/--epochs`.
        variants: keys of VARIANTS; seeds: training seeds per variant.
        seen_routes, heldout_routes: routes driven per route file (0 = all).
        max_sim_s: stop each route after this much simulated time (None = the full route).
        swap_frames: frames of the weather swap; analyze_frames: of Table II.
    """

    towns: int
    frames: int
    episode_seconds: float
    val_town: str
    config: str
    epochs: int
    variants: tuple[str, ...]
    seeds: tuple[int, ...]
    seen_routes: int
    heldout_routes: int
    max_sim_s: float | None
    swap_frames: int
    analyze_frames: int
    workers: int = field(default=2)


PRESETS = {
    # The test suite's: every step and every table of the report, in about two minutes.
    "minute": Preset(
        2, 40, 10.0, "downtown", "tiny", 1, ("full", "ours", "no_weather"), (0,), 1, 1, 8.0, 3, 16
    ),  # fmt: skip
    # A 2-core CPU machine in about 85 min (73 measured for the seven paper rows; the ours row
    # estimated from one row's share): the tiny model, one seed, short routes. 4 epochs:
    # with 2, held-out weather accuracy was 0.79 and ADE 1.29x constant velocity's; the same
    # data at epoch 4 of 6 gave 0.90 and 1.12x (issue 13's notes).
    "small": Preset(
        8, 4000, 45.0, "arterial", "tiny", 4, tuple(VARIANTS), (0,), 4, 4, None, 60, 256
    ),  # fmt: skip
    # The paper's scale: 146k frames, the paper model, three seeds; a GPU machine (--nproc).
    "paper": Preset(
        8, 146000, 180.0, "arterial", "paper", 30, tuple(VARIANTS), (0, 1, 2), 0, 0, None, 240, 1024
    ),  # fmt: skip
}


@dataclass(frozen=True)
class Step:
    """One command of the pipeline: its name, argv (python -m ...), and the file it leaves."""

    name: str
    argv: tuple[str, ...]
    output: str  # relative to OUT; the step's result (checked to exist after it ran)
    resume: tuple[str, ...] = ()  # extra argv when an interrupted run is continued
    epochs: int | None = None  # a fit: its output is complete once it holds this many epochs
    fresh: tuple[str, ...] = ()  # extra argv when it starts anew over what an earlier try left


def _fit_epochs(ckpt: Path) -> int:
    """Epochs a `train fit` checkpoint has finished."""
    from training.checkpoint import load_checkpoint

    return int(load_checkpoint(ckpt).get("epoch", 0))


def run_name(variant: str, seed: int) -> str:
    return f"{variant}-s{seed}"


def seen_routes(p: Preset):
    """The seen-town routes of preset `p`: training_towns.json's routes in the towns of its
    build but not its val_town (held out of training), taken in turn from each town so that
    several towns are covered, `p.seen_routes` of them (0: all)."""
    from datagen.world.towns import TOWN_NAMES
    from drive.routes import load_routes

    _, routes = load_routes(ROUTES / "training_towns.json")
    towns = [t for t in TOWN_NAMES[: p.towns] if t != p.val_town]
    queues = [[r for r in routes if r.town == t] for t in towns]
    picked = []
    while any(queues):
        for q in queues:
            if q:
                picked.append(q.pop(0))
    return picked[: p.seen_routes] if p.seen_routes else picked


def write_seen_routes(p: Preset, out: Path) -> Path:
    """OUT/routes/seen.json (seen_routes), the route file of the seen-town drives."""
    from drive.routes import save_routes

    path = out / "routes" / "seen.json"
    routes = seen_routes(p)
    if not routes:
        raise UserError(f"no seen-town routes: the build's towns are only {p.val_town!r}")
    save_routes(routes, path, "seen")
    return path


def steps(p: Preset, out: Path, device: str, nproc: int) -> list[Step]:
    """Every step of preset `p` writing under `out`, in order."""
    data = str(out / "data")
    py = ("datagen.cli", "build", "--towns", str(p.towns), "--frames", str(p.frames))
    build = py + ("--episode-seconds", f"{p.episode_seconds:g}", "--workers", str(p.workers))
    result = [Step("build", build + ("--out", data, "--no-progress"), "data/_manifest.json")]
    for variant in p.variants:
        for seed in p.seeds:
            name = run_name(variant, seed)
            run = out / "runs" / name
            fit = ("training.cli", "fit", "--shards", data, "--config", p.config, "--out", str(run))
            fit += ("--epochs", str(p.epochs), "--val-towns", p.val_town, "--seed", str(seed))
            fit += ("--device", device, *VARIANTS[variant])
            if nproc > 1:
                fit = ("torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
                       "-m", *fit)  # fmt: skip
            ckpt = str(run / "last.pt")
            fit_step = Step(
                f"fit-{name}", fit, f"runs/{name}/last.pt", ("--resume",), p.epochs, ("--force",)
            )
            result.append(fit_step)
            ev = ("training.cli", "eval", "--ckpt", ckpt, "--shards", data, "--split", "val")
            ev += ("--device", device, "--out", str(run / "eval.json"))
            result.append(Step(f"eval-{name}", ev, f"runs/{name}/eval.json"))
            held = p.heldout_routes or 10
            for kind, routes, limit, record in (
                ("seen", out / "routes" / "seen.json", 0, 0),
                ("heldout", ROUTES / "heldout_short.json", p.heldout_routes, held),
            ):
                for creep in (True, False):
                    sub = kind if creep else f"{kind}_nocreep"
                    dr = ("drive.cli", "eval", "--policy", f"ckpt:{ckpt}")
                    dr += ("--routes", str(routes), "--workers", str(p.workers))
                    dr += ("--device", device, "--out", str(out / "drive" / name / sub))
                    dr += ("--limit", str(limit)) if limit else ()
                    dr += ("--max-sim-s", f"{p.max_sim_s:g}") if p.max_sim_s else ()
                    dr += ("--record", str(record)) if creep and record else ()
                    dr += () if creep else ("--no-creep",)
                    step = f"drive-{kind}-{name}" if creep else f"drive-{kind}-nocreep-{name}"
                    result.append(Step(step, dr, f"drive/{name}/{sub}/summary.json"))
    for seed in p.seeds:  # Table II: every full model (seeds are a level of the interval)
        name = run_name("full", seed)
        an = ("training.cli", "analyze", "--ckpt", str(out / "runs" / name / "last.pt"))
        an += ("--shards", data, "--frames", str(p.analyze_frames), "--device", device)
        an += ("--out", str(out / f"analyze-{name}.json"))
        result.append(Step(f"analyze-{name}", an, f"analyze-{name}.json"))
    for variant in ("full", "no_weather"):
        if variant not in p.variants:
            continue
        name = run_name(variant, p.seeds[0])
        sw = ("drive.cli", "swap", "--policy", f"ckpt:{out / 'runs' / name / 'last.pt'}")
        sw += ("--frames", str(p.swap_frames), "--device", device)
        result.append(Step(f"swap-{name}", sw + ("--out", str(out / "swap" / name)),
                           f"swap/{name}/swap.json"))  # fmt: skip
    return result


def _run_step(step: Step, out: Path, resuming: bool) -> float:
    log = out / "logs" / f"{step.name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", *step.argv, *(step.resume if resuming else step.fresh)]
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    t0 = time.perf_counter()
    with log.open("a") as f:
        f.write(f"$ {' '.join(argv)}\n")
        f.flush()
        child = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        try:
            code = child.wait()
        except KeyboardInterrupt as e:  # Ctrl-C (the child has it too) or SIGTERM (this alone)
            _stop(child, isinstance(e, Terminated) or sigterm_received())
            raise
    if code != 0:
        tail = log.read_text().strip().splitlines()[-1:] or [""]
        raise UserError(f"step {step.name} failed (exit {code}): {tail[0]} (log: {log})")
    if not (out / step.output).exists():
        raise UserError(f"step {step.name} finished without writing {step.output} (log: {log})")
    return time.perf_counter() - t0


def _stop(child: subprocess.Popen, sigterm: bool, wait_s: float = 60.0) -> None:
    """Let a step stop cleanly (a build records what is done, a fit keeps its last checkpoint):
    pass SIGTERM on; after a Ctrl-C, which a terminal sends the step too, give it a moment
    before sending SIGINT (a second one would cut its clean-up short); kill it only if it has
    not stopped within `wait_s`."""
    if sigterm:
        child.send_signal(signal.SIGTERM)
    else:
        try:
            child.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            child.send_signal(signal.SIGINT)
    try:
        child.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def check_out(preset_name: str, out: Path) -> Preset:
    """The preset, checked against `out`, before anything is written there: `out` must be a
    directory that can be written and hold no experiment of another preset."""
    if preset_name not in PRESETS:
        raise UserError(f"unknown preset {preset_name!r}; expected one of {tuple(PRESETS)}")
    p = PRESETS[preset_name]
    outputs.check_dir(out)
    meta_path = out / "experiment.json"
    if meta_path.exists():
        config = json.loads(json.dumps(asdict(p)))  # as read back from the file (lists)
        try:
            old = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("preset") != preset_name or old.get("config") != config:
            raise UserError(
                f"{out} holds an experiment of preset {old.get('preset')!r} (its own settings); "
                "give another --out"
            )
    return p


def run(
    preset_name: str,
    out: Path,
    device: str = "cpu",
    nproc: int = 1,
    until: str | None = None,
    echo=print,
) -> Path | None:
    """Run (or resume) the pipeline; the report's path, or None when stopped at `until`."""
    from experiments import report

    p = check_out(preset_name, out)
    all_steps = steps(p, out, device, nproc)
    names = [s.name for s in all_steps]
    if until is not None and until not in names:
        raise UserError(f"--until {until!r}: no such step (steps: {', '.join(names)})")
    config = json.loads(json.dumps(asdict(p)))  # as read back from the file (lists)
    meta = {"preset": preset_name, "config": config, "device": device, "nproc": nproc}
    outputs.write_json(out / "experiment.json", meta)
    write_seen_routes(p, out)
    for step in all_steps:
        done = out / "steps" / f"{step.name}.json"
        if done.exists():
            echo(f"skip {step.name} (done)")
        else:
            resuming = bool(step.resume) and (out / step.output).exists()
            if resuming and step.epochs and _fit_epochs(out / step.output) >= step.epochs:
                echo(f"skip {step.name} (its checkpoint holds all {step.epochs} epochs)")
                wall = 0.0
            else:
                echo(f"run  {step.name}" + (" (resuming)" if resuming else ""))
                wall = _run_step(step, out, resuming)
            record = {"argv": list(step.argv), "wall_s": round(wall, 2), "finished": time.time()}
            outputs.write_json(done, record)
        if step.name == until:
            echo(f"stopped after {until}")
            return None
    path = report.write(out, p, preset_name, all_steps)
    echo(f"wrote {path}")
    return path
