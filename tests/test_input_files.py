"""Config and scenario files that cannot be used: one clear error naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.config import load_config
from common.errors import ConfigError, FileFormatError
from common.scenario import read_scenario


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ([1, 2], 'a list of "robots"'),
        ({"world": "bshape", "robots": "r0"}, 'a list of "robots"'),
        ({"robots": []}, "no 'world' given"),
        ({"world": "bshape", "robots": [{"id": "r0"}]}, "no 'start_pose' given"),
        # each of these had ended in a traceback, or every command NaN
        ({"world": "b", "robots": [], "seed": 1e300}, "seed must be an integer"),
        ({"world": "b", "robots": [], "seed": -1}, "seed must be an integer"),
        ({"world": "b", "robots": [{"id": "r0", "start_pose": [1e300, 0, 0]}]}, "beyond"),
        (
            {
                "world": "b",
                "robots": [
                    {"id": "r0", "start_pose": [0, 0, 0], "tour": [[1, 1], [float("inf"), 0]]}
                ],
            },
            "tour beyond",
        ),
    ],
)
def test_a_bad_scenario_names_what_is_wrong(tmp_path: Path, doc: object, match: str) -> None:
    path = tmp_path / "s.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match=match) as err:
        read_scenario(path)
    assert str(path) in str(err.value)


def test_a_scenario_nested_too_deep_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text("[" * 100_000)
    with pytest.raises(FileFormatError, match="nested too deep|invalid scenario"):
        read_scenario(path)
    path.write_text('{"world": "b", "robots": [], "seed": 1e400}')  # json: inf
    with pytest.raises(FileFormatError, match="seed must be an integer"):
        read_scenario(path)


def test_a_folder_given_for_a_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match="cannot read the scenario"):
        read_scenario(tmp_path)
    with pytest.raises(ConfigError, match="cannot read the config file"):
        load_config(tmp_path)
    binary = tmp_path / "c.toml"
    binary.write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(ConfigError, match=str(binary)):
        load_config(binary)


def test_a_segment_must_be_finite_and_in_order() -> None:
    """`--segment nan:` or `20:10` had replayed 0 scans and exited 0."""
    from collabslam.cli import _segment

    assert _segment("1:2.5") == (1.0, 2.5) and _segment(":5") == (None, 5.0)
    for bad in ("nan:", "inf:", "5:3", "4:4", "1-2", "a:b"):
        with pytest.raises(ConfigError, match="--segment"):
            _segment(bad)


def test_an_unusable_out_folder_is_refused_at_start(tmp_path: Path) -> None:
    """Found only at shutdown, it had lost a whole mission's outputs to a traceback."""
    import argparse

    from collabslam.cli_options import load_cfg

    (tmp_path / "afile").write_text("")
    args = argparse.Namespace(config=None, set=[], out=str(tmp_path / "afile" / "sub"))
    with pytest.raises(ConfigError, match="--out .*not a writable folder"):
        load_cfg(args)
    args.out = str(tmp_path / "new" / "run")
    assert load_cfg(args).fleet == "default" and (tmp_path / "new" / "run").is_dir()


def test_json_and_sim_time_arguments_are_checked_at_start(tmp_path: Path) -> None:
    """`--json out/b2` (no .json): the benchmark's folder beside it took its name, and
    its numbers could not be written after the whole run; `--max-sim-time nan` had run
    with no limit."""
    import argparse

    from collabslam.cli import main
    from collabslam.cli_options import load_cfg

    (tmp_path / "dir.json").mkdir()
    for bad in ("b2", "dir.json"):
        args = argparse.Namespace(config=None, set=[], json=str(tmp_path / bad))
        with pytest.raises(ConfigError, match="--json .*ending in .json"):
            load_cfg(args)
    args = argparse.Namespace(config=None, set=[], json=str(tmp_path / "b.json"))
    assert load_cfg(args).fleet == "default"
    for limit in (float("nan"), -5.0, 0.0):
        args = argparse.Namespace(config=None, set=[], max_sim_time=limit)
        with pytest.raises(ConfigError, match="--max-sim-time"):
            load_cfg(args)
    assert main(["eval", "relations", "t.tum", "r.relations", "--json", str(tmp_path)]) == 1
    (tmp_path / "afile").write_text("")
    args = argparse.Namespace(config=None, set=[], json=str(tmp_path / "afile" / "b.json"))
    with pytest.raises(ConfigError, match="--json's folder .*not a writable folder"):
        load_cfg(args)
