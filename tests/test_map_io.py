"""Tests for common.map_io (map_server YAML + PGM/PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.errors import CollabSlamError, FileFormatError
from common.map_io import GridMap, read_map, write_map

YAML_OK = """\
image: {image}
resolution: 0.1
origin: [-1.5, 2.0, 0.0]
negate: {negate}
occupied_thresh: 0.65
free_thresh: 0.196
"""


def _random_grid(h: int = 17, w: int = 23, seed: int = 0) -> GridMap:
    rng = np.random.default_rng(seed)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(h, w))
    return GridMap(data=data, resolution=0.05, origin=(-12.345, 3.21, 0.0))


def _write_pgm_p5(path: Path, pixels: np.ndarray) -> None:
    h, w = pixels.shape
    path.write_bytes(f"P5\n# test\n{w} {h}\n255\n".encode() + pixels.astype(np.uint8).tobytes())


def test_round_trip_is_exact(tmp_path: Path) -> None:
    grid = _random_grid()
    write_map(grid, tmp_path / "out" / "map.yaml")
    back = read_map(tmp_path / "out" / "map.yaml")
    assert back.data.dtype == np.int8
    np.testing.assert_array_equal(back.data, grid.data)
    assert back.resolution == grid.resolution
    assert back.origin == grid.origin


def test_write_uses_map_saver_pixels_and_flips_rows(tmp_path: Path) -> None:
    data = np.array([[0, 100, -1], [-1, -1, -1]], dtype=np.int8)  # row 0 = lowest y
    write_map(GridMap(data, 0.5, (0.0, 0.0, 0.0)), tmp_path / "m.yaml", image_name="img.pgm")
    raw = (tmp_path / "img.pgm").read_bytes()
    assert raw.startswith(b"P5")
    pixels = np.frombuffer(raw[-6:], dtype=np.uint8).reshape(2, 3)
    np.testing.assert_array_equal(pixels, [[205, 205, 205], [254, 0, 205]])
    text = (tmp_path / "m.yaml").read_text()
    assert "image: img.pgm" in text and "mode: trinary" in text and "negate: 0" in text


def test_read_thresholds_and_negate(tmp_path: Path) -> None:
    # p = (255 - px) / 255: 254 -> 0.004 free, 205 -> 0.196 unknown, 0 -> 1 occupied,
    # 90 -> 0.647 unknown, 88 -> 0.655 occupied, 205 is just above free_thresh.
    pixels = np.array([[254, 205, 0, 90, 88, 206]], dtype=np.uint8)
    _write_pgm_p5(tmp_path / "a.pgm", pixels)
    (tmp_path / "a.yaml").write_text(YAML_OK.format(image="a.pgm", negate=0))
    np.testing.assert_array_equal(read_map(tmp_path / "a.yaml").data, [[0, -1, 100, -1, 100, 0]])
    (tmp_path / "b.yaml").write_text(YAML_OK.format(image="a.pgm", negate=1))
    np.testing.assert_array_equal(read_map(tmp_path / "b.yaml").data, [[100, 100, 0, -1, -1, 100]])


def test_read_flips_image_rows(tmp_path: Path) -> None:
    pixels = np.array([[0, 0], [254, 254], [205, 205]], dtype=np.uint8)  # top row first
    _write_pgm_p5(tmp_path / "a.pgm", pixels)
    (tmp_path / "a.yaml").write_text(YAML_OK.format(image="a.pgm", negate=0))
    grid = read_map(tmp_path / "a.yaml")
    np.testing.assert_array_equal(grid.data[:, 0], [-1, 0, 100])  # lowest y first
    assert (grid.width, grid.height) == (2, 3)
    assert grid.origin == (-1.5, 2.0, 0.0)


def test_read_ascii_pgm_png_and_scale_mode(tmp_path: Path) -> None:
    (tmp_path / "a.pgm").write_text("P2\n# comment\n3 1\n# another\n255\n0 254\n205\n")
    (tmp_path / "a.yaml").write_text(YAML_OK.format(image="a.pgm", negate=0))
    np.testing.assert_array_equal(read_map(tmp_path / "a.yaml").data, [[100, 0, -1]])

    rgb = np.zeros((1, 3, 3), dtype=np.uint8)
    rgb[0, 1] = 254
    rgb[0, 2] = [200, 210, 205]  # channel mean 205 -> unknown
    Image.fromarray(rgb).save(tmp_path / "c.png")
    (tmp_path / "c.yaml").write_text(YAML_OK.format(image="c.png", negate=0))
    np.testing.assert_array_equal(read_map(tmp_path / "c.yaml").data, [[100, 0, -1]])

    Image.fromarray(np.array([[0, 65535, 30000]], dtype=np.uint16)).save(tmp_path / "w.png")
    (tmp_path / "w.yaml").write_text(YAML_OK.format(image="w.png", negate=0))
    np.testing.assert_array_equal(read_map(tmp_path / "w.yaml").data, [[100, 0, -1]])

    Image.fromarray(np.array([[128, 200, 254, 0]], dtype=np.uint8)).save(tmp_path / "s.png")
    text = YAML_OK.format(image="s.png", negate=0) + "mode: scale\n"
    (tmp_path / "s.yaml").write_text(text)
    grid = read_map(tmp_path / "s.yaml")  # p = 0.498 and 0.216 lie between the thresholds:
    np.testing.assert_array_equal(grid.data, [[50, 22, 0, 100]])  # their percent, unknown
    assert grid.free_mask().tolist() == [[False, False, True, False]]  # (mid-grey had read
    assert grid.occupied_mask().tolist() == [[False, False, False, True]]  # as a wall)


def test_yaml_comments_quotes_and_block_lists(tmp_path: Path) -> None:
    _write_pgm_p5(tmp_path / "a b.pgm", np.array([[254]], dtype=np.uint8))
    (tmp_path / "a.yaml").write_text(
        "# saved by someone\n"
        'image: "a b.pgm"  # quoted\n'
        "resolution: 0.25\n"
        "origin:\n  - 1\n  - -2.5\n  - 0\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
        "robot: extra key ignored\n"
    )
    grid = read_map(tmp_path / "a.yaml")
    assert grid.resolution == 0.25 and grid.origin == (1.0, -2.5, 0.0)
    assert grid.data[0, 0] == 0


@pytest.mark.parametrize(
    ("yaml_text", "image_bytes", "message"),
    [
        (YAML_OK.replace("resolution: 0.1\n", ""), None, "missing map YAML keys"),
        (YAML_OK.replace("0.1", "abc"), None, "'resolution' must be a finite number"),
        (YAML_OK.replace("0.1", "-0.1"), None, "'resolution' must be 0.001..100 m"),
        (YAML_OK.replace("0.1", "1e-320"), None, "'resolution' must be 0.001..100 m"),
        (YAML_OK.replace("-1.5, 2.0", "-1.5, 1e300"), None, "'origin' must lie within"),
        (YAML_OK, b"P5\n20000 20000\n255\n", "larger than"),
        (YAML_OK.replace("2.0, 0.0]", "2.0, 0.5]"), None, "origin yaw must be 0"),
        (YAML_OK.replace("[-1.5, 2.0, 0.0]", "[-1.5, 2.0"), None, "unterminated list"),
        (YAML_OK.replace("[-1.5, 2.0, 0.0]", "[1, 2]"), None, "'origin' must be [x, y, yaw]"),
        (YAML_OK + "mode: raw\n", None, "'mode' must be trinary or scale"),
        (YAML_OK.replace("0.196", "0.9"), None, "free_thresh < occupied_thresh"),
        (YAML_OK + "this line has no colon\n", None, "expected 'key: value'"),
        (YAML_OK, b"P5\n4 4\n255\n" + bytes(10), "truncated P5 PGM"),
        (YAML_OK, b"P2\n2 2\n255\n1 2 3\n", "truncated P2 PGM"),
        (YAML_OK, b"P5\nfour 4\n255\n", "expected integer width"),
        (YAML_OK, b"P6\n1 1\n255\n\x00\x00\x00", "expected PGM magic"),
        (YAML_OK, b"P2\n1 1\n255\n300\n", "pixel values must lie in"),
    ],
)
def test_malformed_input_raises_file_format_error(
    tmp_path: Path, yaml_text: str, image_bytes: bytes | None, message: str
) -> None:
    (tmp_path / "m.pgm").write_bytes(image_bytes or b"P5\n1 1\n255\n\xfe")
    (tmp_path / "m.yaml").write_text(yaml_text.format(image="m.pgm", negate=0))
    with pytest.raises(FileFormatError, match="m.(yaml|pgm)") as info:
        read_map(tmp_path / "m.yaml")
    assert message in str(info.value)


def test_missing_files_and_undecodable_png(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match="cannot read map YAML"):
        read_map(tmp_path / "nope.yaml")
    (tmp_path / "m.yaml").write_text(YAML_OK.format(image="gone.pgm", negate=0))
    with pytest.raises(FileFormatError, match="gone.pgm does not exist"):
        read_map(tmp_path / "m.yaml")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
    (tmp_path / "p.yaml").write_text(YAML_OK.format(image="bad.png", negate=0))
    with pytest.raises(FileFormatError, match="bad.png: cannot decode"):
        read_map(tmp_path / "p.yaml")


def test_a_png_claiming_a_huge_size_is_refused(tmp_path: Path) -> None:
    """A 57-byte PNG whose header claims 10^6 x 10^6 pixels had ended in PIL's
    DecompressionBombError and a traceback."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", 10**6, 10**6, 8, 0, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")
    (tmp_path / "bomb.png").write_bytes(png)
    (tmp_path / "m.yaml").write_text(YAML_OK.format(image="bomb.png", negate=0))
    with pytest.raises(FileFormatError, match="bomb.png: .*(1000000 x 1000000|bomb)"):
        read_map(tmp_path / "m.yaml")


