"""schemas/cli.py (the runner of the four commands) and schemas/outputs.py (checked, atomic
outputs) on their own; the commands themselves are in tests/test_cli_errors.py."""

from __future__ import annotations

import os
import signal

import pytest

from schemas import cli, outputs
from schemas.errors import Stopped, UserError


def _command(run, resume=None) -> cli.Command:
    return cli.Command("go", "one line", lambda p: p.add_argument("--n", type=int), run, resume)


@pytest.mark.parametrize(
    "raised, status, line",
    [
        (UserError("bad --n\n(details)"), 2, "prog go: error: bad --n (details)"),
        (KeyboardInterrupt(), 130, "prog go: interrupted; again to resume"),
        (
            Stopped("stopped with 3 of 9 done", sigterm=True),
            143,
            "prog go: stopped with 3 of 9 done",
        ),
    ],
)
def test_runner_turns_errors_and_stops_into_one_line_and_a_status(raised, status, line, capsys):
    def run(args):
        raise raised

    command = _command(run, resume=lambda args: "again to resume")
    assert cli.main("prog", "doc", [command], ["go"]) == status
    assert capsys.readouterr().err.splitlines() == [line]


def test_sigterm_stops_with_143_and_the_handler_is_restored(capsys):
    before = signal.getsignal(signal.SIGTERM)

    def run(args):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not stop the command")

    assert cli.main("prog", "doc", [_command(run, resume=lambda a: 1 / 0)], ["go"]) == 143
    assert capsys.readouterr().err.splitlines() == ["prog go: stopped (SIGTERM)"]  # hint failed
    assert signal.getsignal(signal.SIGTERM) == before


def test_usage_mistakes_are_one_line_with_status_2(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main("prog", "doc", [_command(lambda a: 0)], ["go", "--n", "x"])
    assert e.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["prog go: error: argument --n: invalid int value: 'x' (see --help)"]


def test_a_help_of_more_than_one_line_is_refused():
    with pytest.raises(ValueError, match="one line"):
        cli.parser("prog", "doc", [cli.Command("go", "two\nlines", lambda p: None, lambda a: 0)])


def test_outputs_of_the_wrong_kind_are_refused_and_nothing_is_created(tmp_path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "dir").mkdir()
    with pytest.raises(UserError, match="not a directory"):
        outputs.check_dir(tmp_path / "file")
    with pytest.raises(UserError, match="file is not a directory"):
        outputs.check_dir(tmp_path / "file" / "sub" / "run")
    with pytest.raises(UserError, match="is a directory, expected a file"):
        outputs.check_file(tmp_path / "dir")
    with pytest.raises(UserError, match=r"must end in \.png"):
        outputs.check_file(tmp_path / "new" / "c.txt", suffixes=(".png",))
    with pytest.raises(UserError, match="cannot write in /proc"):
        outputs.check_dir("/proc/x/y")
    assert outputs.check_dir(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "file"]  # nothing made


def test_an_atomic_write_stopped_midway_leaves_the_old_file_whole(tmp_path):
    path = tmp_path / "out" / "result.json"
    outputs.write_json(path, {"v": 1})
    with pytest.raises(KeyboardInterrupt), outputs.atomic(path) as tmp:
        tmp.write_text('{"v": 2, "half')
        raise KeyboardInterrupt
    assert path.read_text() == '{\n "v": 1\n}\n'
    assert sorted(p.name for p in path.parent.iterdir()) == ["result.json"]
