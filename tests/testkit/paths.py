"""Where the repository's files are, for every test module (whatever its folder under tests/)."""

from __future__ import annotations

from pathlib import Path

#: The repository.
ROOT = Path(__file__).resolve().parents[2]
#: The recorded bags (bags/README.md).
BAGS = ROOT / "bags"
#: The Ventoux Pleiades crops, RPCs, SRTM crop and reference grids (tests/data/ventoux/README.md).
DATA = ROOT / "tests" / "data" / "ventoux"
#: The message definitions of parproj_msgs.
MSG_DIR = ROOT / "msg_defs" / "msg"
