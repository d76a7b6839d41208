"""Read and write g2o pose-graph files (2-D SE2 and 3-D SE3:QUAT).

Supported lines (g2o conventions):
- ``VERTEX_SE2 id x y theta``                       (m, m, rad)
- ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``
- ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
- ``EDGE_SE3:QUAT i j x y z qx qy qz qw I11 I12 .. I16 I22 .. I66`` (21 values)

An edge's measurement is ``T_i_j``, the pose of vertex j in the frame of vertex i.
Information matrices are stored as their upper triangle, row by row; for SE3 the
order is ``[x, y, z, rx, ry, rz]`` (translation first, unlike gtsam's Pose3 tangent).
Quaternions are ``[qx, qy, qz, qw]`` (scalar last), i.e. 3-D poses are "pose7".
Unknown tags (``FIX``, ``VERTEX_XY``, ...) are skipped with a debug log; blank lines
and ``#`` comments are ignored. Files ending in ``.bz2`` are read compressed.
"""

from __future__ import annotations

import bz2
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, NamedTuple

import numpy as np
from numpy.typing import NDArray

from common.errors import FileFormatError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class EdgeSE2(NamedTuple):
    """A 2-D relative-pose measurement ``T_i_j = [dx, dy, dtheta]`` with its 3x3 information."""

    i: int
    j: int
    measurement: FloatArray
    information: FloatArray


class EdgeSE3(NamedTuple):
    """A 3-D relative-pose measurement ``T_i_j`` as pose7 with its 6x6 information."""

    i: int
    j: int
    measurement: FloatArray
    information: FloatArray


@dataclass
class G2oGraph:
    """Contents of a g2o file. Vertex values are initial guesses in the file's world frame."""

    vertices_se2: dict[int, FloatArray] = field(default_factory=dict)  # id -> [x, y, theta]
    edges_se2: list[EdgeSE2] = field(default_factory=list)
    vertices_se3: dict[int, FloatArray] = field(default_factory=dict)  # id -> pose7
    edges_se3: list[EdgeSE3] = field(default_factory=list)


# tag -> (number of numeric fields after the tag, information dimension or 0 for vertices)
_LAYOUT = {
    "VERTEX_SE2": (4, 0),
    "EDGE_SE2": (2 + 3 + 6, 3),
    "VERTEX_SE3:QUAT": (8, 0),
    "EDGE_SE3:QUAT": (2 + 7 + 21, 6),
}


def _upper_to_full(values: FloatArray, dim: int) -> FloatArray:
    info = np.zeros((dim, dim))
    info[np.triu_indices(dim)] = values
    return info + np.triu(info, 1).T


def _open_text(path: Path, mode: str) -> IO[str]:
    if path.suffix == ".bz2":
        return bz2.open(path, mode + "t", encoding="ascii")
    return path.open(mode, encoding="ascii")


def _parse_line(graph: G2oGraph, tag: str, fields: list[str], where: str) -> None:
    expected, info_dim = _LAYOUT[tag]
    if len(fields) != expected:
        raise FileFormatError(f"{where}: {tag} needs {expected} values, got {len(fields)}")
    try:
        ids = [int(f) for f in fields[: 2 if info_dim else 1]]
        numbers = np.array([float(f) for f in fields[len(ids) :]], dtype=np.float64)
    except ValueError as exc:
        raise FileFormatError(f"{where}: {tag} has a non-numeric field ({exc})") from exc
    if not np.all(np.isfinite(numbers)):
        raise FileFormatError(f"{where}: {tag} has a non-finite value")
    if min(ids) < 0:
        raise FileFormatError(f"{where}: {tag} has a negative vertex id {min(ids)}")
    if info_dim == 0:
        vertices = graph.vertices_se2 if tag == "VERTEX_SE2" else graph.vertices_se3
        if ids[0] in vertices:
            raise FileFormatError(f"{where}: duplicate vertex id {ids[0]}")
        vertices[ids[0]] = numbers
        return
    n_meas = 3 if info_dim == 3 else 7
    info = _upper_to_full(numbers[n_meas:], info_dim)
    try:  # an all-zero information matrix had ended in a LinAlgError traceback
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        raise FileFormatError(
            f"{where}: {tag} information matrix is not positive definite"
        ) from None
    if info_dim == 3:
        graph.edges_se2.append(EdgeSE2(ids[0], ids[1], numbers[:n_meas], info))
    else:
        graph.edges_se3.append(EdgeSE3(ids[0], ids[1], numbers[:n_meas], info))


def read_g2o(path: str | Path) -> G2oGraph:
    """Read a g2o file; raise FileFormatError naming the line on a malformed line."""
    path = Path(path)
    graph = G2oGraph()
    skipped: Counter[str] = Counter()
    try:
        with _open_text(path, "r") as f:
            for line_no, line in enumerate(f, start=1):
                tokens = line.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                if tokens[0] not in _LAYOUT:
                    skipped[tokens[0]] += 1
                    continue
                _parse_line(graph, tokens[0], tokens[1:], f"{path}:{line_no}")
    except OSError as exc:
        raise FileFormatError(f"cannot read g2o file {path}: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{path} is not an ASCII g2o file: {exc}") from exc
    for tag, count in skipped.items():
        logger.debug("%s: skipped %d line(s) with unsupported tag %s", path, count, tag)
    return graph


def _fmt(values: FloatArray) -> str:
    return " ".join(repr(float(v)) for v in values)


def _check_edge(edge: EdgeSE2 | EdgeSE3, n_meas: int, dim: int) -> None:
    if np.shape(edge.measurement) != (n_meas,) or np.shape(edge.information) != (dim, dim):
        raise FileFormatError(
            f"edge {edge.i}->{edge.j}: expected measurement ({n_meas},) and information "
            f"({dim}, {dim}), got {np.shape(edge.measurement)} and {np.shape(edge.information)}"
        )


def write_g2o(path: str | Path, graph: G2oGraph) -> None:
    """Write vertices (sorted by id) then edges (in order); floats keep full precision."""
    path = Path(path)
    lines: list[str] = []
    for tag, vertices, n in (
        ("VERTEX_SE2", graph.vertices_se2, 3),
        ("VERTEX_SE3:QUAT", graph.vertices_se3, 7),
    ):
        for vid in sorted(vertices):
            if np.shape(vertices[vid]) != (n,):
                raise FileFormatError(f"{tag} {vid}: expected shape ({n},)")
            lines.append(f"{tag} {vid} {_fmt(vertices[vid])}")
    for edge in graph.edges_se2:
        _check_edge(edge, 3, 3)
        upper = np.asarray(edge.information)[np.triu_indices(3)]
        lines.append(f"EDGE_SE2 {edge.i} {edge.j} {_fmt(edge.measurement)} {_fmt(upper)}")
    for edge in graph.edges_se3:
        _check_edge(edge, 7, 6)
        upper = np.asarray(edge.information)[np.triu_indices(6)]
        lines.append(f"EDGE_SE3:QUAT {edge.i} {edge.j} {_fmt(edge.measurement)} {_fmt(upper)}")
    with _open_text(path, "w") as f:
        f.write("\n".join(lines) + "\n")
