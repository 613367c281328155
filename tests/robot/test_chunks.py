"""Map tools: slice then stitch gives back the same image, meta.json, pixel <-> metre."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mapservice.adapters.ros_map import (
    RosMap,
    load_ros_map,
    read_pgm,
    save_ros_map,
    slice_chunks,
    write_pgm,
)
from mapservice.core.events import MapMetaSet
from mapservice.robot.chunks import (
    chunk_of_pixel,
    describe,
    meta_from_json,
    meta_to_json,
    metres_to_pixel,
    pixel_to_metres,
    slice_to_dir,
    stitch,
    stitch_dir,
)
from tests.fixtures.paths import ROOT
from tests.robot.conftest import all_map_yamls

MAP_YAMLS = all_map_yamls()


@pytest.mark.parametrize("yaml_path", MAP_YAMLS, ids=lambda p: p.stem)
def test_every_map_round_trips_byte_for_byte(yaml_path, tmp_path) -> None:
    """slice_to_dir then stitch_dir writes back the very same PGM file and YAML values."""
    meta = slice_to_dir(yaml_path, tmp_path / "chunks")
    original = load_ros_map(yaml_path)
    assert (meta.width, meta.height) == (original.width, original.height)
    assert meta.width % 100 or meta.height % 100, "real maps do not divide into whole chunks"
    out = stitch_dir(tmp_path / "chunks", tmp_path / "out" / "back.yaml")
    back = load_ros_map(out)
    assert np.array_equal(back.pixels, original.pixels)
    image = yaml_path.parent / f"{yaml_path.stem}.pgm"
    assert (tmp_path / "out" / "back.pgm").read_bytes() == image.read_bytes()
    for name in ("resolution", "origin", "negate", "occupied_thresh", "free_thresh", "mode"):
        assert getattr(back, name) == getattr(original, name), name


def test_shared_maps_are_all_covered() -> None:
    """The round trip runs on every map of ../shared/maps (when it is there) and the repo's."""
    names = {p.stem for p in MAP_YAMLS}
    assert {"depot", "warehouse"} <= names
    shared = ROOT.parent / "shared" / "maps"
    if shared.is_dir():
        assert {p.stem for p in shared.glob("*.yaml")} <= names


def test_meta_json_keeps_2019_fields_and_adds_geometry(tmp_path) -> None:
    """meta.json has listing 8's fields, plus resolution and origin, and reads back the same."""
    yaml_path = next(p for p in MAP_YAMLS if p.stem == "warehouse")
    meta = slice_to_dir(yaml_path, tmp_path)
    doc = json.loads((tmp_path / "meta.json").read_text())
    assert {
        "comment",
        "width",
        "height",
        "max_brightness",
        "CHUNK_WIDTH",
        "CHUNK_HEIGHT",
        "CHUNK_ROWS",
        "CHUNK_COLS",
        "resolution",
        "origin",
    } == set(doc)
    assert doc["comment"].startswith("# Created by GIMP")
    assert (doc["width"], doc["height"], doc["CHUNK_ROWS"], doc["CHUNK_COLS"]) == (
        1006,
        1674,
        17,
        11,
    )
    assert doc["max_brightness"] == "255" and doc["origin"] == [-15.1, -25.0, 0.0]
    assert meta_from_json(doc) == meta
    assert len(list(tmp_path.glob("chunk_*.pgm"))) == 17 * 11


def test_padding_is_the_maps_unknown_value(tmp_path) -> None:
    """Chunks past the edge are padded with 205 (what the maps use for unknown), or 50 with
    negate: 1; stitching crops the padding away."""
    for negate, fill in ((0, 205), (1, 50)):
        m = RosMap(np.full((3, 5), 7, np.uint8), 0.1, (0.0, 0.0, 0.0), negate=negate)
        chunks = slice_chunks(m, 4, 2)
        assert chunks[(1, 1)] == bytes([7, fill, fill, fill, fill, fill, fill, fill])
        meta = meta_from_json(meta_to_json(MapMetaSet(5, 3, 4, 2, 2, 2)))
        assert np.array_equal(stitch(chunks, meta), m.pixels)


@st.composite
def odd_maps(draw):
    width = draw(st.integers(1, 57))
    height = draw(st.integers(1, 57))
    pixels = draw(
        arrays(np.uint8, (height, width), elements=st.sampled_from([0, 205, 254, 255, 17]))
    )
    return (
        pixels,
        draw(st.integers(2, 23)),
        draw(st.integers(2, 23)),
        draw(st.sampled_from(["P2", "P5"])),
    )


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(odd_maps())
def test_generated_odd_maps_round_trip(tmp_path, case) -> None:
    """Any size, any chunk size, P2 or P5: slice then stitch gives the identical pixels."""
    pixels, cw, ch, magic = case
    work = Path(tempfile.mkdtemp(dir=tmp_path))
    save_ros_map(RosMap(pixels, 0.05, (1.5, -2.0, 0.0), magic=magic), work / "m.yaml")
    meta = slice_to_dir(work / "m.yaml", work / "chunks", cw, ch)
    assert meta.chunk_rows == -(-pixels.shape[0] // ch) and meta.chunk_cols == -(
        -pixels.shape[1] // cw
    )
    stitch_dir(work / "chunks", work / "back.pgm")
    back, header = read_pgm(work / "back.pgm")
    assert header.magic == magic
    assert np.array_equal(back, pixels)


