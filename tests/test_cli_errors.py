"""Every command's user mistakes through the real CLI: one line, its exit status, nothing
half-written (issue 40). A new failure is one more row of ROWS.

Each row runs `PROG ARGS...` in this process through the command's own `main(argv)` (argparse
included) against small real inputs (`make_inputs`: a real `datagen build`, a real tiny
`train fit`, a route file) and asserts: the exit status; standard error is exactly one line,
`PROG SUBCOMMAND: error: ...` matching the row's pattern, with no traceback; none of the row's
`absent` paths exists afterwards (no half-written output, no directory holding only a
manifest). Stops (Ctrl-C, SIGTERM) need a process of their own: the tests after the table.
"""

from __future__ import annotations

import importlib
import json
import os
import pickle
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAINS = {
    "datagen": "datagen.cli",
    "train": "training.cli",
    "drive": "drive.cli",
    "experiment": "experiments.cli",
}


@dataclass(frozen=True)
class Row:
    """One bad input. `argv` is split as a shell would, after `{name}` placeholders are filled
    from the inputs (`make_inputs`) and `{tmp}`, a fresh directory per row; `says` is a regex
    the one stderr line must match; `absent` paths must not exist afterwards; `setup` names a
    function of SETUPS run first on the row's `{tmp}`."""

    argv: str
    says: str
    code: int = 2
    absent: tuple[str, ...] = ()
    setup: str | None = None


