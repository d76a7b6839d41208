"""2-D occupancy maps in the ROS map_server format (YAML + PGM/PNG image).

`GridMap.data[iy, ix]` holds cell (ix, iy); row 0 is the LOWEST y (the image
file is stored the other way round: its first row is the top). Cell values
follow nav_msgs/OccupancyGrid: -1 unknown, 0 free, 100 occupied, 1..99 a
probability in percent (only produced by `mode: scale` maps, for pixels between their
thresholds: kept within FREE_MAX + 1..OCCUPIED_MIN - 1, unknown to the masks).

`origin` is the (x, y, yaw) of the lower-left corner of cell (0, 0) in the map
frame (metres, rad); collabslam only supports yaw == 0.

Optional `wgs84_origin: [lat_deg, lon_deg, alt_m]` (a collabslam key that
map_server ignores) is the WGS84 point at the map frame's (0, 0, 0) when the map
frame is an ENU frame (GPS on, seed 000 §III); maps without it read as before.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError, FileFormatError
from common.geodesy import GeoOrigin

logger = logging.getLogger(__name__)

UNKNOWN = -1
FREE = 0
OCCUPIED = 100
# Cell-value classes, matching the thresholds write_map puts in its YAML
# (free_thresh 0.196, occupied_thresh 0.65).
FREE_MAX = 19
OCCUPIED_MIN = 65
# exploration's free cells: seen free more often than not (frontiers, planning)
EXPLORATION_FREE_THRESH = 0.49

# Pixel values written by write_map (map_saver convention).
PIXEL_FREE = 254
PIXEL_OCCUPIED = 0
PIXEL_UNKNOWN = 205

_REQUIRED_KEYS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")
_PGM_EXTENSIONS = (".pgm", ".pnm")
# Limits on what a map file may claim: a 57-byte PNG claiming 10^6 x 10^6 pixels, a
# resolution of 1e-320 m and an origin of 1e300 m had each ended in a traceback.
MAX_MAP_CELLS = 10**8  # 10,000 x 10,000 (500 m square at 0.05 m)
MAP_RESOLUTION_RANGE_M = (1e-3, 100.0)
MAX_ORIGIN_M = 1e7


@dataclass(eq=False)
class GridMap:
    """An occupancy grid in the map frame; see the module docstring for conventions."""

    data: NDArray[np.int8]  # (H, W), data[iy, ix]
    resolution: float  # m per cell
    origin: tuple[float, float, float]  # (x, y, yaw) of the lower-left corner of cell (0, 0)
    wgs84_origin: GeoOrigin | None = None  # WGS84 point at map (0, 0, 0) if map is ENU

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 2:
            raise CollabSlamError(f"GridMap.data must be 2-D (H, W), got shape {data.shape}")
        if data.dtype != np.int8:
            if not np.issubdtype(data.dtype, np.integer):
                raise CollabSlamError(f"GridMap.data must be int8, got {data.dtype}")
            if data.size and (data.min() < -1 or data.max() > 100):
                raise CollabSlamError("GridMap.data values must lie in [-1, 100]")
            data = data.astype(np.int8)
        self.data = data
        self.resolution = float(self.resolution)
        if not (math.isfinite(self.resolution) and self.resolution > 0.0):
            raise CollabSlamError(f"GridMap.resolution must be > 0, got {self.resolution}")
        origin = tuple(float(v) for v in self.origin)
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise CollabSlamError(f"GridMap.origin must be 3 finite numbers, got {self.origin}")
        if origin[2] != 0.0:
            raise CollabSlamError(f"GridMap.origin yaw must be 0, got {origin[2]}")
        self.origin = (origin[0], origin[1], origin[2])

    @property
    def width(self) -> int:
        """Number of cells along x."""
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        """Number of cells along y."""
        return int(self.data.shape[0])

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the covered area in metres."""
        x0, y0, _ = self.origin
        return (
            x0,
            x0 + self.width * self.resolution,
            y0,
            y0 + self.height * self.resolution,
        )

    def world_to_cell(self, xy: ArrayLike) -> NDArray[np.int64]:
        """(N, 2) map-frame points (m) -> (N, 2) cell indices [ix, iy] (not clipped)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        o = np.array(self.origin[:2])
        return np.floor((p - o) / self.resolution).astype(np.int64)

    def cell_to_world(self, cells: ArrayLike) -> NDArray[np.float64]:
        """(N, 2) cell indices [ix, iy] -> (N, 2) map-frame cell centres (m)."""
        c = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
        return (c + 0.5) * self.resolution + np.array(self.origin[:2])

    def cell_centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """x of the cell centres of each column (W,) and y of each row (H,), in metres."""
        xs = self.origin[0] + (np.arange(self.width) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(self.height) + 0.5) * self.resolution
        return xs, ys

    def in_bounds(self, cells: ArrayLike) -> NDArray[np.bool_]:
        """(N,) mask of the (N, 2) cell indices [ix, iy] that lie inside the grid."""
        c = np.asarray(cells).reshape(-1, 2)
        return (c[:, 0] >= 0) & (c[:, 0] < self.width) & (c[:, 1] >= 0) & (c[:, 1] < self.height)

    def sample(self, xy: ArrayLike, outside: int = UNKNOWN) -> NDArray[np.int8]:
        """(N,) values of the cells containing the (N, 2) points; `outside` beyond the grid."""
        cells = self.world_to_cell(xy)
        inside = self.in_bounds(cells)
        out = np.full(len(cells), outside, dtype=np.int8)
        out[inside] = self.data[cells[inside, 1], cells[inside, 0]]
        return out

    def free_mask(self) -> NDArray[np.bool_]:
        """(H, W) cells that are free (0 <= value <= FREE_MAX)."""
        return (self.data >= 0) & (self.data <= FREE_MAX)

    def occupied_mask(self) -> NDArray[np.bool_]:
        """(H, W) cells that are occupied (value >= OCCUPIED_MIN)."""
        return self.data >= OCCUPIED_MIN

    def known_mask(self) -> NDArray[np.bool_]:
        """(H, W) cells that are free or occupied."""
        return self.free_mask() | self.occupied_mask()


# --------------------------------------------------------------------------- YAML


def _parse_scalar(text: str) -> str | float | int:
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def _strip_comment(line: str) -> str:
    quote = ""
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


def _parse_flat_yaml(text: str, path: Path) -> dict[str, object]:
    """Parse the flat `key: value` / `key: [a, b]` / block-list YAML of map_server files."""
    out: dict[str, object] = {}
    pending_list: list[object] | None = None  # the block list being filled by '- ' lines
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = _strip_comment(raw).rstrip()
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        stripped = line.strip()
        if stripped.startswith("- ") or stripped == "-":
            if pending_list is None:
                raise FileFormatError(f"{path}:{lineno}: list item outside a list: {raw!r}")
            pending_list.append(_parse_scalar(stripped[1:]))
            continue
        key, sep, value = line.partition(":")
        if not sep or not key.strip() or key[0].isspace():
            raise FileFormatError(f"{path}:{lineno}: expected 'key: value', got {raw!r}")
        key, value = key.strip(), value.strip()
        pending_list = None
        if not value:
            pending_list = []
            out[key] = pending_list
        elif value.startswith("["):
            if not value.endswith("]"):
                raise FileFormatError(f"{path}:{lineno}: unterminated list for {key!r}: {raw!r}")
            inner = value[1:-1].strip()
            out[key] = [_parse_scalar(v) for v in inner.split(",")] if inner else []
        else:
            out[key] = _parse_scalar(value)
    return out


def _number(value: object, key: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise FileFormatError(f"{path}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _flag(value: object, key: str, path: Path) -> bool:
    if value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    raise FileFormatError(f"{path}: '{key}' must be 0 or 1, got {value!r}")


# --------------------------------------------------------------------------- images


def _next_token(buf: bytes, pos: int) -> tuple[bytes, int]:
    """Next whitespace-separated header token of a PNM file, skipping '#' comments."""
    n = len(buf)
    while pos < n:
        if buf[pos : pos + 1].isspace():
            pos += 1
        elif buf[pos : pos + 1] == b"#":
            while pos < n and buf[pos : pos + 1] not in (b"\n", b"\r"):
                pos += 1
        else:
            break
    start = pos
    while pos < n and not buf[pos : pos + 1].isspace() and buf[pos : pos + 1] != b"#":
        pos += 1
    return buf[start:pos], pos


# a map image's grey level, its alpha (None: none) and the mean of all its channels
_Pixels = tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64]]


def _read_pgm(path: Path, buf: bytes) -> _Pixels:
    """Pixels of a P5/P2 PGM scaled to [0, 255] (top row first); no alpha."""
    magic, pos = _next_token(buf, 0)
    header: list[int] = []
    for name in ("width", "height", "maxval"):
        tok, pos = _next_token(buf, pos)
        try:
            header.append(int(tok))
        except ValueError:
            raise FileFormatError(
                f"{path}: PGM header: expected integer {name}, got {tok[:20]!r}"
            ) from None
    width, height, maxval = header
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise FileFormatError(
            f"{path}: PGM header: expected width, height > 0 and 0 < maxval < 65536, "
            f"got {width} x {height}, maxval {maxval}"
        )
    _check_size(path, width, height)
    count = width * height
    if magic == b"P5":
        pos += 1  # exactly one whitespace byte separates the header from the raster
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
        nbytes = count * dtype.itemsize
        if len(buf) - pos < nbytes:
            raise FileFormatError(
                f"{path}: truncated P5 PGM: expected {nbytes} raster bytes for "
                f"{width} x {height}, found {max(len(buf) - pos, 0)}"
            )
        pixels = np.frombuffer(buf, dtype=dtype, count=count, offset=pos)
    else:
        body = re.sub(rb"#[^\n\r]*", b" ", buf[pos:]).split()
        if len(body) < count:
            raise FileFormatError(
                f"{path}: truncated P2 PGM: expected {count} pixel values, found {len(body)}"
            )
        try:
            pixels = np.array(body[:count], dtype=np.int64)
        except ValueError:
            raise FileFormatError(f"{path}: P2 PGM: pixel values must be integers") from None
    if pixels.size and (pixels.min() < 0 or pixels.max() > maxval):
        raise FileFormatError(f"{path}: PGM pixel values must lie in [0, {maxval}]")
    scaled = pixels.astype(np.float64).reshape(height, width) * (255.0 / maxval)
    return scaled, None, scaled


def _read_with_pil(path: Path) -> _Pixels:
    """Grey level in [0, 255] (mean of the colour channels), alpha, and the mean of all
    channels (alpha too: map_server's trinary mode), top row first."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            _check_size(path, *img.size)
            img.load()
            if img.mode.startswith("I;16"):
                arr = np.asarray(img, dtype=np.float64) * (255.0 / 65535.0)
                return arr, None, arr
            if img.mode not in ("L", "LA", "RGB", "RGBA"):
                has_alpha = "transparency" in img.info or img.mode in ("PA", "La", "RGBa")
                img = img.convert("RGBA" if has_alpha else "RGB")
            arr = np.asarray(img, dtype=np.float64)
            mode = img.mode
    except (
        UnidentifiedImageError,
        OSError,
        ValueError,
        SyntaxError,
        Image.DecompressionBombError,
    ) as exc:
        raise FileFormatError(f"{path}: cannot decode map image: {exc}") from exc
    if arr.ndim == 2:
        return arr, None, arr
    if mode in ("LA", "RGBA"):
        return arr[..., :-1].mean(axis=-1), arr[..., -1], arr.mean(axis=-1)
    grey = arr.mean(axis=-1)
    return grey, None, grey


def _check_size(path: Path, width: int, height: int) -> None:
    """A map image's header may claim any size (a 57-byte PNG claimed 10^6 x 10^6)."""
    if width * height > MAX_MAP_CELLS:
        raise FileFormatError(
            f"{path}: map image of {width} x {height} pixels is larger than "
            f"{MAX_MAP_CELLS:.0e} cells"
        )


def _read_image(path: Path) -> _Pixels:
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read map image: {exc}") from exc
    if buf[:2] in (b"P2", b"P5") and (len(buf) < 3 or buf[2:3].isspace() or buf[2:3] == b"#"):
        return _read_pgm(path, buf)
    if path.suffix.lower() in _PGM_EXTENSIONS:
        raise FileFormatError(f"{path}: expected PGM magic 'P5' or 'P2', got {buf[:2]!r}")
    return _read_with_pil(path)


# --------------------------------------------------------------------------- public API


def read_map(yaml_path: str | Path) -> GridMap:
    """Read a map_server YAML and its image (PGM P5/P2, PNG or any format PIL reads).

    map_server semantics: p = (255 - pixel) / 255 (pixel / 255 if `negate`),
    p > occupied_thresh -> 100, p < free_thresh -> 0, otherwise -1 (`mode: trinary`,
    the default) or 1 + 98 * (p - free_thresh) / (occupied_thresh - free_thresh)
    (`mode: scale`; translucent pixels stay -1). Colour images use the mean of the
    colour channels. Unknown YAML keys are ignored.
    """
    yaml_path = Path(yaml_path)
    try:
        text = yaml_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{yaml_path}: cannot read map YAML: {exc}") from exc
    meta = _parse_flat_yaml(text, yaml_path)
    missing = [k for k in _REQUIRED_KEYS if k not in meta]
    if missing:
        raise FileFormatError(
            f"{yaml_path}: missing map YAML keys {missing} (expected {list(_REQUIRED_KEYS)})"
        )
    image = meta["image"]
    if not isinstance(image, str) or not image:
        raise FileFormatError(f"{yaml_path}: 'image' must be a file name, got {image!r}")
    resolution = _number(meta["resolution"], "resolution", yaml_path)
    if not MAP_RESOLUTION_RANGE_M[0] <= resolution <= MAP_RESOLUTION_RANGE_M[1]:
        lo, hi = MAP_RESOLUTION_RANGE_M
        raise FileFormatError(
            f"{yaml_path}: 'resolution' must be {lo:g}..{hi:g} m, got {resolution}"
        )
    origin = meta["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise FileFormatError(f"{yaml_path}: 'origin' must be [x, y, yaw], got {origin!r}")
    ox, oy, oyaw = (_number(v, "origin", yaml_path) for v in origin)
    if max(abs(ox), abs(oy)) > MAX_ORIGIN_M:
        raise FileFormatError(f"{yaml_path}: 'origin' must lie within {MAX_ORIGIN_M:g} m")
    if abs(oyaw) > 1e-9:
        raise FileFormatError(f"{yaml_path}: origin yaw must be 0, got {oyaw}")
    negate = _flag(meta["negate"], "negate", yaml_path)
    occ_th = _number(meta["occupied_thresh"], "occupied_thresh", yaml_path)
    free_th = _number(meta["free_thresh"], "free_thresh", yaml_path)
    if not 0.0 <= free_th < occ_th <= 1.0:
        raise FileFormatError(
            f"{yaml_path}: expected 0 <= free_thresh < occupied_thresh <= 1, "
            f"got {free_th}, {occ_th}"
        )
    mode = str(meta.get("mode", "trinary")).lower()
    if mode not in ("trinary", "scale"):
        raise FileFormatError(f"{yaml_path}: 'mode' must be trinary or scale, got {mode!r}")

    image_path = yaml_path.parent / image
    if not image_path.is_file():
        raise FileFormatError(f"{yaml_path}: map image {image_path} does not exist")
    grey, alpha, all_channels = _read_image(image_path)
    if mode == "trinary":  # map_server averages alpha in with the colours there
        grey = all_channels

    p = grey / 255.0 if negate else (255.0 - grey) / 255.0
    data = np.full(grey.shape, UNKNOWN, dtype=np.int8)
    if mode == "scale":  # the band's probability in percent, unknown to the masks (stored
        # as map_server's place in the band, 1..99, mid-grey had read as a wall)
        scaled = np.clip(np.rint(100.0 * p), FREE_MAX + 1, OCCUPIED_MIN - 1).astype(np.int8)
        between = (p >= free_th) & (p <= occ_th)
        if alpha is not None:
            between &= alpha >= 255.0
        data[between] = scaled[between]
    data[p > occ_th] = OCCUPIED
    data[p < free_th] = FREE
    grid = GridMap(
        data=np.ascontiguousarray(data[::-1]),
        resolution=resolution,
        origin=(ox, oy, 0.0),
        wgs84_origin=_geo_origin(meta.get("wgs84_origin"), yaml_path),
    )
    logger.debug(
        "read map %s: %d x %d cells at %.3f m", yaml_path, grid.width, grid.height, resolution
    )
    return grid


def _geo_origin(value: object, path: Path) -> GeoOrigin | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 3:
        raise FileFormatError(f"{path}: 'wgs84_origin' must be [lat, lon, alt], got {value!r}")
    try:
        return GeoOrigin(*(_number(v, "wgs84_origin", path) for v in value))
    except CollabSlamError as exc:
        raise FileFormatError(f"{path}: bad 'wgs84_origin': {exc}") from None


def read_wgs84_origin(yaml_path: str | Path) -> GeoOrigin | None:
    """The optional ``wgs84_origin`` of a map YAML without reading its image (None: none)."""
    yaml_path = Path(yaml_path)
    try:
        text = yaml_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{yaml_path}: cannot read map YAML: {exc}") from exc
    return _geo_origin(_parse_flat_yaml(text, yaml_path).get("wgs84_origin"), yaml_path)


def write_map(grid: GridMap, yaml_path: str | Path, image_name: str | None = None) -> None:
    """Write `grid` as a trinary map_server map: P5 PGM (free 254, occupied 0, unknown 205)
    next to `yaml_path`, named `image_name` (default: the YAML's stem + '.pgm').

    Cells are classified with `GridMap.free_mask` / `occupied_mask`, so -1/0/100 maps
    round-trip exactly. Parent directories are created.
    """
    yaml_path = Path(yaml_path)
    if image_name is None:
        image_name = yaml_path.stem + ".pgm"
    if Path(image_name).name != image_name:
        raise FileFormatError(
            f"{yaml_path}: image_name must be a bare file name, got {image_name!r}"
        )
    yaml_path.parent.mkdir(parents=True, exist_ok=True)

    pixels = np.full(grid.data.shape, PIXEL_UNKNOWN, dtype=np.uint8)
    pixels[grid.free_mask()] = PIXEL_FREE
    pixels[grid.occupied_mask()] = PIXEL_OCCUPIED
    header = f"P5\n# collabslam map\n{grid.width} {grid.height}\n255\n".encode("ascii")
    (yaml_path.parent / image_name).write_bytes(header + pixels[::-1].tobytes())

    x, y, _ = grid.origin
    lines = [
        f"image: {image_name}",
        "mode: trinary",
        f"resolution: {grid.resolution!r}",
        f"origin: [{x!r}, {y!r}, 0.0]",
        "negate: 0",
        "occupied_thresh: 0.65",
        "free_thresh: 0.196",
    ]
    if grid.wgs84_origin is not None:
        lat, lon, alt = grid.wgs84_origin.as_list()
        lines.append(f"wgs84_origin: [{lat!r}, {lon!r}, {alt!r}]")
    yaml_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    logger.debug("wrote map %s (%d x %d)", yaml_path, grid.width, grid.height)
