"""Does it drive? Build, train and drive in one command, and print the closed-loop table.

    python bench/drive_check.py --out runs/check                      # the recipe, seed 0
    python bench/drive_check.py --out runs/check --seeds 0,1,2 --routes heldout   # the figure
    python bench/drive_check.py --out runs/check --seeds '' --privileged-seeds 0 \
        --privileged-name priv-ps --privileged-arg=--planner-output --privileged-arg=path_speed

Steps (each skipped when its output is already there, so a stopped check resumes):
1. `datagen build` of --frames in the eight training towns (--recovery: the share of recovery
   frames, sensed from a shifted rig; data/README.md), and `drive collect` of --dart-frames
   driven by the expert's plan with DART-style perturbations (--noise; drive/collect.py);
2. per training seed, `train fit --config tiny --arch A` (--val-towns held out of training), then
   --dagger-rounds rounds of `drive collect` (the model drives, the expert labels; --beta) and a
   fine-tune on the union (`train fit --init`);
2b. per --privileged-seeds seed, `train fit --arch privileged` (the planner on ground truth,
   training/privileged.py; --privileged-arg flags, --privileged-name its rows' name) on the
   same shards;
3. `drive eval` of the route sets: `dev` (the training towns' short routes, where choices are
   made) and/or `heldout` (boulevard's short routes, and with --long its long ones, measured
   once per choice), for the expert (the ceiling), `expert-plan` (its plan through the model's
   controller: the controller's ceiling), `constant` (the floor), each privileged planner
   without the creep, and each seed's model with the creep and without it.

Prints DS, RC, IS, infractions per km and the seconds per route the policy stood where the
expert would have driven on, per policy, then each model's DS as a share of the expert's in the
same run, mean and spread over the seeds. Writes OUT/check.json. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
ROUTES = ROOT / "drive" / "routes"
# summary.json per_km keys (drive/score.py INFRACTION_TYPES), in the paper's Table III order
COLUMNS = (
    "collision_pedestrian",
    "collision_vehicle",
    "collision_layout",
    "red_light",
    "stop_sign",
    "off_road",
    "route_deviation",
    "route_timeout",
    "agent_blocked",
)
SHORT = "Ped / Veh / Lay / Red / Stop / OR / Dev / TO / Block"


def run(cmd: list[str], log: Path) -> float:
    """Run a command, its output to `log`; seconds it took (exit on failure)."""
    print("$", " ".join(str(c) for c in cmd), flush=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.call([str(c) for c in cmd], stdout=f, stderr=subprocess.STDOUT)
    if rc:
        sys.exit(f"failed ({rc}); see {log}")
    return time.perf_counter() - t0


def dev_routes(out: Path) -> Path:
    """The training towns' short routes (the development set)."""
    path = out / "dev_short.json"
    if not path.exists():
        doc = json.loads((ROUTES / "training_towns.json").read_text())
        doc["routes"] = [r for r in doc["routes"] if "-short-" in r["route_id"]]
        doc["name"] = "training_towns short"
        path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/check"))
    p.add_argument("--data", type=Path, default=None, help="an existing build (skips step 1)")
    p.add_argument("--frames", type=int, default=16000)
    p.add_argument("--build-seed", type=int, default=41)
    p.add_argument("--recovery", type=float, default=0.5, help="share of recovery frames")
    p.add_argument("--dart-frames", type=int, default=4000, help="0: no perturbed driving")
    p.add_argument("--noise", type=float, default=0.15, help="drive collect --noise")
    p.add_argument("--epochs", type=int, default=6)
    p.add_argument("--val-towns", default="downtown")
    p.add_argument("--arch", choices=("paper", "ours"), default="paper", help="train fit --arch")
    p.add_argument("--seeds", default="0", help="sensor-model seeds, comma-separated ('': none)")
    p.add_argument(
        "--privileged-seeds",
        default="",
        help="privileged planner seeds (train fit --arch privileged), comma-separated ('': none)",
    )
    p.add_argument(
        "--privileged-arg", action="append", default=[], help="extra privileged train fit flag"
    )
    p.add_argument(
        "--privileged-name", default="privileged", help="its rows' and run directories' name"
    )
    p.add_argument("--privileged-epochs", type=int, default=12)
    p.add_argument("--dagger-rounds", type=int, default=1)
    p.add_argument("--dagger-frames", type=int, default=4000)
    p.add_argument("--dagger-epochs", type=int, default=2)
    p.add_argument("--beta", type=float, default=0.5)
    p.add_argument("--routes", default="dev", help="dev, heldout or dev,heldout")
    p.add_argument("--long", action="store_true", help="also boulevard's long routes")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--lateral", default="pursuit", choices=("pursuit", "pid"))
    args = p.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    privileged_seeds = [int(s) for s in args.privileged_seeds.split(",") if s]
    wall: dict[str, float] = {}

    data = args.data or out / "data"
    if args.data is None and not (data / "_manifest.json").exists():
        wall["build"] = run(
            [BIN / "datagen", "build", "--towns", 8, "--frames", args.frames, "--seed",
             args.build_seed, "--sensor", f"recovery_share={args.recovery}", "--out", data,
             "--workers", args.workers, "--no-progress"],
            out / "build.log",
        )  # fmt: skip
    base = [str(data)]
    if args.dart_frames:
        dart = out / "dart"
        if not (dart / "done").exists():
            wall["dart"] = run(
                [BIN / "drive", "collect", "--policy", "expert-plan", "--beta", 0, "--noise",
                 args.noise, "--towns", 8, "--frames", args.dart_frames, "--seed",
                 args.build_seed * 1000 + 7, "--out", dart, "--workers", args.workers,
                 "--no-progress"],
                out / "dart.log",
            )  # fmt: skip
            (dart / "done").write_text("")
        base.append(str(dart))
    models: dict[int, Path] = {}
    for seed in seeds:
        fit_dir = out / f"fit-s{seed}"
        common = [
            "--config",
            "tiny",
            "--arch",
            args.arch,
            "--val-towns",
            args.val_towns,
            "--seed",
            seed,
        ]
        if not (fit_dir / "done").exists():
            wall[f"fit-s{seed}"] = run(
                [BIN / "train", "fit", "--shards", ",".join(base), "--epochs", args.epochs,
                 "--out", fit_dir, "--force", *common],
                out / f"fit-s{seed}.log",
            )  # fmt: skip
            (fit_dir / "done").write_text("")
        ckpt, shards = fit_dir / "last.pt", list(base)
        for r in range(1, args.dagger_rounds + 1):
            on_policy = out / f"dagger-s{seed}-r{r}"
            if not (on_policy / "done").exists():
                wall[f"collect-s{seed}-r{r}"] = run(
                    [BIN / "drive", "collect", "--policy", f"ckpt:{ckpt}", "--beta", args.beta,
                     "--towns", 8, "--frames", args.dagger_frames, "--seed",
                     args.build_seed * 1000 + seed * 10 + r, "--out", on_policy, "--workers",
                     args.workers, "--no-progress"],
                    out / f"collect-s{seed}-r{r}.log",
                )  # fmt: skip
                (on_policy / "done").write_text("")
            shards.append(str(on_policy))
            tuned = out / f"fit-s{seed}-r{r}"
            if not (tuned / "done").exists():
                wall[f"fit-s{seed}-r{r}"] = run(
                    [BIN / "train", "fit", "--shards", ",".join(shards), "--init", ckpt,
                     "--epochs", args.dagger_epochs, "--out", tuned, "--force", *common],
                    out / f"fit-s{seed}-r{r}.log",
                )  # fmt: skip
                (tuned / "done").write_text("")
            ckpt = tuned / "last.pt"
        models[seed] = ckpt

    planners: dict[int, Path] = {}
    for seed in privileged_seeds:
        fit_dir = out / f"{args.privileged_name}-s{seed}"
        if not (fit_dir / "done").exists():
            wall[f"{args.privileged_name}-s{seed}"] = run(
                [BIN / "train", "fit", "--arch", "privileged", "--shards", ",".join(base),
                 "--epochs", args.privileged_epochs, "--val-towns", args.val_towns, "--seed",
                 seed, "--out", fit_dir, "--force", *args.privileged_arg],
                out / f"{args.privileged_name}-s{seed}.log",
            )  # fmt: skip
            (fit_dir / "done").write_text("")
        planners[seed] = fit_dir / "last.pt"

    sets = {}
    for name in args.routes.split(","):
        if name == "dev":
            sets["dev"] = dev_routes(out)
        elif name == "heldout":
            sets["heldout_short"] = ROUTES / "heldout_short.json"
            if args.long:
                sets["heldout_long"] = ROUTES / "heldout_long.json"
        else:
            sys.exit(f"--routes: unknown set {name!r} (dev, heldout)")
    results: dict = {"wall_s": wall, "sets": {}}
    for set_name, routes in sets.items():
        policies = [("expert", "expert", []), ("expert-plan", "expert-plan", ["--no-creep"])]
        policies.append(("constant", "constant", []))
        for seed, ckpt in planners.items():
            policies.append(
                (f"{args.privileged_name}-s{seed} no creep", f"ckpt:{ckpt}", ["--no-creep"])
            )
        for seed, ckpt in models.items():
            policies.append((f"model-s{seed}", f"ckpt:{ckpt}", []))
            policies.append((f"model-s{seed} no creep", f"ckpt:{ckpt}", ["--no-creep"]))
        rows = {}
        for name, policy, extra in policies:
            ev = out / "eval" / set_name / name.replace(" ", "-")
            if not (ev / "summary.json").exists():
                wall[f"eval-{set_name}-{name}"] = run(
                    [BIN / "drive", "eval", "--policy", policy, "--routes", routes, "--out", ev,
                     "--workers", args.workers, "--lateral", args.lateral, *extra],
                    out / f"eval-{set_name}-{name.replace(' ', '-')}.log",
                )  # fmt: skip
            rows[name] = json.loads((ev / "summary.json").read_text())
        results["sets"][set_name] = rows
        print(table(set_name, rows, {"model": seeds, args.privileged_name: privileged_seeds}))
    (out / "check.json").write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")


