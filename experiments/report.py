"""OUT/REPORT.md of an experiment (experiments/runner.py), written from its steps' JSON files.

Sections: Table III (closed loop, held-out and seen towns: DS with and without the creep, RC,
IS with 95 % intervals, infractions per km) beside the paper's numbers; the paired differences
of DS against "All tasks" per route; Table II (ECA similarity, our three forms and an untrained
model's, with intervals) beside the paper's; the weather swap (Fig. 6); open-loop metrics per
head; data and compute; and which of the paper's claims the numbers support, contradict or
cannot decide. Figures (PNG beside the report): DS per variant, the paired differences, the
infractions per km; and links to the video of each variant's worst held-out route.

Intervals and verdicts: experiments/verdicts.py. Training seeds are a level of their own
(resampled first, then routes or frames within a seed); variants are compared paired per
route; a claim is supported only when its whole 95 % interval is on its side. Every number
comes from a file; none is typed here except the paper's own, quoted from its tables.
"""

from __future__ import annotations

import json
import platform
from pathlib import Path

import numpy as np

from drive.score import TABLE_COLUMNS, Summary, summarise
from experiments import verdicts
from schemas import outputs

# The paper's Table III (CARLA 42 Routes), by our variant names; per-km infractions in the
# order of PAPER_COLUMNS (the paper has no stop-sign column).
PAPER_COLUMNS = ("Ped", "Veh", "Lay", "Red", "OR", "Dev", "TO", "Block")
PAPER_TABLE_III = {
    "none": (59.28, 75.15, 0.81, (0.19, 1.11, 0.21, 0.14, 1.90, 0.02, 1.91, 3.38)),
    "no_multiframe": (84.72, 93.90, 0.89, (0.14, 0.72, 0.09, 0.09, 1.39, 0.00, 1.34, 2.87)),
    "no_detection": (75.93, 88.94, 0.88, (0.18, 1.06, 0.14, 0.09, 1.37, 0.00, 1.36, 3.07)),
    "no_bev": (74.61, 88.11, 0.87, (0.12, 0.69, 0.21, 0.06, 1.84, 0.01, 1.51, 2.54)),
    "no_traffic": (81.51, 94.12, 0.88, (0.11, 0.63, 0.16, 0.16, 1.37, 0.00, 1.39, 3.14)),
    "no_weather": (78.83, 93.36, 0.86, (0.18, 0.97, 0.14, 0.08, 1.42, 0.00, 2.00, 2.68)),
    "full": (86.79, 94.93, 0.91, (0.10, 0.56, 0.11, 0.08, 1.32, 0.00, 1.21, 2.44)),
}
PAPER_TABLE_II = {"detection": 0.6465, "bev": 0.6154, "traffic": 0.2177, "weather": 0.3253}
LABELS = {
    "full": "All tasks",
    "ours": "Ours (All tasks + our additions)",
    "none": "None",
    "no_multiframe": "No Multi-frame LiDAR",
    "no_detection": "No Detection & Prediction",
    "no_bev": "No BEV Map",
    "no_traffic": "No Traffic Rule",
    "no_weather": "No Weather",
}
HEADS = {"detection": "det&pred", "bev": "BEV", "traffic": "traffic", "weather": "weather"}


def _load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _routes(out: Path, name: str, kind: str) -> list[dict]:
    return [
        json.loads(p.read_text())
        for p in sorted((out / "drive" / name / kind / "routes").glob("*.json"))
    ]


def variant_seed_routes(out: Path, preset, kind: str) -> dict[str, dict[int, list[dict]]]:
    """Per variant with any, per seed with any, the route result documents of `kind` ("seen",
    "heldout", "seen_nocreep", "heldout_nocreep"); seen-town drives of the town held out of
    training (the preset's val_town) are left out."""
    rows: dict[str, dict[int, list[dict]]] = {}
    for v in preset.variants:
        for s in preset.seeds:
            docs = [
                d
                for d in _routes(out, f"{v}-s{s}", kind)
                if not (kind.startswith("seen") and d["route"]["town"] == preset.val_town)
            ]
            if docs:
                rows.setdefault(v, {})[s] = docs
    return rows


def variant_routes(out: Path, preset, kind: str) -> dict[str, list[dict]]:
    """Per variant with any, the route result documents of all its seeds pooled."""
    return {
        v: [d for docs in seeds.values() for d in docs]
        for v, seeds in variant_seed_routes(out, preset, kind).items()
    }