ROWS = {
    # --- datagen ------------------------------------------------------------------------------
    "datagen inspect --rerun unwritable": Row(
        "datagen inspect {d} --rerun /proc/x.rrd", r"^datagen inspect: error: /proc/x\.rrd: "
    ),
    "datagen inspect --out unwritable": Row(
        "datagen inspect {d} --out /proc/x/f.png", r"^datagen inspect: error: /proc/x/f\.png: "
    ),
    "datagen towns --cache unwritable": Row(
        "datagen towns --cache /proc/x", r"^datagen towns: error: --cache /proc/x: "
    ),
    "datagen towns --cache a file": Row(
        "datagen towns --cache {file}", r"^datagen towns: error: --cache .*: not a directory"
    ),
    "datagen build --out unwritable": Row(
        "datagen build --town grid_small --frames 4 --out /proc/x",
        r"^datagen build: error: .*/proc/x",
    ),
    "datagen build --out a file": Row(
        "datagen build --town grid_small --frames 4 --out {file}",
        r"^datagen build: error: .*: not a directory",
    ),
    "datagen build --sensor camera={json}": Row(
        "datagen build --town grid_small --frames 4 --out {tmp}/o --sensor "
        """'camera={"crop_px": 256, "bogus": 1}'""",
        r"^datagen build: error: --sensor .*no field 'bogus'",
        absent=("{tmp}/o",),
    ),
    "datagen build --sensor camera.crop_px=0": Row(
        "datagen build --town grid_small --frames 4 --out {tmp}/o --sensor camera.crop_px=0",
        r"^datagen build: error: --sensor camera.crop_px=0: .*positive",
        absent=("{tmp}/o",),
    ),
    "datagen build --sensor jpeg_quality=500": Row(
        "datagen build --town grid_small --frames 4 --out {tmp}/o --sensor jpeg_quality=500",
        r"^datagen build: error: --sensor jpeg_quality=500: .*1\.\.100",
        absent=("{tmp}/o",),
    ),
    "datagen build --sensor pose_noise_m=-5": Row(
        "datagen build --town grid_small --frames 4 --out {tmp}/o --sensor pose_noise_m=-5",
        r"^datagen build: error: --sensor pose_noise_m=-5: .*0 or more",
        absent=("{tmp}/o",),
    ),
    "datagen build --town boulevard (held out)": Row(
        "datagen build --town boulevard --frames 4 --out {tmp}/o",
        r"^datagen build: error: .*boulevard.*held-out town",
        absent=("{tmp}/o",),
    ),
    "datagen validate --workers 0": Row(
        "datagen validate {d} --workers 0", r"^datagen validate: error: --workers .*0"
    ),
    "datagen validate --workers -3": Row(
        "datagen validate {d} --workers -3", r"^datagen validate: error: --workers .*-3"
    ),
    # --- train --------------------------------------------------------------------------------
    "train fit --out unwritable": Row(
        "train fit --shards {d} --config tiny --out /proc/x", r"^train fit: error: .*/proc/x"
    ),
    "train fit --out a file": Row(
        "train fit --shards {d} --config tiny --out {file}", r"^train fit: error: .*not a directory"
    ),
    "train fit into an existing run": Row(
        "train fit --shards {d} --config tiny --out {tmp}/run",
        r"^train fit: error: .*/run holds a run .*--resume.*--force",
        setup="run_copy",
    ),
    "train fit on an unfinished build": Row(
        "train fit --shards {tmp}/d --config tiny --out {tmp}/o",
        r"^train fit: error: .*build is not finished",
        absent=("{tmp}/o",),
        setup="building",
    ),
    "train fit --val-towns every town": Row(
        "train fit --shards {d} --config tiny --val-towns grid_small --out {tmp}/o",
        r"^train fit: error: --val-towns grid_small holds out every town",
        absent=("{tmp}/o",),
    ),
    "train fit --resume on junk": Row(
        "train fit --resume --out {tmp}/r",
        r"^train fit: error: .*last\.pt: not a checkpoint written by `train fit`$",
        setup="junk_run",
    ),
    "train eval --out unwritable": Row(
        "train eval --ckpt {ckpt} --shards {d} --workers 0 --out /proc/x/e.json",
        r"^train eval: error: .*/proc/x/e\.json",
    ),
    "train eval on junk": Row(
        "train eval --ckpt {junk} --shards {d}",
        r"^train eval: error: .*junk\.pt: not a checkpoint written by `train fit`$",
    ),
    "train eval on other sensors": Row(
        "train eval --ckpt {ckpt} --shards {dcam} --workers 0 --out {tmp}/e.json",
        r"^train eval: error: .*other sensors.*camera",
        absent=("{tmp}/e.json",),
    ),
    "train eval on a foreign pickle": Row(
        "train eval --ckpt {foreign} --shards {d}",
        r"^train eval: error: .*foreign\.pt: not a checkpoint written by `train fit`$",
    ),
    "train analyze --out unwritable": Row(
        "train analyze --ckpt {ckpt} --shards {d} --frames 4 --out /proc/x/a.json",
        r"^train analyze: error: .*/proc/x/a\.json",
    ),
    "train analyze on junk": Row(
        "train analyze --ckpt {junk}",
        r"^train analyze: error: .*junk\.pt: not a checkpoint written by `train fit`$",
    ),
    "train show on junk": Row(
        "train show --ckpt {junk} --shards {d}",
        r"^train show: error: .*junk\.pt: not a checkpoint written by `train fit`$",
    ),
    "train show on other sensors": Row(
        "train show --ckpt {ckpt} --shards {dcam} --out {tmp}/s.png",
        r"^train show: error: .*other sensors.*camera",
        absent=("{tmp}/s.png",),
    ),
    "train curves --run a checkpoint": Row(
        "train curves --run {ckpt}", r"^train curves: error: .*last\.pt: not a run directory"
    ),
    "train curves --out not a PNG": Row(
        "train curves --run {run} --out {tmp}/c.txt",
        r"^train curves: error: .*c\.txt: .*\.png",
        absent=("{tmp}/c.txt",),
    ),
    "train curves on empty logs": Row(
        "train curves --run {tmp}/r",
        r"^train curves: error: .*/r: its logs are empty",
        setup="empty_run",
    ),
    # --- drive --------------------------------------------------------------------------------
    "drive routes --out unwritable": Row(
        "drive routes --town grid_small --short 1 --out /proc/x/r.json",
        r"^drive routes: error: .*/proc/x/r\.json",
    ),
    "drive eval --out unwritable": Row(
        "drive eval --policy constant --routes {routes} --out /proc/x --max-sim-s 1",
        r"^drive eval: error: .*/proc/x",
    ),
    "drive eval --out a file": Row(
        "drive eval --policy constant --routes {routes} --out {file} --max-sim-s 1",
        r"^drive eval: error: .*not a directory",
    ),
    "drive eval unknown edge": Row(
        "drive eval --policy constant --routes {badroutes} --out {tmp}/e --max-sim-s 1",
        r"^drive eval: error: route grid_small-short-00: edge 'nosuchedge' is not in",
        absent=("{tmp}/e",),
    ),
    "drive eval --limit -3": Row(
        "drive eval --policy constant --routes {routes} --out {tmp}/e --limit -3",
        r"^drive eval: error: --limit",
        absent=("{tmp}/e",),
    ),
    "drive eval --limit 0": Row(
        "drive eval --policy constant --routes {routes} --out {tmp}/e --limit 0",
        r"^drive eval: error: --limit",
        absent=("{tmp}/e",),
    ),
    "drive eval on a foreign pickle": Row(
        "drive eval --policy ckpt:{foreign} --routes {routes} --out {tmp}/e",
        r"^drive eval: error: .*foreign\.pt: not a checkpoint written by `train fit`$",
        absent=("{tmp}/e",),
    ),
    "drive swap --out unwritable": Row(
        "drive swap --policy ckpt:{ckpt} --town grid_small --frames 1 --out /proc/x",
        r"^drive swap: error: .*/proc/x",
    ),
    "drive swap --net not XML": Row(
        "drive swap --policy ckpt:{ckpt} --net {file} --out {tmp}/s",
        r"^drive swap: error: .*not a SUMO network",
        absent=("{tmp}/s",),
    ),
    "drive swap --net missing": Row(
        "drive swap --policy ckpt:{ckpt} --net {tmp}/nothing.net.xml --out {tmp}/s",
        r"^drive swap: error: .*nothing\.net\.xml: no such file",
        absent=("{tmp}/s",),
    ),
    "drive swap --net a route file": Row(
        "drive swap --policy ckpt:{ckpt} --net {routes} --out {tmp}/s",
        r"^drive swap: error: .*not a SUMO network",
        absent=("{tmp}/s",),
    ),
    "drive swap on junk": Row(
        "drive swap --policy ckpt:{junk} --town grid_small --out {tmp}/s",
        r"^drive swap: error: .*junk\.pt: not a checkpoint written by `train fit`$",
        absent=("{tmp}/s",),
    ),
    # --- experiment ---------------------------------------------------------------------------
    "experiment run --out unwritable": Row(
        "experiment run --out /proc/x", r"^experiment run: error: .*/proc/x"
    ),
    "experiment run --out a file": Row(
        "experiment run --out {file}", r"^experiment run: error: .*not a directory"
    ),
    "experiment run --until unknown": Row(
        "experiment run --preset minute --out {tmp}/x --until nosuchstep",
        r"^experiment run: error: --until 'nosuchstep': no such step",
        absent=("{tmp}/x",),
    ),
    "experiment run --list on another preset": Row(
        "experiment run --preset small --out {tmp}/x --list",
        r"^experiment run: error: .*/x holds an experiment of preset 'minute'",
        setup="minute_experiment",
    ),
}


