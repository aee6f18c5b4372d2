"""``parproj import`` reads by windows: peak memory does not grow with the raster (issue 10).

A generated 6000 x 6000 uint16 pair (72 MB per image, tiled GeoTIFF with the Ventoux RPCs of two
crops of the full scenes) is imported in a subprocess; its peak RSS (ru_maxrss) is compared with
the import of a 500 x 500 pair in the same kind of subprocess. Holding either image would add
72 MB (and the old right-padding copy as much again); reading strips of 64 rows adds about one
strip (0.8 MB) plus the bag writer's chunk buffer.

Three images (``parproj import A B C``, the same importer with a pair selection), scaled small:
3300 x 3300 against 1100 x 1100 (22 MB against 2.4 MB per image; both above the 1024 px side of
the constant-band check's decimated read, whose size is bounded), GDAL's block cache held to 2 MB
so that it cannot hide a whole image.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from rasterio.windows import Window
from testkit.rasters import DATA, to_rasterio

from parproj_ros import rpc

SCRIPT = """
import resource, sys
from parproj_ros.apps.importer import import_pair
import_pair(sys.argv[1], sys.argv[2], sys.argv[3], heights=(500.0, 1500.0), log=lambda _: None)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""

SCRIPT_3 = """
import resource, sys
from parproj_ros.io import raster as raster_io
from parproj_ros.apps.importer import import_scenes
raster_io.GDAL_CACHE_MB = 2
import_scenes(sys.argv[1:4], sys.argv[4], pairs="all", heights=(500.0, 1500.0), log=lambda _: None)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""

#: (file name, Ventoux RPC, crop origin (line, sample) in its full scene).
PAIR = (("left", "left", (5000.0, 5000.0)), ("right", "right", (5162.0, 4915.0)))
#: A third acquisition: another crop of the left scene, overlapping both.
THIRD = ("third", "left", (5100.0, 4950.0))


def make_pair(
    folder: Path, size: int, views: tuple[tuple[str, str, Any], ...] = PAIR
) -> list[Path]:
    """size x size uint16 tiled GeoTIFFs (written by windows) with crop RPCs in tag 50844."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, scene, origin in views:
        model = rpc.read_rpc(DATA / f"{scene}_image.geom").shifted(-origin[0], -origin[1])
        p = folder / f"{name}.tif"
        with rasterio.open(
            p,
            "w",
            driver="GTiff",
            width=size,
            height=size,
            count=1,
            dtype="uint16",
            tiled=True,
            blockxsize=256,
            blockysize=256,
            rpcs=to_rasterio(model),
        ) as dst:
            cols = np.arange(size, dtype=np.uint32)
            for r0 in range(0, size, 512):
                n = min(512, size - r0)
                rows = np.arange(r0, r0 + n, dtype=np.uint32)[:, None]
                block = ((rows * 7 + cols[None, :] * 13) % 4096).astype(np.uint16)
                dst.write(block, 1, window=Window(0, r0, size, n))
        paths.append(p)
    return paths


def peak_rss_mb(images: list[Path], out: Path) -> float:
    """Peak RSS of the import of ``images`` (two: import_pair, three: import_scenes), MB."""
    res = subprocess.run(
        [
            sys.executable,
            "-c",
            SCRIPT_3 if len(images) == 3 else SCRIPT,
            *map(str, images),
            str(out),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(res.stdout.split()[-1]) / 1024.0  # ru_maxrss is in kB on Linux


@pytest.mark.ros  # the imports run in subprocesses: they write bags (parproj_msgs, rclpy)
@pytest.mark.slow
def test_import_peak_memory_does_not_grow_with_the_raster(tmp_path: Path) -> None:
    small = peak_rss_mb(make_pair(tmp_path / "small", 500), tmp_path / "bag_small")
    large = peak_rss_mb(make_pair(tmp_path / "large", 6000), tmp_path / "bag_large")
    print(f"peak RSS: 500 x 500 pair {small:.0f} MB, 6000 x 6000 pair {large:.0f} MB")
    assert large - small < 30.0  # one image is 72 MB


def test_three_images_read_by_windows(tmp_path: Path) -> None:
    """``parproj import A B C``: every image by strips (the old multi-image path held each)."""
    views = (*PAIR, THIRD)
    small = peak_rss_mb(make_pair(tmp_path / "small", 1100, views), tmp_path / "bag_small")
    large = peak_rss_mb(make_pair(tmp_path / "large", 3300, views), tmp_path / "bag_large")
    print(f"peak RSS: 3 x 1100 x 1100 {small:.0f} MB, 3 x 3300 x 3300 {large:.0f} MB")
    # Holding the images (the old path) costs 3 x 22 MB = 66 MB more; reading by windows costs
    # 1-6 MB more here, up to 13 MB on a loaded machine (GDAL's threads): the bound is below
    # one image.
    assert large - small < 20.0  # one image is 22 MB
