"""`experiment run` end to end on the minute preset (real build, fits, evals, SUMO drives, Table
II, weather swap): every table of REPORT.md with its rows, and a resume after an interruption
that skips what was done."""

import json

import pytest

from experiments import cli, runner

pytestmark = pytest.mark.slow  # minutes of building, training or driving

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp") / "minute"
    first = []
    # interrupted after the first fit (as --until stops it), then run again to the end
    assert runner.run("minute", out, until="fit-full-s0", echo=first.append) is None
    second = []
    report = runner.run("minute", out, echo=second.append)
    return out, first, second, report.read_text()


def test_table_iii_rows_are_the_papers_architecture_and_ours_one_extra_row(tmp_path):
    fits = {
        s.name: s.argv for s in runner.steps(runner.PRESETS["small"], tmp_path, "cpu", 1)
        if s.name.startswith("fit-")
    }  # fmt: skip
    assert len(fits) == 8
    for name, argv in fits.items():
        arch = argv[argv.index("--arch") + 1]
        assert arch == ("ours" if name == "fit-ours-s0" else "paper"), name


def test_rerun_skips_the_finished_steps_and_runs_the_rest(experiment):
    out, first, second, _ = experiment
    assert first == ["run  build", "run  fit-full-s0", "stopped after fit-full-s0"]
    assert second[:2] == ["skip build (done)", "skip fit-full-s0 (done)"]
    names = [s.name for s in runner.steps(runner.PRESETS["minute"], out, "cpu", 1)]
    assert second[2:-1] == [f"run  {n}" for n in names[2:]]
    for n in names:
        assert json.loads((out / "steps" / f"{n}.json").read_text())["wall_s"] >= 0


def test_report_has_every_table_with_the_presets_rows(experiment):
    out, _, _, text = experiment
    for section in (
        "## Table III, held-out town",
        "## Table III, seen towns",
        "## Table II:",
        "## Weather swap (Fig. 6)",
        "## Open loop on the held-out town",
        "## Data and compute",
        "## What the numbers say about the paper's claims",
    ):
        assert section in text, section
    held = text.split("## Table III, held-out town")[1].split("## Table III, seen")[0]
    assert "| All tasks | 1 | 1 | 0.00 |" in held and "| No Weather | 1 | 1 | 0.00 |" in held
    assert "| *paper: All tasks* | 42 | - | - | *86.79* |" in held
    assert "DS without creep" in held
    seen = text.split("## Table III, seen towns")[1].split("## Paired differences")[0]
    assert "without `downtown`" in seen  # the minute preset's val_town is not a seen town
    paired = text.split("## Paired differences")[1].split("## Table II:")[0]
    assert "| No Weather | 1 |" in paired and "too few samples" in paired
    assert "![DS per variant](ds.png)" in paired and (out / "ds.png").stat().st_size > 1000
    assert "- All tasks: [" in paired  # the worst route's video, recorded
    seen_routes = json.loads((out / "routes" / "seen.json").read_text())["routes"]
    assert seen_routes and all(r["town"] != "downtown" for r in seen_routes)
    # the paper's architecture in every row of the paper's, ours beside it and named so
    assert "| Ours (All tasks + our additions) | 1 | 1 |" in held
    assert "*paper: Ours" not in held
    assert "The row *Ours*" in text and "Not the paper's claim, ours:" in text
    table2 = text.split("## Table II:")[1].split("## Weather swap")[0]
    for head in ("det&pred", "BEV", "traffic", "weather"):
        assert f"| plan x {head} |" in table2
    swap = text.split("## Weather swap (Fig. 6)")[1].split("## Open loop")[0]
    assert "| full-s0 | 3 |" in swap and "| no_weather-s0 | 3 |" in swap
    open_loop = text.split("## Open loop")[1].split("## Data and compute")[0]
    assert "| full-s0 |" in open_loop and "| no_weather-s0 |" in open_loop
    assert "| ours-s0 |" in open_loop
    assert "undecided (too few samples" in text  # one route and three frames decide nothing


def test_another_preset_in_the_same_directory_and_bad_input_are_one_line(experiment, capsys):
    out, *_ = experiment
    assert cli.main(["run", "--preset", "small", "--out", str(out)]) == 2
    assert "holds an experiment of preset 'minute'" in capsys.readouterr().err
    assert cli.main(["run", "--preset", "huge", "--out", str(out)]) == 2
    assert "unknown preset" in capsys.readouterr().err
    assert cli.main(["run", "--preset", "minute", "--out", str(out), "--until", "nope"]) == 2
    assert "no such step" in capsys.readouterr().err
    assert cli.main(["run", "--preset", "minute", "--out", str(out), "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert listed[0] == "done  build" and all(line.startswith("done") for line in listed)
