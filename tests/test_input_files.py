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
    ],
)
def test_a_bad_scenario_names_what_is_wrong(tmp_path: Path, doc: object, match: str) -> None:
    path = tmp_path / "s.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match=match) as err:
        read_scenario(path)
    assert str(path) in str(err.value)


def test_a_folder_given_for_a_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match="cannot read the scenario"):
        read_scenario(tmp_path)
    with pytest.raises(ConfigError, match="cannot read the config file"):
        load_config(tmp_path)
    binary = tmp_path / "c.toml"
    binary.write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(ConfigError, match=str(binary)):
        load_config(binary)
