"""`mapservice zones import-mask`: a keep-out mask's files posted to the API with the
operator's token (the real API app over a memory store), refusals that say why, and the
command's help."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image

from mapservice.adapters.ros_map import RosMap, meta_for
from mapservice.api.context import context_of
from mapservice.cli import build_parser
from mapservice.core.events import make_envelope
from mapservice.robot import zones_cli
from mapservice.robot.zones_cli import MaskFiles, import_mask, mask_files, refusal
from tests.api.test_annotations import NOW, OPERATOR, READER, World

FLOOR = RosMap(np.full((30, 40), 254, dtype=np.uint8), 0.05, (-1.0, -2.0, 0.0))
YAML = (
    "image: {image}\nmode: trinary\nresolution: 0.05\norigin: [-1.0, -2.0, 0]\nnegate: 0\n"
    "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
)


def write_mask(tmp_path, keep_out: np.ndarray, name: str = "mask"):
    pixels = np.where(keep_out, 0, 254).astype(np.uint8)
    header = f"P5\n{pixels.shape[1]} {pixels.shape[0]}\n255\n".encode()
    (tmp_path / f"{name}.pgm").write_bytes(header + pixels.tobytes())
    (tmp_path / f"{name}.yaml").write_text(YAML.format(image=f"{name}.pgm"))
    return tmp_path / f"{name}.yaml"


@pytest.fixture
def keep_out() -> np.ndarray:
    mask = np.zeros((30, 40), dtype=bool)
    mask[5:12, 8:20] = True  # a rack's surroundings
    mask[20:26, 30:36] = True  # a charger's
    return mask


def test_import_mask_posts_the_files_and_the_keep_out_mask_exports_the_same_pixels(
    tmp_path, keep_out
) -> None:
    w = World(make_envelope("admin", NOW - 1000, NOW - 1000, meta_for(FLOOR)))
    path = write_mask(tmp_path, keep_out)
    w.client.headers["Authorization"] = f"Bearer {OPERATOR}"
    answer = import_mask(w.client, path, "racks")
    assert len(answer["ids"]) == 2
    events = w.store_published()
    assert {e.payload.annotation.name for e in events} == {"racks 1", "racks 2"}
    context_of(w.client.app).recent_edits.edits = []
    r = w.client.get(
        "/api/v1/costmap-filters/keepout/mask.pgm", params={"at": str(answer["at_ms"])}
    )
    exported = np.asarray(Image.open(io.BytesIO(r.content)))
    assert np.array_equal(exported == 0, keep_out)
    # The PGM went as a PNG of the same pixels.
    _, sent = mask_files(path)
    assert sent[:4] == b"\x89PNG"
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(sent))) == 0, keep_out)


def test_a_reader_token_is_refused_with_what_to_do(tmp_path, keep_out) -> None:
    w = World(make_envelope("admin", NOW - 1000, NOW - 1000, meta_for(FLOOR)))
    w.client.headers["Authorization"] = f"Bearer {READER}"
    with pytest.raises(httpx.HTTPStatusError) as caught:
        import_mask(w.client, write_mask(tmp_path, keep_out), "racks")
    message = refusal(caught.value)
    assert "(403)" in message and "operator" in message
    assert w.store_published() == []


def test_mask_files_by_image_or_yaml_and_what_is_missing(tmp_path, keep_out) -> None:
    path = write_mask(tmp_path, keep_out)
    assert mask_files(path.with_suffix(".pgm"))[0] == path.read_text()
    (tmp_path / "lone.pgm").write_bytes(b"P5\n1 1\n255\n\x00")
    with pytest.raises(MaskFiles, match="no map_server YAML next to it"):
        mask_files(tmp_path / "lone.pgm")
    (tmp_path / "bad.yaml").write_text("resolution: 0.05\n")
    with pytest.raises(MaskFiles, match="names no image"):
        mask_files(tmp_path / "bad.yaml")
    (tmp_path / "gone.yaml").write_text(YAML.format(image="gone.pgm"))
    with pytest.raises(MaskFiles, match="cannot read the mask image"):
        mask_files(tmp_path / "gone.yaml")


def test_the_command_line_has_help_and_fails_saying_why(tmp_path, capsys, monkeypatch) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["zones", "import-mask", "--help"])
    help_text = capsys.readouterr().out
    assert "keep-out" in help_text and "--token" in help_text and "operator token" in help_text
    args = build_parser().parse_args(
        [
            "zones",
            "import-mask",
            str(tmp_path / "none.yaml"),
            "--api",
            "http://127.0.0.1:9",
            "--token",
            "t",
        ]
    )
    with pytest.raises(SystemExit, match="cannot read the mask YAML"):
        args.func(args)
    monkeypatch.setenv(zones_cli.OPERATOR_TOKEN_ENV, "from-env")
    assert zones_cli.operator_token(None) == "from-env" and zones_cli.operator_token("x") == "x"