def closed_loop(docs: dict[str, list[dict]]) -> dict[str, Summary]:
    """Per variant, drive/score.py's Summary over its pooled routes (per-km rates, counts)."""
    from drive.summary import route_score

    return {v: summarise([route_score(d) for d in ds]) for v, ds in docs.items()}


def route_means(docs: list[dict]) -> dict[str, dict[str, float]]:
    """Per route id, its DS, RC and IS averaged over its repetitions (a failed drive: DS 0)."""
    from drive.score import per_route
    from drive.summary import route_score

    return {
        r["route_id"]: {"ds": r["ds"], "rc": r["rc"], "is": r["is"]}
        for r in per_route([route_score(d) for d in docs])
    }


def seeded(seeds: dict[int, list[dict]], measure: str = "ds") -> dict[int, dict[str, float]]:
    """Per seed, per route id, one measure (route_means)."""
    return {s: {r: m[measure] for r, m in route_means(d).items()} for s, d in seeds.items()}


def interval(seeds: dict[int, list[dict]], measure: str = "ds") -> tuple[float, float, float]:
    """(mean, lo, hi) of a measure over routes and seeds (verdicts.hierarchical)."""
    per = {s: np.array(list(v.values())) for s, v in seeded(seeds, measure).items()}
    return verdicts.hierarchical(per)


def paired(a: dict[int, list[dict]], b: dict[int, list[dict]]):
    """(mean, lo, hi, n routes x seeds, enough) of DS(a) - DS(b), paired per route and seed."""
    diff = verdicts.paired_differences(seeded(a), seeded(b))
    if not diff:
        return None
    n = sum(len(v) for v in diff.values())
    return (*verdicts.hierarchical(diff), n, verdicts.enough(diff))


def paired_against_full(held: dict[str, dict[int, list[dict]]], skip: tuple[str, ...] = ()):
    """(variant, mean, lo, hi, n, enough) of DS(All tasks) - DS(variant) for every variant but
    "full" and `skip` that shares routes and seeds with it (`paired`)."""
    full = held.get("full")
    if full is None:
        return
    for v, seeds in held.items():
        if v == "full" or v in skip:
            continue
        got = paired(full, seeds)
        if got is not None:
            yield (v, *got)


def creeps_per_route(docs: dict[str, list[dict]]) -> dict[str, float]:
    """Per variant, the mean number of creeps (drive.controller.Creep) per route."""
    return {v: sum(d.get("creeps", 0) for d in ds) / len(ds) for v, ds in docs.items()}


def _ci(m: tuple[float, float, float], fmt: str = ".2f") -> str:
    return f"{m[0]:{fmt}} ({m[1]:{fmt}} - {m[2]:{fmt}})"


def _table_iii(out: Path, preset, kind: str, with_paper: bool) -> list[str]:
    seeds = variant_seed_routes(out, preset, kind)
    bare = variant_seed_routes(out, preset, f"{kind}_nocreep")
    pooled = {v: [d for ds in ss.values() for d in ds] for v, ss in seeds.items()}
    rows, creeps = closed_loop(pooled), creeps_per_route(pooled)
    cols = " | ".join(c for _, c in TABLE_COLUMNS)
    lines = [
        f"| variant | routes | seeds | creeps | DS | DS without creep | RC | IS | {cols} |",
        "|---" * (8 + len(TABLE_COLUMNS)) + "|",
    ]
    for v, r in rows.items():
        per = " | ".join(f"{r.per_km[k]:.2f}" for k, _ in TABLE_COLUMNS)
        alone = _ci(interval(bare[v])) if v in bare else "-"
        lines.append(
            f"| {LABELS[v]} | {r.n_routes} | {len(seeds[v])} | {creeps.get(v, 0.0):.2f} | "
            f"{_ci(interval(seeds[v]))} | {alone} | {_ci(interval(seeds[v], 'rc'))} | "
            f"{_ci(interval(seeds[v], 'is'), '.3f')} | {per} |"
        )
        if with_paper and v in PAPER_TABLE_III:
            ds, rc, is_, inf = PAPER_TABLE_III[v]
            paper = dict(zip(PAPER_COLUMNS, inf))
            per = " | ".join(f"*{paper[c]:.2f}*" if c in paper else "-" for _, c in TABLE_COLUMNS)
            lines.append(
                f"| *paper: {LABELS[v]}* | 42 | - | - | *{ds}* | - | *{rc}* | *{is_}* | {per} |"
            )
    return lines


