"""The resampling kernel table (parproj_ros/imaging/kernels.py) is the single source.

Each row's OpenCV flag exists, its declared support is enough to render a block from the lines
it keeps (bit-identical to rendering from the whole image) and is needed (one line fewer changes
the result), and the ``interpolation`` parameter's choices and docs/extending.md's table come
from it; a kernel added to the table (a fixture) works through the parameter, the config and
the pipeline's flag without any other edit.
"""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from parproj_ros.core import params
from parproj_ros.imaging import kernels
from parproj_ros.imaging.kernels import KERNELS, Kernel
from parproj_ros.imaging.resample import kernel_flag

ROOT = Path(__file__).resolve().parents[2]

#: A 2x3 map (output col, row) -> (sample, line) with dyadic entries: every product and sum is
#: exact in floating point, so moving the origin by whole lines changes no weight.
AFFINE = np.array([[0.75, 0.125, 3.25], [0.0625, 0.625, 50.375]])
TILE = (40, 40)  # output rows, columns


def _lines_reached() -> tuple[float, float]:
    """Smallest and largest source line the tile's map reaches (a linear map: at corners)."""
    rows, cols = TILE
    corners = np.array([[0, 0, 1], [cols - 1, 0, 1], [0, rows - 1, 1], [cols - 1, rows - 1, 1]])
    lines = corners @ AFFINE[1]
    return float(lines.min()), float(lines.max())


def _renders_alike(k: Kernel) -> bool:
    """Whether the tile rendered from lines floor(lo) - s + 1 .. floor(hi) + s alone (s the
    kernel's support) is bit-identical to the tile rendered from the whole image."""
    rng = np.random.default_rng(3)
    image = rng.uniform(0.0, 1000.0, (160, 90)).astype(np.float32)
    flags = getattr(cv2, k.opencv) | cv2.WARP_INVERSE_MAP
    rows, cols = TILE
    whole = cv2.warpAffine(image, AFFINE, (cols, rows), flags=flags, borderValue=-1.0)
    lo, hi = _lines_reached()
    first = math.floor(lo) - k.support_lines + 1
    last = math.floor(hi) + k.support_lines
    kept = image[first : last + 1]
    m = AFFINE.copy()
    m[1, 2] -= first
    block = cv2.warpAffine(kept, m, (cols, rows), flags=flags, borderValue=-1.0)
    return bool(np.array_equal(whole, block))


@pytest.mark.parametrize("name", list(KERNELS))
def test_each_row_is_an_opencv_kernel_with_enough_support(name: str) -> None:
    k = KERNELS[name]
    assert kernel_flag(name) == getattr(cv2, k.opencv)
    assert k.support_lines >= 1 and k.description
    assert _renders_alike(k)
    # the support is needed, not just enough: one line fewer on each side changes the tile
    assert not _renders_alike(Kernel(k.name, k.opencv, k.support_lines - 1, ""))


def test_unknown_kernel_is_named() -> None:
    with pytest.raises(ValueError, match=r"interpolation 'sinc': not a .* \(known: linear, cubic"):
        kernel_flag("sinc")


def test_parameter_choices_and_docs_come_from_the_table() -> None:
    (row,) = [p for p in params.PARAMS if p.name == "interpolation"]
    assert row.choices == tuple(KERNELS)
    assert row.default == next(iter(KERNELS))
    assert all(repr(n) in row.description for n in KERNELS)
    assert kernels.kernels_markdown() in (ROOT / "docs" / "extending.md").read_text()


def test_a_kernel_added_to_the_table_works_without_other_edits(tmp_path: Path) -> None:
    """A fixture row (nearest neighbour) added before the parameter table is built: it is a
    choice of ``interpolation``, the config takes it and the pipeline's flag is OpenCV's."""
    script = textwrap.dedent(
        """
        from parproj_ros.imaging import kernels
        kernels.KERNELS["nearest"] = kernels.Kernel("nearest", "INTER_NEAREST", 1, "nearest")
        import cv2
        from parproj_ros.core import params
        from parproj_ros.core.config import config_from_values
        from parproj_ros.core.normalization import interpolation_flag
        (row,) = [p for p in params.PARAMS if p.name == "interpolation"]
        assert row.choices == ("linear", "cubic", "nearest"), row.choices
        assert "'nearest'" in row.description, row.description
        cfg = config_from_values({"interpolation": "nearest"})
        assert interpolation_flag(cfg) == cv2.INTER_NEAREST
        try:
            config_from_values({"interpolation": "sinc"})
        except ValueError as err:
            assert "nearest" in str(err), err
        else:
            raise AssertionError("sinc accepted")
        print("ok")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "ok"
