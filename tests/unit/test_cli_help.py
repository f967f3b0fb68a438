"""What the help says is what the commands do and what the docs say (issue #25: `up
--glob` said "replay only", `up --preset` omitted tilts, `semservo teach` could not
average frames, the map gave another default precision than the README)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from semservo import cli
from semservo.config import Settings
from semservo.simulation.world import PRESETS

ROOT = Path(__file__).parents[2]


def help_of(command: str) -> str:
    parser = cli.build_parser()
    action = next(action for action in parser._actions if action.dest == "command")
    return action.choices[command].format_help()


def test_up_names_every_preset_and_its_glob_reaches_a_watched_folder(monkeypatch, tmp_path):
    text = re.sub(r"-\s+", "-", " ".join(help_of("up").split()))  # argparse wraps at hyphens
    for name in PRESETS:
        assert name in text, name
    assert "replay only" not in text and "watched one" in text
    # _source_environment writes the process's environment for the children `up` starts:
    # give it a copy, so that nothing it sets outlives this test (a watched source left
    # set made a later whole-stack test start without frames).
    monkeypatch.setattr(os, "environ", {key: value for key, value in os.environ.items()
                                        if not key.startswith("SEMSERVO_IMAGESERVER__")})
    args = cli.build_parser().parse_args(["up", "--watch-dir", str(tmp_path), "--glob", "*.tif"])
    cli._source_environment(args)
    assert Settings().imageserver.watch_glob == "*.tif" and Settings().imageserver.source == "watch"


def test_teach_averages_frames_and_teaches_tilts_as_the_api_does():
    args = cli.build_parser().parse_args(["teach", "--frames", "4", "--tilts"])
    assert args.frames == 4 and args.tilts


@pytest.mark.parametrize("setting, default", [("__PRECISION", Settings().estimator.precision)])
def test_the_maps_settings_table_gives_the_defaults_the_code_has(setting, default):
    text = (ROOT / "docs" / "architecture.md").read_text()
    row = next(line for line in text.splitlines() if setting in line and line.startswith("|"))
    names = re.findall(r"`(SEMSERVO_\w+|__\w+)`", row.split("|")[1])
    values = [value.strip().strip("`") for value in row.split("|")[2].split(",")]
    assert values[names.index(setting)] == default, row


@pytest.mark.parametrize("arguments, said", [
    (["demo", "--tolerance", "-1"], "--tolerance: must be a finite number over 0, got -1"),
    (["demo", "--offset", "nan", "0"], "--offset: must be a finite number from -100 to 100, got nan"),
    (["demo", "--offset", "500", "0"], "got 500"),
    (["demo", "--frames", "17"], "--frames: must be 1..16, got 17"),
    (["demo", "--speedup", "0"], "--speedup: must be a finite number over 0, got 0"),
    (["up", "--speedup", "0"], "--speedup: must be a finite number over 0"),
    (["up", "--fps", "0"], "--fps: must be a finite number over 0"),
    (["up", "--check", "--frames", "0"], "--frames: must be 1 or more, got 0"),
    (["health", "nosuch"], "no service 'nosuch'; services: fakelab, imageserver"),
    (["calibrate", "--step", "inf"], "--step: must be a finite number over 0, got inf"),
])
def test_a_bad_value_is_refused_before_anything_is_taught_moved_or_started(capsys, arguments, said):
    """The demo taught and jogged before the gateway refused its tolerance, leaving the
    stage displaced; `up --speedup 0` ran at x1 and `--fps 0` at 10 fps without a word;
    `health nosuch` ended in a traceback. Each is now argparse's error, before any step."""
    with pytest.raises(SystemExit) as exit_:
        cli.build_parser().parse_args(arguments)
    assert exit_.value.code == 2
    assert said in " ".join(capsys.readouterr().err.split())


def test_a_bad_setting_is_named_by_its_variable_not_as_a_sample_image(monkeypatch, capsys):
    """A speed-up set to -5 was reported as 'sample image refused' with pydantic's dump,
    naming the stage's rate the user never set."""
    monkeypatch.setattr(os, "environ", {key: value for key, value in os.environ.items()
                                        if not key.startswith("SEMSERVO_")} | {"SEMSERVO_FAKELAB__SPEEDUP": "-5"})
    args = cli.build_parser().parse_args(["up"])
    cli._source_environment(args)
    assert not cli._sample_image_environment("up")
    said = capsys.readouterr().err
    assert "settings refused: SEMSERVO_FAKELAB__SPEEDUP = '-5': Input should be greater than 0" in said
    assert "sample image" not in said and "MAX_RATE" not in said and "errors.pydantic.dev" not in said
