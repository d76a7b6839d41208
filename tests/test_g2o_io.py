"""Tests for common.g2o_io: the shared data sets and a write/read round trip."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from common.errors import FileFormatError
from common.g2o_io import EdgeSE2, EdgeSE3, G2oGraph, read_g2o, write_g2o

G2O_DIR = Path(__file__).parents[2] / "shared/data/g2o"
needs_data = pytest.mark.skipif(
    not G2O_DIR.is_dir(), reason=f"shared g2o data folder {G2O_DIR} is absent"
)


def _count_tags(path: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    for line in path.read_text().splitlines():
        if line.strip():
            tag = line.split()[0]
            counts[tag] = counts.get(tag, 0) + 1
    return counts


@needs_data
def test_reads_intel() -> None:
    path = G2O_DIR / "intel.g2o"
    graph = read_g2o(path)
    counts = _count_tags(path)
    assert len(graph.vertices_se2) == counts["VERTEX_SE2"]
    assert len(graph.edges_se2) == counts["EDGE_SE2"]
    assert not graph.vertices_se3 and not graph.edges_se3
    np.testing.assert_allclose(graph.vertices_se2[1], [0.144012, -0.004462, -0.017453])
    for edge in graph.edges_se2:
        assert edge.measurement.shape == (3,)
        np.testing.assert_array_equal(edge.information, edge.information.T)
        assert np.all(np.linalg.eigvalsh(edge.information) > 0)
    # the chain's odometry edges link consecutive vertices
    assert sum(e.j == e.i + 1 for e in graph.edges_se2) >= len(graph.vertices_se2) - 1


@needs_data
def test_reads_3d_sphere() -> None:
    graph = read_g2o(G2O_DIR / "sphere2500.g2o")
    assert len(graph.vertices_se3) == 2500 and not graph.vertices_se2
    edge = graph.edges_se3[0]
    assert edge.measurement.shape == (7,) and edge.information.shape == (6, 6)
    np.testing.assert_allclose(np.linalg.norm(edge.measurement[3:]), 1.0, atol=1e-5)
    np.testing.assert_array_equal(edge.information, edge.information.T)


def _small_graph() -> G2oGraph:
    rng = np.random.default_rng(3)
    info2 = np.array([[100.0, 1.5, 0.25], [1.5, 90.0, -0.5], [0.25, -0.5, 400.0]])
    info6 = np.diag([10.0, 11.0, 12.0, 400.0, 401.0, 402.0])
    info6[0, 4] = info6[4, 0] = 0.125
    quat = rng.normal(size=4)
    graph = G2oGraph()
    graph.vertices_se2 = {i: rng.normal(size=3) for i in (0, 1, 2)}
    graph.edges_se2 = [
        EdgeSE2(0, 1, rng.normal(size=3), info2),
        EdgeSE2(0, 2, np.array([1 / 3, -2e-17, np.pi]), info2),
    ]
    graph.vertices_se3 = {7: np.concatenate([rng.normal(size=3), quat / np.linalg.norm(quat)])}
    graph.edges_se3 = [EdgeSE3(7, 8, rng.normal(size=7), info6)]
    return graph


def test_round_trip(tmp_path: Path) -> None:
    graph = _small_graph()
    path = tmp_path / "small.g2o"
    write_g2o(path, graph)
    back = read_g2o(path)
    assert back.vertices_se2.keys() == graph.vertices_se2.keys()
    for vid, value in graph.vertices_se2.items():
        np.testing.assert_array_equal(back.vertices_se2[vid], value)
    np.testing.assert_array_equal(back.vertices_se3[7], graph.vertices_se3[7])
    for got, want in zip(
        back.edges_se2 + back.edges_se3, graph.edges_se2 + graph.edges_se3, strict=True
    ):
        assert (got.i, got.j) == (want.i, want.j)
        np.testing.assert_array_equal(got.measurement, want.measurement)
        np.testing.assert_array_equal(got.information, want.information)


def test_round_trip_bz2(tmp_path: Path) -> None:
    path = tmp_path / "small.g2o.bz2"
    write_g2o(path, _small_graph())
    assert len(read_g2o(path).edges_se2) == 2


def test_skips_unknown_tags_and_comments(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "fix.g2o"
    path.write_text("# comment\nVERTEX_SE2 0 0 0 0\n\nFIX 0\nVERTEX_XY 5 1 2\n")
    with caplog.at_level(logging.DEBUG, logger="common.g2o_io"):
        graph = read_g2o(path)
    assert list(graph.vertices_se2) == [0]
    assert "FIX" in caplog.text and "VERTEX_XY" in caplog.text


@pytest.mark.parametrize(
    "bad_line",
    [
        "EDGE_SE2 0 1 1 0 0 1 0 0 1 0",  # one information value missing
        "VERTEX_SE2 1 0 zero 0",
        "VERTEX_SE2 1.5 0 0 0",
        "VERTEX_SE2 1 nan 0 0",
        "VERTEX_SE2 0 1 1 1",  # duplicate id
        "EDGE_SE2 0 1 1 0 0 0 0 0 0 0 0",  # zero information: a LinAlgError traceback
        "EDGE_SE2 -5 0 1 0 0 1 0 0 1 0 1",  # negative id: a KeyError traceback
    ],
)
def test_malformed_line_names_the_line(tmp_path: Path, bad_line: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text(f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 0 0 0 1 0 0 1 0 1\n{bad_line}\n")
    with pytest.raises(FileFormatError, match=r"bad\.g2o:3"):
        read_g2o(path)


def test_missing_file_and_bad_shapes(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError):
        read_g2o(tmp_path / "missing.g2o")
    graph = G2oGraph(edges_se2=[EdgeSE2(0, 1, np.zeros(3), np.eye(2))])
    with pytest.raises(FileFormatError, match="information"):
        write_g2o(tmp_path / "out.g2o", graph)
