"""PNG snapshots of a map with robots, trajectories, frontiers and planned paths.

Uses matplotlib's object API with the Agg canvas (no pyplot): safe to call from any
thread, never opens a window. Everything is drawn in the map frame, in metres.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.markers import MarkerStyle
from matplotlib.transforms import Affine2D
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError
from common.map_io import FREE_MAX, OCCUPIED_MIN, GridMap

logger = logging.getLogger(__name__)


def robot_colour(i: int, n: int) -> str:
    """Robot i's of n: `ROBOT_COLOURS`, or for more robots (segments count) as many
    apart on the viridis colour map, which holds neither the frontiers' orange nor the
    unknown's grey (8 drones and 3 restarts had shared colours)."""
    if n <= len(ROBOT_COLOURS):
        return ROBOT_COLOURS[i]
    from matplotlib import colormaps, colors

    return str(colors.to_hex(colormaps["viridis"](0.9 * i / (n - 1))))


DPI = 150
FIG_WIDTH_IN = 9.0
# Robot colours: tab10 without orange (frontiers) and grey (unknown space).
ROBOT_COLOURS = (
    "#1f77b4",
    "#d62728",
    "#2ca02c",
    "#9467bd",
    "#8c564b",
    "#17becf",
    "#e377c2",
    "#bcbd22",
    "#000080",
    "#006400",
)
FRONTIER_COLOUR = "#ff7f0e"
GREY_UNKNOWN = 0.75
HEADING_ARROW_M = 0.8
# The map is drawn from an RGBA raster of at most this many pixels a side (blocks of cells,
# the darkest of each: thin walls stay). matplotlib resamples an image in floats, an RGB
# one in float64 (its alpha channel np.ones): a 1536 x 1483 map (60-minute soak) took
# ~180 MB for a picture ~1000 pixels across; RGBA uint8 stays in float32.
MAX_RASTER_PX = 800
# m drawn round the known cells and the overlays (the rest of a grid, often mostly
# unknown space the map was sized for, is left out)
VIEW_MARGIN_M = 1.0


def map_grey(data: NDArray[np.int8]) -> NDArray[np.uint8]:
    """Grey levels of grid values (row 0 = lowest y): unknown grey, free white, occupied
    black, in-between probabilities (scale-mode maps) as shades of grey."""
    shade = np.clip(1.0 - data.astype(np.float32) / 100.0, 0.0, 1.0)
    shade[data < 0] = GREY_UNKNOWN
    shade[(data >= 0) & (data <= FREE_MAX)] = 1.0
    shade[data >= OCCUPIED_MIN] = 0.0
    return (shade * 255.0).astype(np.uint8)


def map_rgb(grid: GridMap) -> NDArray[np.uint8]:
    """(H, W, 3) image of the grid (`map_grey`)."""
    return np.repeat(map_grey(grid.data)[..., None], 3, axis=2)


