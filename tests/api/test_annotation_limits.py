"""Zones and imported masks through the API, off the event loop: zone
geometry refused with the right reason at any size, the caps on vertices and on the cells
a zone rasterises into answered early with a 422 naming the cap, and a mask image's size
read from its header (a decompression bomb, a checkerboard, other formats, truncated
files) before anything is decoded or traced. How long they take while the probes are
timed: tests/api/test_heavy_requests.py."""

from __future__ import annotations

import asyncio
import base64
import io
import random

import numpy as np
import pytest
from PIL import Image, ImageFile

from mapservice.adapters import costmap_filters
from mapservice.api.routers import annotations as annotations_router
from mapservice.core import annotations as core_annotations
from mapservice.core.zone_geometry import MAX_ZONE_VERTICES
from tests.api.test_annotations import NOW, OPERATOR, World, keep_out, square
from tests.conftest import meta_event
from tests.geometry_kit import (
    checkerboard,
    crossing_ring,
    largest_allowed_zone_doc,
    mask_png,
    mask_yaml,
    png_bomb,
    png_header_only,
    star_ring,
)

# The default map of tests.conftest.meta_event: 500 x 400 px of 5 cm, origin (-1.5, 2.0).
ORIGIN, RESOLUTION = (-1.5, 2.0), 0.05


def _big_map(cols: int, rows: int) -> World:
    """A map of cols x rows chunks of 100 x 100 px (the same resolution and origin)."""
    return World(meta_event(NOW - 86_400_000, chunk_rows=rows, chunk_cols=cols))


def _on_event_loop() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def test_zone_geometry_is_checked_on_a_worker_thread_not_the_event_loop(monkeypatch) -> None:
    seen: list[bool] = []
    real = core_annotations.validate

    def spy(annotation):
        seen.append(_on_event_loop())
        return real(annotation)

    monkeypatch.setattr(core_annotations, "validate", spy)
    w = World()
    assert w.create(keep_out("aisle", square(0, 3, 2))).status_code == 201
    r = w.client.put(
        "/api/v1/annotations/" + w.at(NOW)[next(iter(w.at(NOW)))]["id"],
        json=keep_out("aisle", square(0, 3, 3)),
        headers=w.as_(OPERATOR),
    )
    assert r.status_code == 200, r.text
    assert seen == [False, False]


@pytest.mark.parametrize("n", [4, 100, 501, 600, 5_000, MAX_ZONE_VERTICES])
def test_a_self_crossing_zone_of_any_size_is_a_422_saying_so(n) -> None:
    w = World()
    rng = random.Random(n)
    ring = [[x / 10 + 10, y / 10 + 12] for x, y in crossing_ring(rng, n)]
    r = w.create(keep_out("crossing", ring))
    assert r.status_code == 422, r.text
    assert "crosses itself" in r.json()["detail"]
    simple = [[x / 10 + 10, y / 10 + 12] for x, y in star_ring(rng, n)]
    assert w.create(keep_out("simple", simple)).status_code == 201


@pytest.mark.parametrize(
    ("hole", "says"),
    [
        (square(20, 20, 1), "hole 0 lies outside the polygon"),
        (square(3, 6, 4), "hole 0 crosses the polygon's edge"),
        (square(1, 4, 1), None),
    ],
)
def test_a_hole_outside_or_across_its_polygon_is_a_422(hole, says) -> None:
    w = World()
    r = w.create(keep_out("holed", square(0, 3, 5), holes=[hole]))
    if says is None:
        assert r.status_code == 201, r.text
        return
    assert r.status_code == 422, r.text
    assert says in r.json()["detail"]


def test_the_largest_allowed_zone_passes_and_one_vertex_more_is_refused_naming_the_cap() -> None:
    w = World()
    doc = largest_allowed_zone_doc(radius_m=8.0, cx=10.0, cy=12.0)
    r = w.create(doc)
    assert r.status_code == 201, r.text
    doc["holes"][0].insert(
        1, [(doc["holes"][0][0][0] + doc["holes"][0][1][0]) / 2, doc["holes"][0][0][1] - 1e-6]
    )
    r = w.create(doc)
    assert r.status_code == 422 and "MAX_ZONE_VERTICES" in r.json()["detail"], r.text


