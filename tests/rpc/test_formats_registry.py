"""The RPC format table (parproj_ros/rpc/formats/) is the single source of the formats.

Every row with a writer round-trips through the one entrance; every row GDAL reads gives the
same model through GDAL (io/raster.py's reader) as through its own parser; and a format added
to the table (a fixture: a JSON file with a pixel origin of 0.5) is detected, read, shifted,
found beside an image and named in the errors through every entrance, with no other edit.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from parproj_ros import rpc
from parproj_ros.io import raster, scene_import
from parproj_ros.rpc import formats
from parproj_ros.rpc.formats import FORMATS, RPCFormatSpec, RPCValues

DATA = Path(__file__).resolve().parents[1] / "data" / "ventoux"
LEFT = rpc.read_rpc(DATA / "left_image.geom")


@pytest.mark.parametrize("name", [n for n, s in FORMATS.items() if s.write is not None])
def test_every_writable_format_round_trips_through_the_entrance(name: str, tmp_path: Path) -> None:
    path = tmp_path / "model"  # no extension: the content decides
    rpc.write_rpc(path, LEFT, name)
    assert rpc.detect_rpc_format(path) == name
    model, source = rpc.read_rpc_file(path)
    assert source == "model"
    # DIMAP carries no ERR_BIAS / ERR_RAND and its offsets go through +1 and -1
    got, want = model.as_vector()[2:], LEFT.as_vector()[2:]
    np.testing.assert_allclose(got, want, rtol=1e-15 if name == "dimap" else 0.0, atol=0.0)


@pytest.mark.parametrize(
    "name", [n for n, s in FORMATS.items() if s.gdal is not None and s.write is not None]
)
def test_gdal_and_the_own_parser_give_the_same_model(name: str, tmp_path: Path) -> None:
    """The io side reads through the same table: GDAL for its rows, the bits of the parser."""
    path = tmp_path / f"scene{FORMATS[name].extensions[0] if FORMATS[name].extensions else ''}"
    rpc.write_rpc(path, LEFT, name)
    via_gdal, source = raster.read_rpc_file(path)
    assert "GDAL" in source
    assert np.array_equal(via_gdal.as_vector(), rpc.read_rpc(path).as_vector())


def test_write_rpc_names_the_formats_it_writes() -> None:
    with pytest.raises(rpc.RPCFormatError, match=r"cannot write RPC format 'nitf' \(written: "):
        rpc.write_rpc("x", LEFT, "nitf")


# ---- a format added to the table -------------------------------------------------------------


def _read_json(path: Path) -> RPCValues:
    data = json.loads(path.read_text())
    return {k: (np.array(v) if isinstance(v, list) else float(v)) for k, v in data.items()}


def _write_json(path: Path, model: rpc.RPCModel) -> None:
    v = model.as_vector()
    names = ("line_off", "samp_off", "lat_off", "long_off", "height_off", "line_scale",
             "samp_scale", "lat_scale", "long_scale", "height_scale")  # fmt: skip
    data: dict[str, object] = {n: float(v[2 + i]) + (0.5 if i < 2 else 0.0)
                               for i, n in enumerate(names)}  # fmt: skip
    for i, n in enumerate(
        ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff")
    ):
        data[n] = [float(c) for c in v[12 + 20 * i : 32 + 20 * i]]
    path.write_text(json.dumps(data))


JSON = RPCFormatSpec(
    name="json",
    label=".rpc.json",
    detect=lambda path, head: head.lstrip().startswith(b'{"line_off"'),
    read=_read_json,
    pixel_origin=lambda path: 0.5,  # (0.5, 0.5) = centre of the first pixel in the file
    write=_write_json,
    extensions=(".json",),
    sidecar_suffixes=(".rpc.json",),
)


@pytest.fixture
def with_json(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(FORMATS, "json", JSON)


def _image(path: Path) -> Path:
    """A 40 x 40 TIFF without RPC (GDAL finds none)."""
    tifffile.imwrite(path, np.tile(np.arange(40, dtype=np.uint8), (40, 1)))
    return path


@pytest.mark.usefixtures("with_json")
def test_a_format_added_to_the_table_works_through_every_entrance(tmp_path: Path) -> None:
    path = tmp_path / "a.rpc.json"
    rpc.write_rpc(path, LEFT, "json")
    assert rpc.detect_rpc_format(path) == "json"
    expected = LEFT.as_vector()
    expected[:2] = -1.0  # no errors in the file
    for model in (rpc.read_rpc(path), raster.read_rpc_file(path)[0]):
        # the pixel origin is subtracted: the 0.5 the writer added comes back off
        assert np.array_equal(model.as_vector(), expected)
    # beside an image GDAL finds no RPC for, it is found by the image's stem
    model, source = scene_import.find_rpc(_image(tmp_path / "a.tif"))
    assert source == "a.rpc.json"
    assert np.array_equal(model.as_vector(), expected)
    # and named when missing
    with pytest.raises(raster.SceneImportError, match=r"no b\.geom; no b\.rpc\.json; no RPC_"):
        scene_import.find_rpc(_other(tmp_path))
    (tmp_path / "junk").write_text("hello: world\n")
    with pytest.raises(rpc.RPCFormatError, match=r"junk: not a known RPC format \(.*\.rpc\.json"):
        rpc.read_rpc(tmp_path / "junk")


def _other(tmp_path: Path) -> Path:
    folder = tmp_path / "other"
    folder.mkdir()
    return _image(folder / "b.tif")


def test_the_format_table_is_where_the_search_order_comes_from() -> None:
    """GDAL's own sidecars first (found, they are GDAL's skip to explain), then the stem
    sidecars only our parsers read, then folder patterns."""
    order = [s.name for s in formats.sidecar_formats()]
    assert order == ["rpb", "rpc_txt", "geom", "dimap"]
    assert formats.sidecars_looked_for(Path("/d/a.tif"), gdal=True) == "no a.RPB / a_RPC.TXT"


def test_docs_hold_the_format_table() -> None:
    """docs/extending.md's table of formats is the rendered table (paste it when a row changes)."""
    doc = Path(__file__).resolve().parents[2] / "docs" / "extending.md"
    assert formats.formats_markdown() in doc.read_text()