def test_cell_helpers() -> None:
    grid = GridMap(np.zeros((4, 5), dtype=np.int8), 0.5, (-1.0, 2.0, 0.0))
    assert grid.extent == (-1.0, 1.5, 2.0, 4.0)
    cells = grid.world_to_cell([[-1.0, 2.0], [-0.01, 2.49], [1.49, 3.99], [-1.01, 5.0]])
    np.testing.assert_array_equal(cells, [[0, 0], [1, 0], [4, 3], [-1, 6]])
    np.testing.assert_array_equal(grid.in_bounds(cells), [True, True, True, False])
    np.testing.assert_allclose(grid.cell_to_world([[0, 0], [4, 3]]), [[-0.75, 2.25], [1.25, 3.75]])
    xs, ys = grid.cell_centers()
    np.testing.assert_allclose(xs, [-0.75, -0.25, 0.25, 0.75, 1.25])
    np.testing.assert_allclose(ys, [2.25, 2.75, 3.25, 3.75])
    grid.data[3, 4] = 100
    np.testing.assert_array_equal(grid.sample([[1.4, 3.9], [0.0, 3.0], [9.0, 9.0]]), [100, 0, -1])
    assert grid.occupied_mask().sum() == 1 and grid.free_mask().sum() == 19
    assert grid.known_mask().all()


