"""ROS occupancy-grid maps (maps/*.yaml) and their cut into 2019 chunks."""

from __future__ import annotations

import numpy as np
import pytest

from mapservice.adapters.ros_map import (
    UNKNOWN,
    RosMap,
    free_cells_metres,
    load_ros_map,
    meta_for,
    slice_chunks,
)
from tests.fixtures.paths import MAPS

# name: (width, height, resolution, origin, chunk rows, chunk cols) for 100 x 100 chunks
EXPECTED = {
    "warehouse": (1006, 1674, 0.03, (-15.1, -25.0, 0.0), 17, 11),
    "depot": (604, 307, 0.05, (0.0, 0.0, 0.0), 4, 7),
}


@pytest.fixture(scope="module", params=sorted(EXPECTED))
def named_map(request) -> tuple[str, RosMap]:
    return request.param, load_ros_map(MAPS / f"{request.param}.yaml")


def test_load_reads_image_and_yaml(named_map) -> None:
    """Loading a map gives its pixels (height x width, uint8), resolution and origin."""
    name, m = named_map
    width, height, resolution, origin, _, _ = EXPECTED[name]
    assert m.pixels.dtype == np.uint8 and m.pixels.shape == (height, width)
    assert (m.width, m.height) == (width, height)
    assert m.resolution == resolution
    assert m.origin == origin
    # A trinary ROS map: free (254), occupied (0) and unknown (205) all occur.
    values = set(np.unique(m.pixels).tolist())
    assert {0, 205, 254} <= values


def test_load_accepts_a_string_path_relative_image(tmp_path) -> None:
    """The YAML's image path is resolved relative to the YAML file, not the working directory."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "tiny.pgm").write_bytes(
        b"P5\n3 2\n255\n" + bytes([0, 205, 254, 254, 0, 205])
    )
    (tmp_path / "tiny.yaml").write_text("image: sub/tiny.pgm\nresolution: 0.5\norigin: [1, 2, 0]\n")
    m = load_ros_map(str(tmp_path / "tiny.yaml"))
    assert m.pixels.tolist() == [[0, 205, 254], [254, 0, 205]]
    assert m.origin == (1.0, 2.0, 0.0)


def test_meta_counts_whole_chunks(named_map) -> None:
    """meta_for rounds the grid up to whole chunks and keeps resolution and origin."""
    name, m = named_map
    width, height, resolution, origin, rows, cols = EXPECTED[name]
    meta = meta_for(m)
    assert (meta.width, meta.height, meta.chunk_width, meta.chunk_height) == (
        width,
        height,
        100,
        100,
    )
    assert (meta.chunk_rows, meta.chunk_cols) == (rows, cols)
    assert (meta.resolution, meta.origin) == (resolution, origin)


def test_slice_gives_rows_times_cols_chunks(named_map) -> None:
    """Slicing yields exactly rows x cols chunks, keyed (row, column), each 100 x 100 bytes."""
    name, m = named_map
    *_, rows, cols = EXPECTED[name]
    chunks = slice_chunks(m)
    assert len(chunks) == rows * cols
    assert set(chunks) == {(r, c) for r in range(rows) for c in range(cols)}
    assert all(len(data) == 100 * 100 for data in chunks.values())


def test_slice_pads_with_unknown_and_keeps_pixels(named_map) -> None:
    """Reassembled chunks give back the map exactly, padded to whole chunks with 205."""
    name, m = named_map
    *_, rows, cols = EXPECTED[name]
    chunks = slice_chunks(m)
    grid = np.block(
        [
            [np.frombuffer(chunks[(r, c)], np.uint8).reshape(100, 100) for c in range(cols)]
            for r in range(rows)
        ]
    )
    assert grid.shape == (rows * 100, cols * 100)
    assert np.array_equal(grid[: m.height, : m.width], m.pixels)
    assert (grid[m.height :, :] == UNKNOWN).all()
    assert (grid[:, m.width :] == UNKNOWN).all()
    assert UNKNOWN == 205
    # The last chunk of the bottom row holds padding on both edges.
    last = np.frombuffer(chunks[(rows - 1, cols - 1)], np.uint8).reshape(100, 100)
    assert last[-1, -1] == UNKNOWN


def test_slice_with_other_chunk_size() -> None:
    """A 5 x 3 map cut into 2 x 2 chunks gives 2 x 3 chunks, padding with 205."""
    pixels = np.arange(15, dtype=np.uint8).reshape(3, 5)
    chunks = slice_chunks(RosMap(pixels, 0.1, (0.0, 0.0, 0.0)), chunk_width=2, chunk_height=2)
    assert len(chunks) == 6
    assert chunks[(0, 0)] == bytes([0, 1, 5, 6])
    assert chunks[(1, 2)] == bytes([14, 205, 205, 205])


def test_free_cells_lie_on_free_pixels(named_map) -> None:
    """Every sampled world point maps back to a free (>= 250) pixel inside the map."""
    _, m = named_map
    points = free_cells_metres(m)
    assert points.ndim == 2 and points.shape[1] == 2 and len(points) > 50
    ox, oy, _ = m.origin
    col = np.floor((points[:, 0] - ox) / m.resolution).astype(int)
    row_from_bottom = np.floor((points[:, 1] - oy) / m.resolution).astype(int)
    row = m.height - 1 - row_from_bottom
    assert ((0 <= col) & (col < m.width) & (0 <= row) & (row < m.height)).all()
    assert (m.pixels[row, col] >= 250).all()


def test_free_cells_follow_the_origin_and_flip() -> None:
    """World y grows upwards: a free pixel in the top row is the highest point."""
    pixels = np.zeros((4, 3), np.uint8)
    pixels[0, 2] = 254  # top-right
    pixels[3, 0] = 254  # bottom-left
    points = free_cells_metres(RosMap(pixels, 0.5, (10.0, -1.0, 0.0)), stride=1)
    assert sorted(map(tuple, points.tolist())) == [(10.25, -0.75), (11.25, 0.75)]