def _paired_table(held: dict[str, dict[int, list[dict]]]) -> list[str]:
    lines = [
        "| variant | routes x seeds | DS(All tasks) - DS(variant) | 95 % interval | verdict |",
        "|---|---|---|---|---|",
    ]
    for v, mean, lo, hi, n, ok in paired_against_full(held):
        lines.append(
            f"| {LABELS[v]} | {n} | {mean:+.2f} | {lo:+.2f} - {hi:+.2f} | "
            f"{verdicts.verdict(lo, hi, ok)} |"
        )
    return lines


def swap_claims(swap: dict) -> list[str]:
    """The weather-swap claims (Fig. 6): the full model's rainy / sunny planned-speed ratio
    below 1 (its whole interval), and its slowdown larger than the no-weather model's (the
    paired block-bootstrap interval of the ratios' difference over the same frames)."""
    from drive.swap import BLOCK_FRAMES

    out = []
    full = next((d for n, d in swap.items() if n.startswith("full-")), None)
    if full is None:
        return out
    s = full["summary"]
    lo, hi = s["speed_ratio_ci95"]
    ok = s["frames"] >= 2 * BLOCK_FRAMES
    # a ratio below 1 is the claim: lo, hi of 1 - ratio above 0
    out.append(
        "- *The full model plans slower in rain than in sun for the same scene* (Fig. 6): "
        f"rainy / sunny planned speed {s['speed_ratio']:.3f} (95 % CI {lo:.3f}-{hi:.3f}): "
        f"{verdicts.verdict(1.0 - hi, 1.0 - lo, ok)}."
    )
    nw = next((d for n, d in swap.items() if n.startswith("no_weather-")), None)
    if nw is not None:
        t = nw["summary"]
        diff = ratio_difference(full, nw)
        if diff is None:
            verdict, text = "undecided (the two swaps saw different frames)", ""
        else:
            est, dlo, dhi = diff
            verdict = verdicts.verdict(dlo, dhi, ok and t["frames"] >= 2 * BLOCK_FRAMES)
            text = f", no-weather minus full {est:+.3f} (95 % CI {dlo:+.3f} - {dhi:+.3f})"
        out.append(
            "- *Without the weather head the rain / sun difference is smaller* (Fig. 6): "
            f"no-weather ratio {t['speed_ratio']:.3f} vs the full model's "
            f"{s['speed_ratio']:.3f}{text}: {verdict}."
        )
    return out


def ratio_difference(a: dict, b: dict) -> tuple[float, float, float] | None:
    """(estimate, lo, hi) of ratio(b) - ratio(a), each rainy / sunny mean planned speed, over
    the same frames resampled in blocks (drive.swap.BLOCK_FRAMES); None if the frames differ."""
    from drive.swap import BLOCK_FRAMES

    fa, fb = a.get("per_frame"), b.get("per_frame")
    if not fa or not fb or fa["time_s"] != fb["time_s"]:
        return None
    sun, rain = a["summary"]["weathers"]
    cols = [
        fa["speed_mps"][sun],
        fa["speed_mps"][rain],
        fb["speed_mps"][sun],
        fb["speed_mps"][rain],
    ]
    units = {0: np.array(cols, dtype=np.float64).T}  # (frames, 4)

    def stat(m: np.ndarray) -> float:
        return m[3] / max(m[2], 1e-9) - m[1] / max(m[0], 1e-9)

    return verdicts.hierarchical(units, stat, block=BLOCK_FRAMES)


def table_ii(analyses: dict[str, dict]) -> dict[str, tuple[float, float, float]]:
    """Per head, (mean, lo, hi) of the centred similarity over frames and seeds (the analyses
    of each full model; verdicts.hierarchical)."""
    out = {}
    heads = next(iter(analyses.values()))["trained"]
    for h in heads:
        per = {
            n: np.array(a["trained_per_frame"][h]["centred"])
            for n, a in analyses.items()
            if a.get("trained_per_frame", {}).get(h, {}).get("centred")
        }
        if per:
            out[h] = verdicts.hierarchical(per)
    return out