def test_gridmap_validates() -> None:
    with pytest.raises(CollabSlamError, match="2-D"):
        GridMap(np.zeros(3, dtype=np.int8), 0.1, (0.0, 0.0, 0.0))
    with pytest.raises(CollabSlamError, match="yaw must be 0"):
        GridMap(np.zeros((2, 2), dtype=np.int8), 0.1, (0.0, 0.0, 0.3))
    with pytest.raises(CollabSlamError, match="resolution"):
        GridMap(np.zeros((2, 2), dtype=np.int8), 0.0, (0.0, 0.0, 0.0))
    grid = GridMap(np.array([[0, 100]]), 0.1, (0.0, 0.0, 0.0))  # other ints are converted
    assert grid.data.dtype == np.int8


def test_an_rgba_map_in_trinary_mode_reads_as_map_server_reads_it(tmp_path: Path) -> None:
    """map_server (ROS 1 image_loader, Nav2 map_io) averages alpha in with the colour
    channels in trinary mode: an opaque RGBA export's 205-grey reads free and its
    80-grey unknown there. read_map had left alpha out ([-1, 100, 0, 100])."""
    from PIL import Image

    px = np.array([[205, 80, 254, 0]], dtype=np.uint8)
    rgba = np.dstack([px, px, px, np.full_like(px, 255)])
    Image.fromarray(rgba, "RGBA").save(tmp_path / "w.png")
    meta = "resolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n"
    (tmp_path / "w.yaml").write_text(f"image: w.png\n{meta}free_thresh: 0.196\n")
    assert read_map(tmp_path / "w.yaml").data[0].tolist() == [0, -1, 0, 100]
    (tmp_path / "s.yaml").write_text(f"image: w.png\n{meta}free_thresh: 0.196\nmode: scale\n")
    assert read_map(tmp_path / "s.yaml").data[0].tolist()[3] == 100  # scale: alpha apart
