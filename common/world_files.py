"""Where a world's map_server YAML is: a shipped world's name or a path.

The simulator's worlds ship as data under `simulation/worlds/`; the base station and a
scenario's georeferenced tours read their YAML too (the WGS84 origin), so the names
are resolved here, without the simulator's code.
"""

from __future__ import annotations

from pathlib import Path

from common.errors import ConfigError, FileFormatError
from common.geodesy import GeoOrigin

__all__ = ["SHIPPED_WORLDS", "SHIPPED_WORLDS_DIR", "resolve_world", "world_wgs84_origin"]

SHIPPED_WORLDS_DIR = Path(__file__).resolve().parents[1] / "simulation" / "worlds"
SHIPPED_WORLDS = ("bshape", "rooms15", "floor30x25")


def resolve_world(name_or_path: str | Path) -> Path:
    """Path of a world's map_server YAML: a shipped name (see `SHIPPED_WORLDS`) or a
    path to an existing .yaml / .yml file.

    Raises ConfigError for an unknown name or a missing file, FileFormatError for
    an existing file that is not a YAML.
    """
    text = str(name_or_path)
    shipped = ", ".join(SHIPPED_WORLDS)
    if text in SHIPPED_WORLDS:
        path = SHIPPED_WORLDS_DIR / f"{text}.yaml"
        if not path.is_file():
            raise ConfigError(
                f"shipped world {text!r} is missing its file {path}; regenerate it with "
                "`python -m simulation.world_generator --out simulation/worlds`"
            )
        return path
    path = Path(text).expanduser()
    if path.is_file():
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise FileFormatError(
                f"world {text!r}: expected a map_server .yaml file or a shipped world ({shipped})"
            )
        return path
    raise ConfigError(f"unknown world {text!r}: not a shipped world ({shipped}) and no such file")


def world_wgs84_origin(name_or_path: str | Path) -> GeoOrigin | None:
    """The ``wgs84_origin`` of a world's map YAML (None: it has none); errors as
    `resolve_world`, or FileFormatError for a YAML that cannot be read."""
    from common.map_io import read_wgs84_origin  # local: map_io is heavier

    return read_wgs84_origin(resolve_world(name_or_path))