def test_pillow_reads_plain_p2(tmp_path) -> None:
    """A plain (P2) PGM with a comment and maxval 15 loads with its own values and comment."""
    (tmp_path / "p2.pgm").write_text("P2\n# made by hand\n3 2\n15\n0 5 15\n15 0 5\n")
    pixels, header = read_pgm(tmp_path / "p2.pgm")
    assert pixels.tolist() == [[0, 5, 15], [15, 0, 5]]
    assert (header.magic, header.maxval, header.comments) == ("P2", 15, ("# made by hand",))
    write_pgm(tmp_path / "again.pgm", pixels, magic="P2", comment="# made by hand", maxval=15)
    assert read_pgm(tmp_path / "again.pgm")[0].tolist() == pixels.tolist()


def test_sixteen_bit_pgm_is_refused_with_a_reason(tmp_path) -> None:
    """maxval above 255 is refused with a message instead of being misread."""
    (tmp_path / "deep.pgm").write_bytes(b"P5\n1 1\n65535\n\x00\x01")
    with pytest.raises(ValueError, match="8-bit"):
        read_pgm(tmp_path / "deep.pgm")


META = MapMetaSet(
    width=604,
    height=307,
    chunk_width=100,
    chunk_height=100,
    chunk_rows=4,
    chunk_cols=7,
    resolution=0.05,
    origin=(-3.0, 2.5, 0.0),
)


@given(st.integers(0, 603), st.integers(0, 306))
def test_pixel_to_metres_and_back(col, row) -> None:
    """A pixel's centre in metres converts back to the same pixel."""
    x, y = pixel_to_metres(col, row, META)
    assert metres_to_pixel(x, y, META) == (col, row)


@given(st.floats(-3.0, -3.0 + 604 * 0.05 - 1e-6), st.floats(2.5, 2.5 + 307 * 0.05 - 1e-6))
def test_metres_to_pixel_and_back(x, y) -> None:
    """A world point lies within half a pixel of the centre of the pixel it converts to."""
    col, row = metres_to_pixel(x, y, META)
    assert 0 <= col < 604 and 0 <= row < 307
    cx, cy = pixel_to_metres(col, row, META)
    assert abs(cx - x) <= 0.025 + 1e-9 and abs(cy - y) <= 0.025 + 1e-9


def test_conversion_orientation() -> None:
    """The origin is the lower-left corner: the bottom-left pixel is at origin + half a pixel,
    and the top row is the highest y."""
    assert pixel_to_metres(0, 306, META) == pytest.approx((-2.975, 2.525))
    assert pixel_to_metres(0, 0, META)[1] == pytest.approx(2.5 + 306.5 * 0.05)
    assert chunk_of_pixel(603, 306, META) == (3, 6)


def test_info_counts_pixel_classes() -> None:
    """describe() gives the 2019 meta plus ROS thresholds and the free/occupied counts."""
    info = describe(next(p for p in MAP_YAMLS if p.stem == "depot"))
    assert (info["CHUNK_ROWS"], info["CHUNK_COLS"], info["pgm_format"]) == (4, 7, "P5")
    assert info["free_px"] + info["occupied_px"] + info["unknown_px"] == 604 * 307
    assert info["occupied_px"] == 5947


def test_cli_with_relative_paths(tmp_path) -> None:
    """`mapservice map slice/stitch/info` work with paths relative to the working directory."""
    src = next(p for p in MAP_YAMLS if p.stem == "depot")
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "depot.yaml").write_text(src.read_text())
    (tmp_path / "maps" / "depot.pgm").write_bytes((src.parent / "depot.pgm").read_bytes())
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def run(*args):
        return subprocess.run(
            [sys.executable, "-m", "mapservice.cli", "map", *args],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )

    sliced = run(
        "slice", "maps/depot.yaml", "-o", "out", "--chunk-width", "64", "--chunk-height", "48"
    )
    assert sliced.returncode == 0, sliced.stderr
    assert "70 chunks" in sliced.stdout  # ceil(604/64)=10 columns x ceil(307/48)=7 rows
    stitched = run("stitch", "out", "-o", "back/depot.pgm")
    assert stitched.returncode == 0, stitched.stderr
    assert (tmp_path / "back" / "depot.pgm").read_bytes() == (src.parent / "depot.pgm").read_bytes()
    info = run("info", "maps/depot.yaml")
    assert info.returncode == 0 and json.loads(info.stdout)["width"] == 604
    missing = run("stitch", "nowhere", "-o", "x.pgm")
    assert missing.returncode != 0 and "meta.json" in missing.stderr


def test_bare_plain_pgm_round_trips_as_plain(tmp_path) -> None:
    """A bare P2 file (no YAML) slices without resolution/origin and stitches back as P2."""
    (tmp_path / "hand.pgm").write_text(
        "P2\n# hand made\n5 3\n255\n" + "0 205 254 254 0\n254 254 254 205 205\n0 0 254 254 254\n"
    )
    meta = slice_to_dir(tmp_path / "hand.pgm", tmp_path / "c", 2, 2)
    assert (meta.chunk_rows, meta.chunk_cols, meta.resolution, meta.origin) == (2, 3, None, None)
    assert "resolution" not in json.loads((tmp_path / "c" / "meta.json").read_text())
    stitch_dir(tmp_path / "c", tmp_path / "back.pgm")
    back, header = read_pgm(tmp_path / "back.pgm")
    assert header.magic == "P2" and header.comments == ("# hand made",)
    assert np.array_equal(back, read_pgm(tmp_path / "hand.pgm")[0])
    with pytest.raises(ValueError, match="resolution"):
        stitch_dir(tmp_path / "c", tmp_path / "back.yaml")