def _raster(grid: GridMap) -> tuple[NDArray[np.uint8], tuple[float, float, float, float]]:
    """The grid's grey as opaque RGBA in blocks of k x k cells (k so it fits
    `MAX_RASTER_PX`; the darkest cell of each, so a wall one cell thick stays), with its
    extent (m). Made a strip of blocks at a time: the whole grid in floats and RGB had
    peaked at 9 times its size (225 MB for 5000 x 5000 cells)."""
    x0, _, y0, _ = grid.extent
    rows, cols = grid.data.shape
    k = max(1, math.ceil(max(rows, cols) / MAX_RASTER_PX))
    h, w = -(-rows // k), -(-cols // k)  # blocks, the last ones padded
    out = np.empty((h, w), dtype=np.uint8)
    step = max(1, (1 << 20) // max(1, cols * k))  # block rows a strip (~1 M cells)
    for b0 in range(0, h, step):
        strip = map_grey(grid.data[b0 * k : (b0 + step) * k])
        pad = ((0, min(step, h - b0) * k - strip.shape[0]), (0, w * k - cols))
        strip = np.pad(strip, pad, "edge")
        out[b0 : b0 + step] = strip.reshape(-1, k, w, k).min(axis=(1, 3))
    rgba = np.dstack([out, out, out, np.full_like(out, 255)])
    res = grid.resolution * k
    return rgba, (x0, x0 + w * res, y0, y0 + h * res)


def cropped(grid: GridMap, points: list[NDArray[np.float64]]) -> GridMap:
    """The part of `grid` worth drawing: the box round its known cells and `points`
    ((N, 2) arrays, the overlays) with `VIEW_MARGIN_M` round it, within the grid; the
    whole grid when nothing is known or given."""
    r = grid.resolution
    x0, y0 = float(grid.origin[0]), float(grid.origin[1])
    known = grid.data >= 0
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    xs = [x0 + cols[0] * r, x0 + (cols[-1] + 1) * r] if len(cols) else []
    ys = [y0 + rows[0] * r, y0 + (rows[-1] + 1) * r] if len(rows) else []
    for p in points:
        if len(p):
            xs += [float(p[:, 0].min()), float(p[:, 0].max())]
            ys += [float(p[:, 1].min()), float(p[:, 1].max())]
    if not xs:
        return grid
    h, w = grid.data.shape
    c0 = max(0, math.floor((min(xs) - VIEW_MARGIN_M - x0) / r))
    c1 = min(w, math.ceil((max(xs) + VIEW_MARGIN_M - x0) / r))
    r0 = max(0, math.floor((min(ys) - VIEW_MARGIN_M - y0) / r))
    r1 = min(h, math.ceil((max(ys) + VIEW_MARGIN_M - y0) / r))
    if c1 <= c0 or r1 <= r0:  # the overlays lie off the grid
        return grid
    origin = (x0 + c0 * r, y0 + r0 * r, *tuple(grid.origin)[2:])
    return GridMap(data=grid.data[r0:r1, c0:c1], resolution=r, origin=origin)


def _xy(points: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 2:
        raise CollabSlamError(f"{what}: expected an (N, 2+) array of map-frame xy, got {p.shape}")
    return p[:, :2]


def _nice_length(span_m: float) -> float:
    """A 1/2/5 x 10^k length of about a fifth of `span_m`."""
    target = max(span_m / 5.0, 1e-3)
    base = 10.0 ** math.floor(math.log10(target))
    return max(m * base for m in (1.0, 2.0, 5.0) if m * base <= target)


def render_map_picture(
    path: str | Path,
    grid: GridMap,
    trajectories: dict[str, NDArray[np.float64]] | None = None,
    robots: dict[str, NDArray[np.float64]] | None = None,
    frontiers: NDArray[np.float64] | None = None,
    paths: dict[str, NDArray[np.float64]] | None = None,
    ground_truth: dict[str, NDArray[np.float64]] | None = None,
    title: str = "",
) -> None:
    """Save a PNG (parent directories created) of `grid` with overlays, all in the map frame.

    trajectories: robot id -> (N, 2+) xy travelled (solid line, one colour per robot).
    robots: robot id -> [x, y, yaw] current pose (triangle pointing along yaw + arrow).
    frontiers: (K, 2) frontier points. paths: robot id -> (M, 2) planned path (dotted).
    ground_truth: robot id -> (N, 2+) true xy (dashed, same colour as the robot).
    """
    trajectories = trajectories or {}
    robots = robots or {}
    paths = paths or {}
    ground_truth = ground_truth or {}
    ids = sorted(set(trajectories) | set(robots) | set(paths) | set(ground_truth))
    colour = {rid: robot_colour(i, len(ids)) for i, rid in enumerate(ids)}
    overlays = [_xy(p, f"trajectories[{r}]") for r, p in trajectories.items()]
    overlays += [_xy(p, f"paths[{r}]") for r, p in paths.items()]
    overlays += [_xy(p, f"ground_truth[{r}]") for r, p in ground_truth.items()]
    overlays += [_xy(np.reshape(p, (1, -1)), f"robots[{r}]") for r, p in robots.items()]
    if frontiers is not None and len(frontiers):
        overlays.append(_xy(frontiers, "frontiers"))
    grid = cropped(grid, overlays)

    x0, x1, y0, y1 = grid.extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig = Figure(figsize=(FIG_WIDTH_IN, min(max(FIG_WIDTH_IN * aspect, 3.0), 16.0) + 0.8))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    raster, extent = _raster(grid)
    ax.imshow(
        raster,
        origin="lower",
        extent=extent,
        interpolation="nearest",
        zorder=0,
    )

    for rid, xy in ground_truth.items():
        p = _xy(xy, f"ground_truth[{rid}]")
        ax.plot(p[:, 0], p[:, 1], "--", color=colour[rid], lw=1.0, alpha=0.8, zorder=2)
    for rid, xy in trajectories.items():
        p = _xy(xy, f"trajectories[{rid}]")
        ax.plot(p[:, 0], p[:, 1], "-", color=colour[rid], lw=1.5, zorder=3)
    for rid, xy in paths.items():
        p = _xy(xy, f"paths[{rid}]")
        ax.plot(p[:, 0], p[:, 1], ":", color=colour[rid], lw=2.0, zorder=4)
    if frontiers is not None and len(frontiers):
        f = _xy(frontiers, "frontiers")
        ax.scatter(f[:, 0], f[:, 1], s=10, c=FRONTIER_COLOUR, marker="o", lw=0, zorder=5)
    for rid, pose in robots.items():
        x, y, yaw = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(-1)[:3])
        marker = MarkerStyle(">", transform=Affine2D().rotate(yaw))
        ax.plot(x, y, marker=marker, ms=11, color=colour[rid], mec="k", mew=0.8, zorder=7)
        ax.annotate(
            "",
            xy=(x + HEADING_ARROW_M * math.cos(yaw), y + HEADING_ARROW_M * math.sin(yaw)),
            xytext=(x, y),
            arrowprops={"arrowstyle": "->", "color": colour[rid], "lw": 1.5},
            zorder=6,
        )

    handles = [Line2D([], [], color=colour[rid], lw=2.5, label=rid) for rid in ids]
    if ground_truth:
        handles.append(Line2D([], [], color="k", ls="--", lw=1.0, label="ground truth"))
    if paths:
        handles.append(Line2D([], [], color="k", ls=":", lw=2.0, label="planned path"))
    if frontiers is not None and len(frontiers):
        handles.append(
            Line2D([], [], color=FRONTIER_COLOUR, ls="", marker="o", ms=4, label="frontiers")
        )
    if handles:
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)

    bar = _nice_length(x1 - x0)
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            bar,
            f"{bar:g} m",
            loc="lower right",
            pad=0.4,
            borderpad=0.5,
            sep=3,
            frameon=True,
            size_vertical=(y1 - y0) / 150.0,
        )
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.tick_params(labelsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.set_layout_engine("constrained")

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, format="png", bbox_inches="tight", pad_inches=0.1)
    logger.debug("wrote map picture %s", path)