# --- inputs -----------------------------------------------------------------------------------


def run_main(argv: list[str]) -> int:
    """`PROG ARGS...` through PROG's own main (argparse's exit included) -> exit status."""
    main = importlib.import_module(MAINS[argv[0]]).main
    try:
        return int(main(argv[1:]) or 0)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1


def make_inputs(root: Path) -> dict[str, str]:
    """Real small inputs under `root`: d (a 24-frame build of one town), dcam (8 frames with a
    128 px camera crop), run and ckpt (a 1-epoch tiny fit on d), junk (random bytes named
    .pt), foreign (a pickle that is no checkpoint), file (a text file), routes (one short
    routes) and badroutes (with an unknown edge)."""
    root.mkdir(parents=True, exist_ok=True)
    paths = {k: str(root / v) for k, v in (
        ("d", "d"), ("dcam", "dcam"), ("run", "run"), ("junk", "junk.pt"), ("file", "notes.txt"),
        ("routes", "routes.json"), ("badroutes", "bad_routes.json"), ("foreign", "foreign.pt"),
    )}  # fmt: skip
    paths["ckpt"] = str(root / "run" / "last.pt")
    build = ["datagen", "build", "--town", "grid_small", "--workers", "1", "--no-progress"]
    steps = [
        build + ["--frames", "24", "--out", paths["d"]],
        build + ["--frames", "8", "--episode-seconds", "4", "--out", paths["dcam"]]
        + ["--sensor", "camera.crop_px=128"],
        ["train", "fit", "--shards", paths["d"], "--config", "tiny", "--epochs", "1"]
        + ["--workers", "0", "--out", paths["run"]],
        ["drive", "routes", "--town", "grid_small", "--short", "2", "--out", paths["routes"]],
    ]  # fmt: skip
    for argv in steps:
        assert run_main(argv) == 0, argv
    Path(paths["junk"]).write_bytes(os.urandom(4096))
    Path(paths["foreign"]).write_bytes(pickle.dumps({"model": Path("x")}))  # not torch's
    Path(paths["file"]).write_text("not a directory, a network or a checkpoint\n")
    doc = json.loads(Path(paths["routes"]).read_text())
    doc["routes"][0]["edges"][0] = "nosuchedge"
    Path(paths["badroutes"]).write_text(json.dumps(doc))
    return paths