def table_ii_claim(analyses: dict[str, dict]) -> str | None:
    """Detection's and BEV's centred similarity above traffic's and weather's: the interval of
    min(det, BEV) - max(traffic, weather) over frames and seeds."""
    order = ("detection", "bev", "traffic", "weather")
    per = {}
    for n, a in analyses.items():
        f = a.get("trained_per_frame", {})
        if all(f.get(h, {}).get("centred") for h in order):
            per[n] = np.stack([np.array(f[h]["centred"]) for h in order], 1)
    if not per:
        return None
    est, lo, hi = verdicts.hierarchical(per, lambda m: min(m[0], m[1]) - max(m[2], m[3]))
    frames = sum(len(v) for v in per.values())
    return (
        "- *Detection and BEV channel weights are closer to planning's than traffic's and "
        f"weather's* (Table II, centred form): min(det, BEV) - max(traffic, weather) {est:+.3f} "
        f"(95 % CI {lo:+.3f} - {hi:+.3f}, {frames} frames of {len(per)} model(s)): "
        f"{verdicts.verdict(lo, hi, verdicts.enough(per))}."
    )


def _claims(held: dict[str, dict[int, list[dict]]], swap: dict, analyses: dict) -> list[str]:
    """The paper's claims, each supported / contradicted / undecided by our numbers (the
    module docstring's rule)."""
    out = []
    full = held.get("full")
    for v, mean, lo, hi, n, ok in paired_against_full(held, skip=("ours",)):
        out.append(
            f"- *All tasks drive better than {LABELS[v]}* (Table III, held-out DS, paired over "
            f"{n} routes x seeds): {verdicts.verdict(lo, hi, ok)} (difference {mean:+.2f}, "
            f"95 % CI {lo:+.2f} - {hi:+.2f})."
        )
    ours = held.get("ours")
    got = paired(ours, full) if ours is not None and full is not None else None
    if got is not None:
        mean, lo, hi, n, ok = got
        out.append(
            "- Not the paper's claim, ours: *our additions drive better than the paper's model* "
            f"(held-out DS, Ours minus All tasks, paired over {n} routes x seeds): "
            f"{verdicts.verdict(lo, hi, ok)} (difference {mean:+.2f}, 95 % CI {lo:+.2f} - {hi:+.2f})."
        )
    out += swap_claims(swap)
    claim = table_ii_claim(analyses) if analyses else None
    if claim:
        out.append(claim)
    return out or ["- nothing to decide (no closed-loop or swap results)"]