def test_a_zone_of_101_rings_of_500_vertices_is_refused_early_naming_the_cap(monkeypatch) -> None:
    """The shape that held the event loop for 21.7 s: 50,500 vertices, over the cap."""
    w = World()
    rng = random.Random(1)
    # Millimetres, as a UI sends them: 50,500 vertices within the default 1 MiB body.
    holes = [
        [[round(x / 100 + 10, 3), round(y / 100 + 12, 3)] for x, y in star_ring(rng, 500)]
        for _ in range(100)
    ]
    outer = [[round(x + 10, 3), round(y + 12, 3)] for x, y in star_ring(rng, 500, radius=9)]
    body = keep_out("heavy", outer, holes=holes)
    geometry_checked: list[int] = []
    real = core_annotations.check_zone_rings

    def spy(polygon, holes):
        geometry_checked.append(len(holes))
        return real(polygon, holes)

    monkeypatch.setattr(core_annotations, "check_zone_rings", spy)
    r = w.create(body)
    assert r.status_code == 422, r.text
    assert "MAX_ZONE_VERTICES" in r.text
    # Early: refused by the count of its vertices, before any geometry was computed.
    assert geometry_checked == []


def test_a_zone_spanning_too_many_map_cells_is_refused_naming_the_cap() -> None:
    """On a 9,000 x 9,000 px map, a zone over all of it (81 M cells) is refused; one over
    a quarter of it is stored. Without a map frame the cells cannot be counted: stored."""
    w = _big_map(90, 90)
    whole = [
        [ORIGIN[0], ORIGIN[1]],
        [ORIGIN[0] + 450, ORIGIN[1]],
        [ORIGIN[0] + 450, ORIGIN[1] + 450],
    ]
    r = w.create(keep_out("everything", whole))
    assert r.status_code == 422, r.text
    assert "MAX_ZONE_MASK_CELLS" in r.json()["detail"]
    quarter = [[x, y] for x, y in square(ORIGIN[0], ORIGIN[1], 225)]
    assert w.create(keep_out("quarter", quarter)).status_code == 201


# --- import-mask ------------------------------------------------------------------------


def _import(w: World, image: bytes, resolution: float = RESOLUTION):
    return w.client.post(
        "/api/v1/annotations/import-mask",
        headers=w.as_(OPERATOR),
        json={
            "yaml": mask_yaml(resolution, ORIGIN),
            "image_base64": base64.b64encode(image).decode(),
        },
    )


@pytest.fixture
def decodes(monkeypatch) -> list[tuple[int, int]]:
    """The sizes of the images whose pixels were decoded (Pillow's load)."""
    seen: list[tuple[int, int]] = []
    real = ImageFile.ImageFile.load

    def load(self):
        seen.append(self.size)
        return real(self)

    monkeypatch.setattr(ImageFile.ImageFile, "load", load)
    return seen


def test_a_png_bomb_is_refused_from_its_header_before_decoding(decodes) -> None:
    """12,000 x 14,000 px of zeros in ~0.2 MB: a 422 naming both sizes, fast, no pixel
    decoded; so for every size within one pixel of the map's but the map's own."""
    w = World()
    bomb = png_bomb(12_000, 14_000)
    assert len(bomb) < 1_000_000
    r = _import(w, bomb)
    assert r.status_code == 422, r.text
    assert "12000 x 14000 px but the map is 500 x 400 px" in r.json()["detail"]
    for size in ((499, 400), (501, 400), (500, 399), (500, 401), (400, 500)):
        r = _import(w, png_bomb(*size))
        assert r.status_code == 422 and "but the map is 500 x 400 px" in r.text, size
    assert decodes == []
    assert _import(w, png_bomb(500, 400)).status_code == 201
    assert decodes and set(decodes) == {(500, 400)}