def _run_copy(tmp: Path, inputs: dict) -> None:
    shutil.copytree(inputs["run"], tmp / "run")


def _building(tmp: Path, inputs: dict) -> None:
    shutil.copytree(inputs["d"], tmp / "d")
    manifest = tmp / "d" / "_manifest.json"
    doc = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({**doc, "status": "building"}))


def _junk_run(tmp: Path, inputs: dict) -> None:
    (tmp / "r").mkdir()
    shutil.copy(inputs["junk"], tmp / "r" / "last.pt")


def _empty_run(tmp: Path, inputs: dict) -> None:
    (tmp / "r").mkdir()
    for name in ("metrics.jsonl", "steps.jsonl"):  # what a fit stopped in its first steps leaves
        (tmp / "r" / name).write_text("")


def _minute_experiment(tmp: Path, inputs: dict) -> None:
    from dataclasses import asdict

    from experiments.runner import PRESETS

    (tmp / "x").mkdir()
    config = json.loads(json.dumps(asdict(PRESETS["minute"])))
    meta = {"preset": "minute", "config": config, "device": "cpu", "nproc": 1}
    (tmp / "x" / "experiment.json").write_text(json.dumps(meta))


SETUPS = {
    "run_copy": _run_copy,
    "building": _building,
    "junk_run": _junk_run,
    "empty_run": _empty_run,
    "minute_experiment": _minute_experiment,
}


def prepare(row: Row, inputs: dict, tmp: Path) -> tuple[list[str], list[Path]]:
    """The row's argv and absent paths, its setup done in `tmp`."""
    tmp.mkdir(parents=True, exist_ok=True)
    if row.setup:
        SETUPS[row.setup](tmp, inputs)
    values = {**inputs, "tmp": str(tmp)}
    fill = lambda s: re.sub(r"\{(\w+)\}", lambda m: values[m.group(1)], s)  # noqa: E731
    return shlex.split(fill(row.argv)), [Path(fill(a)) for a in row.absent]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, str]:
    return make_inputs(tmp_path_factory.mktemp("inputs"))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(ROWS))
def test_bad_input_gives_one_line_its_status_and_nothing_half_written(
    name, inputs, tmp_path, capsys
):
    row = ROWS[name]
    argv, absent = prepare(row, inputs, tmp_path / "case")
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:  # each would be lines on stderr
        warnings.simplefilter("always")
        status = run_main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert status == row.code, err
    assert [str(w.message) for w in caught] == []
    assert len(lines) == 1 and "Traceback" not in err, err
    assert re.search(row.says, lines[0]), lines[0]
    assert [p for p in absent if p.exists()] == []


# --- help -------------------------------------------------------------------------------------


def _parsers():
    """(prog, subcommand, parser) of every subcommand of the four commands."""
    import argparse

    from schemas import cli

    for prog, module in MAINS.items():
        m = importlib.import_module(module)
        commands = m.commands() if hasattr(m, "commands") else m.COMMANDS
        top = cli.parser(prog, "", commands)
        sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
        for name, parser in sub.choices.items():
            yield prog, name, parser