def figures(out: Path, held: dict[str, dict[int, list[dict]]], rows: dict) -> list[str]:
    """ds.png, paired.png, infractions.png beside the report; Markdown lines linking them
    (a note instead when matplotlib is not installed)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return ["(figures need matplotlib: `pip install iidsu[curves]`)"]
    names = list(held)
    if not names:
        return []
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for k, v in enumerate(names):
        m, lo, hi = interval(held[v])
        ax.errorbar([k], [m], yerr=[[m - lo], [hi - m]], fmt="o", capsize=4, color="C0")
    ax.set_xticks(range(len(names)), [LABELS[v] for v in names], rotation=20, ha="right")
    ax.set_ylabel("DS (held-out), 95 % CI")
    fig.tight_layout()
    fig.savefig(out / "ds.png", dpi=110)
    plt.close(fig)
    links = ["![DS per variant](ds.png)"]
    others = [v for v in names if v != "full" and "full" in held]
    diffs = [(v, paired(held["full"], held[v])) for v in others]
    diffs = [(v, d) for v, d in diffs if d is not None]
    if diffs:
        fig, ax = plt.subplots(figsize=(7, 3.2))
        for k, (_, (m, lo, hi, _n, _ok)) in enumerate(diffs):
            ax.errorbar([k], [m], yerr=[[m - lo], [hi - m]], fmt="o", capsize=4, color="C1")
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xticks(range(len(diffs)), [LABELS[v] for v, _ in diffs], rotation=20, ha="right")
        ax.set_ylabel("DS(All tasks) - DS(variant)")
        fig.tight_layout()
        fig.savefig(out / "paired.png", dpi=110)
        plt.close(fig)
        links.append("![Paired differences against All tasks](paired.png)")
    fig, ax = plt.subplots(figsize=(8, 3.2))
    width = 0.8 / max(len(rows), 1)
    for k, (v, r) in enumerate(rows.items()):
        xs = np.arange(len(TABLE_COLUMNS)) + k * width
        ax.bar(xs, [r.per_km[c] for c, _ in TABLE_COLUMNS], width, label=LABELS[v])
    ax.set_xticks(np.arange(len(TABLE_COLUMNS)) + 0.4 - width / 2, [c for _, c in TABLE_COLUMNS])
    ax.set_ylabel("per km (held-out)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "infractions.png", dpi=110)
    plt.close(fig)
    links.append("![Infractions per km](infractions.png)")
    return links


def worst_videos(out: Path, held: dict[str, dict[int, list[dict]]]) -> list[str]:
    """Per variant, a link to the video of its worst held-out drive (lowest DS), if recorded."""
    from drive.summary import result_name

    lines = []
    for v, seeds in held.items():
        worst = min(((s, d) for s, docs in seeds.items() for d in docs), key=lambda sd: sd[1]["ds"])
        s, d = worst
        name = result_name(d["route"]["route_id"], d.get("repetition", 0))
        video = Path("drive") / f"{v}-s{s}" / "heldout" / "videos" / f"{name}.mp4"
        what = f"{d['route']['route_id']} (seed {s}): DS {d['ds']:.1f}, ended {d['ended']}"
        if (out / video).is_file():
            lines.append(f"- {LABELS[v]}: [{what}]({video})")
        else:
            lines.append(f"- {LABELS[v]}: {what} (not recorded)")
    return lines


def write(out: Path, preset, preset_name: str, steps) -> Path:
    """Write OUT/REPORT.md (and its PNG figures); its path."""
    from drive.controller import CreepConfig

    creep = CreepConfig()
    held_seeds = variant_seed_routes(out, preset, "heldout")
    held_pooled = {v: [d for ds in ss.values() for d in ds] for v, ss in held_seeds.items()}
    analyses = {
        n: a for s in preset.seeds if (a := _load(out / f"analyze-{(n := f'full-s{s}')}.json"))
    }
    swap = {
        n: d
        for n in (f"full-s{preset.seeds[0]}", f"no_weather-s{preset.seeds[0]}")
        if (d := _load(out / "swap" / n / "swap.json"))
    }
    manifest = _load(out / "data" / "_manifest.json") or {}
    walls = {s.name: (_load(out / "steps" / f"{s.name}.json") or {}).get("wall_s") for s in steps}
    lines = [
        f"# II-DSU experiments: preset `{preset_name}`",
        "",
        "Written by `experiment run` from the JSON files of its steps (experiments/runner.py).",
        f"Closed loop: the paper's Table III layout on our routes; the paper's numbers (CARLA 42 "
        f"Routes, 146k frames, the paper model) are quoted in italics for reference, not as a "
        f"like-for-like comparison at this scale ({preset.frames} frames, the `{preset.config}` "
        f"model, {preset.epochs} epochs, seeds {list(preset.seeds)}).",
        "",
        "Architectures: every row but one is the paper's II-DSU as Sec. III describes it "
        "(`train fit --arch paper`, nothing of ours): *All tasks* is the full model, the other "
        "rows remove heads or LiDAR frames from it, as the paper's ablations do. The row *Ours* "
        "(runs `ours-s*`) is the full model plus our additions (`--arch ours`: lamp maps, a "
        "camera-only traffic head, the speed into the planner, training/lamps.py); the paper "
        "has no such row.",
        "",
        "## Table III, held-out town (`boulevard`, drive/routes/heldout_short.json)",
        "",
        *_table_iii(out, preset, "heldout", with_paper=True),
        "",
        f"## Table III, seen towns (drive/routes/training_towns.json, without `{preset.val_town}`)",
        "",
        *_table_iii(out, preset, "seen", with_paper=False),
        "",
        "DS, RC, IS: mean over seeds of the mean over routes, with its 95 % interval "
        "(experiments/verdicts.py: seeds resampled, then routes within a seed; with one seed "
        "the interval covers routes only). DS without creep: the same model driven with "
        "`--no-creep`, what it does alone. Infractions per km driven, routes and seeds pooled. "
        f"creeps: per route, how often a model that had stood {creep.stuck_s:g} s was pushed "
        f"forward for {creep.duration_s:g} s (TransFuser's creep, drive.controller.Creep; the "
        "paper's baselines drive with it). The seen-town routes come from the towns the model "
        "trained on, in turn from each (OUT/routes/seen.json).",
        "",
        "## Paired differences against All tasks (held-out DS, per route and seed)",
        "",
        *_paired_table(held_seeds),
        "",
        *figures(out, held_seeds, closed_loop(held_pooled)),
        "",
        "Worst held-out drive per variant:",
        "",
        *worst_videos(out, held_seeds),
        "",
        "## Table II: ECA channel weights of each head vs planning's",
        "",
    ]
    if analyses:
        first = next(iter(analyses.values()))
        cis = table_ii(analyses)
        lines += [
            "| | raw | centred (95 % CI) | kernel | untrained: raw | centred | kernel | paper |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for h, v in first["trained"].items():
            u = first["untrained"][h]
            centred = _ci(cis[h], ".4f") if h in cis else f"{v['centred']:.4f}"
            lines.append(
                f"| plan x {HEADS[h]} | {v['raw']:.4f} | {centred} | {v['kernel']:.4f} | "
                f"{u['raw']:.4f} | {u['centred']:.4f} | {u['kernel']:.4f} | "
                f"*{PAPER_TABLE_II[h]}* |"
            )
        lines += [
            "",
            f"{first['frames']} frames, models {', '.join(analyses)} (raw, kernel and the "
            "untrained columns: the first). raw: cosine of the sigmoid weights (unrelated "
            "weights already score ~0.75); centred: across-channel correlation (unrelated 0, the "
            "form comparable with the paper's), mean over seeds and frames with its bootstrap "
            "interval; kernel: cosine of the learnt ECA kernels.",
        ]
    lines += ["", "## Weather swap (Fig. 6)", ""]
    if swap:
        lines += ["| model | frames | sunny m/s | rainy m/s | rainy / sunny | 95 % CI | gap sunny / rainy m |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for n, d in swap.items():
            s = d["summary"]
            a, b = s["weathers"]
            g = s["mean_gap_m"]
            gaps = "n/a" if g[a] is None else f"{g[a]:.2f} / {g[b]:.2f} ({s['frames_with_lead']})"
            lines.append(
                f"| {n} | {s['frames']} | {s['mean_speed_mps'][a]:.3f} | "
                f"{s['mean_speed_mps'][b]:.3f} | {s['speed_ratio']:.3f} | "
                f"{s['speed_ratio_ci95'][0]:.3f}-{s['speed_ratio_ci95'][1]:.3f} | {gaps} |"
            )
        lines += ["", "Figures: " + ", ".join(f"`swap/{n}/swap.png`" for n in swap) + "."]
    lines += ["", "## Open loop on the held-out town (`train eval --split val`)", ""]
    cols = ("ade_m", "cv_ade_m", "fde_m", "det_map", "miou", "iou_lane_marking",
            "red_light_f1", "stop_sign_f1", "weather_accuracy")  # fmt: skip
    lines += ["| run | frames | " + " | ".join(cols) + " |", "|---" * (len(cols) + 2) + "|"]
    from training.evaluate import headline

    for v in preset.variants:
        for s in preset.seeds:
            doc = _load(out / "runs" / f"{v}-s{s}" / "eval.json")
            if doc is None:
                continue
            h = headline(doc)
            vals = " | ".join("-" if h.get(c) is None else f"{h[c]:.3f}" for c in cols)
            lines.append(f"| {v}-s{s} | {doc['frames']} | {vals} |")
    stats = manifest.get("statistics", {})
    lines += [
        "",
        "## Data and compute",
        "",
        f"- data: {stats.get('frames', '?')} frames, {preset.towns} towns "
        f"(`{preset.val_town}` held out of training), episodes of {preset.episode_seconds:g} s;",
        f"- training: `{preset.config}` config, {preset.epochs} epochs, seeds {list(preset.seeds)};",
        f"- machine: {platform.machine()}, {platform.processor() or 'cpu'}, "
        f"device {json.loads((out / 'experiment.json').read_text()).get('device')};",
        "- wall time per step (s): "
        + ", ".join(f"{k} {v:.0f}" for k, v in walls.items() if v is not None)
        + f"; total {sum(v for v in walls.values() if v):.0f} s.",
        "",
        "## What the numbers say about the paper's claims",
        "",
        *_claims(held_seeds, swap, analyses),
        "",
    ]
    return outputs.write_text(out / "REPORT.md", "\n".join(lines))