def table(set_name: str, rows: dict[str, dict], seeds: dict[str, list[int]]) -> str:
    """The markdown table of `rows` (name -> summary.json), then per kind of trained policy
    (`seeds`: name -> its seeds) its DS as a share of the expert's, mean and spread."""
    head = f"| {set_name} | DS | RC | IS | {SHORT} per km | stuck s | creeps |"
    lines = [head, "|" + "---|" * 7]
    for name, s in rows.items():
        per_km = " / ".join(f"{s['per_km'].get(c, 0.0):.2f}" for c in COLUMNS)
        lines.append(
            f"| {name} | {s['ds']:.1f} ± {s['ds_ci']:.1f} | {s['rc']:.1f} | "
            f"{s['is_']:.2f} | {per_km} | {s.get('stuck_s_mean', 0.0):.1f} | "
            f"{s.get('creeps', 0)} |"
        )
    expert = rows["expert"]["ds"]
    for kind, kind_seeds in seeds.items():
        for creep in ("", " no creep"):
            names = [f"{kind}-s{k}{creep}" for k in kind_seeds]
            if not names or any(n not in rows for n in names):
                continue
            ds = [rows[n]["ds"] for n in names]
            ratio = [d / max(expert, 1e-9) for d in ds]
            lines.append(
                f"\n{kind}{creep or ' with creep'}: DS {np.mean(ds):.1f} (seeds "
                f"{', '.join(f'{d:.1f}' for d in ds)}; spread {np.ptp(ds):.1f}), "
                f"{np.mean(ratio):.2f}x the expert's {expert:.1f}"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