@pytest.mark.parametrize(
    "size",
    [
        (2**31 - 1, 2**31 - 1),
        (20_000, 20_000),  # past Pillow's own guard (twice Image.MAX_IMAGE_PIXELS)
        (Image.MAX_IMAGE_PIXELS // 400 + 1, 400),  # past its warning only
        (1, 10**9),
        (500, 400),  # the map's own size, but no pixels
    ],
)
def test_a_header_of_any_size_without_pixels_is_a_fast_422(size, decodes) -> None:
    w = World()
    r = _import(w, png_header_only(*size))
    assert r.status_code == 422, r.text
    if size != (500, 400):
        assert decodes == [] and "500 x 400 px" in r.json()["detail"]


def test_a_mask_for_a_map_over_the_pixel_cap_is_refused_before_decoding(decodes) -> None:
    w = _big_map(90, 90)
    r = _import(w, png_bomb(9_000, 9_000))
    assert r.status_code == 422, r.text
    assert "MAX_MASK_PIXELS" in r.json()["detail"]
    assert decodes == []


def test_a_checkerboard_mask_is_refused_before_tracing_naming_the_cap() -> None:
    """A 1,000 x 1,000 px checkerboard: a few kB of PNG, half a million areas."""
    w = _big_map(10, 10)
    image = mask_png(checkerboard(1000, 1000))
    assert len(image) < 10_000
    r = _import(w, image)
    assert r.status_code == 422, r.text
    assert "MAX_TRACED_EDGES" in r.json()["detail"]
    assert not w.publisher.records[w.settings.topic_annotation_events]


def test_a_mask_area_with_too_many_vertices_is_refused_naming_the_cap() -> None:
    """One connected area whose outline has more than MAX_ZONE_VERTICES corners (combs
    on a spine) but few enough pixel edges to be traced."""
    w = _big_map(10, 10)
    mask = np.zeros((1000, 1000), dtype=bool)
    mask[:, 0] = True
    for band in range(12):
        mask[3 * band, :] = True
        mask[3 * band + 1, 0::2] = True
    r = _import(w, mask_png(mask))
    assert r.status_code == 422, r.text
    assert "MAX_ZONE_VERTICES" in r.json()["detail"]


def _encoded(pixels: np.ndarray, fmt: str) -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, format=fmt)
    return out.getvalue()


@pytest.mark.parametrize("fmt", ["BMP", "GIF", "TIFF", "JPEG", "WEBP", "ICO"])
def test_a_mask_in_another_format_than_png_or_pgm_is_refused(fmt, decodes) -> None:
    w = World()
    pixels = np.full((400, 500), 254, dtype=np.uint8)
    pixels[10:20, 10:20] = 0
    if fmt == "ICO":
        pixels = pixels[:256, :256]
    r = _import(w, _encoded(pixels, fmt))
    assert r.status_code == 422, r.text
    assert "PNG or PGM" in r.json()["detail"]
    assert decodes == []


def test_truncated_or_garbled_images_are_a_422() -> None:
    w = World()
    good = mask_png(checkerboard(500, 400, cell=50))
    assert _import(w, good).status_code == 201
    for image in (
        png_bomb(500, 400, truncate=True),
        good[: len(good) // 2],
        good[:40],
        b"\x89PNG\r\n\x1a\n",
        b"",
        b"P5\n500 400\n255\n" + b"\0" * 100,
        b"P5\n500 400\n65535\n",
        bytes(random.Random(3).randbytes(5000)),
    ):
        r = _import(w, image)
        assert r.status_code == 422, (image[:20], r.text)


def test_a_mask_is_decoded_on_a_worker_thread_not_the_event_loop(monkeypatch) -> None:
    seen: list[bool] = []
    real = costmap_filters.read_mask

    def spy(*args, **kwargs):
        seen.append(_on_event_loop())
        return real(*args, **kwargs)

    monkeypatch.setattr(annotations_router, "read_mask", spy)
    w = World()
    assert _import(w, mask_png(checkerboard(500, 400, cell=100))).status_code == 201
    assert seen == [False]