def test_every_subcommand_and_flag_has_help():
    from schemas import cli

    seen = 0
    for prog, name, parser in _parsers():
        assert parser.description and "\n" not in parser.description, (prog, name)
        for action in parser._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"{prog} {name} {action.option_strings[0]}: no help"
                text = cli.HelpFormatter(prog)._get_help_string(action)
                # a default is stated unless the flag is a switch or optional (None: "off")
                if action.default not in (None, False, []):
                    assert "default" in text.lower(), f"{prog} {name} {action.option_strings[0]}"
                seen += 1
    assert seen > 80


def test_experiment_run_help_names_the_default_preset_and_the_steps(capsys):
    assert run_main(["experiment", "run", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())  # as wrapped to any terminal's width
    assert "(default: small)" in out
    assert all(s in out for s in ("build", "fit-full-s0", "drive-heldout-none-s0", "analyze"))


# --- stops ------------------------------------------------------------------------------------


def _spawn(argv: list[str], tmp: Path) -> tuple[subprocess.Popen, Path]:
    """`python -m MODULE ARGS...` in a session of its own (a terminal's foreground job: SIGINT
    not ignored, whatever the test runner inherited), stderr to a file."""
    err = tmp / "stderr.txt"
    proc = subprocess.Popen(
        [sys.executable, "-m", MAINS[argv[0]], *argv[1:]],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=err.open("w"),
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    return proc, err


def _wait_for(check, proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert proc.poll() is None, "exited before the stop"
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.2)


def _stopped(proc: subprocess.Popen, err: Path) -> tuple[int, str]:
    """Exit status and the last stderr line (progress bars may precede it), no traceback."""
    status = proc.wait(timeout=120)
    text = err.read_text()
    assert "Traceback" not in text, text
    return status, text.replace("\r", "\n").strip().splitlines()[-1]


@pytest.mark.slow
def test_ctrl_c_in_drive_eval_stops_in_one_line_with_130(inputs, tmp_path):
    out = tmp_path / "e"
    argv = ["drive", "eval", "--policy", "expert", "--routes", inputs["routes"], "--out", str(out)]
    proc, err = _spawn(argv, tmp_path)
    _wait_for(lambda: "drive expert" in err.read_text(), proc)  # the route is being driven
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    status, last = _stopped(proc, err)
    assert (status, last) == (130, "drive eval: interrupted")
    assert not (out / "summary.json").exists()  # no summary of routes never driven
    assert list(out.rglob(".*partial*")) == []


@pytest.mark.slow
def test_sigterm_in_train_fit_stops_with_143_and_the_resume_hint(inputs, tmp_path):
    out = tmp_path / "run"
    argv = ["train", "fit", "--shards", inputs["d"], "--config", "tiny", "--epochs", "100"]
    proc, err = _spawn(argv + ["--workers", "0", "--out", str(out)], tmp_path)
    _wait_for(lambda: (out / "last.pt").exists(), proc)  # an epoch is done
    proc.send_signal(signal.SIGTERM)  # the process alone, as `timeout` or a scheduler does
    status, last = _stopped(proc, err)
    assert status == 143
    assert last == f"train fit: stopped (SIGTERM); run it again with --resume (and without " \
        f"--force) to continue from {out / 'last.pt'}"  # fmt: skip
    assert [p.name for p in out.glob(".*partial*")] == []
    assert run_main(["train", "fit", "--resume", "--epochs", "1", "--out", str(out)]) == 2


@pytest.mark.slow
def test_sigterm_in_experiment_run_stops_its_step_then_itself_with_143(tmp_path):
    out = tmp_path / "x"
    proc, err = _spawn(["experiment", "run", "--preset", "minute", "--out", str(out)], tmp_path)
    _wait_for((out / "data" / "_manifest.json").exists, proc)  # the build step is building
    proc.send_signal(signal.SIGTERM)
    status, last = _stopped(proc, err)
    assert (status, last) == (
        143,
        "experiment run: stopped (SIGTERM); run the same command again to resume",
    )
    log = (out / "logs" / "build.log").read_text()
    assert "datagen build: stopped (SIGTERM) with" in log  # the step stopped cleanly
    assert not (out / "steps" / "build.json").exists()
