"""Foreign bags (issue 25, item 5): a ROS 1 recording in MCAP and a rosbag2 sqlite3 bag.

Every command that reads a bag reads it through ``parproj_ros.ros.bag.BagReader``, which
refuses both by name, in one line saying what to do. Each foreign bag is made here in
``tmp_path`` (the ROS 1 one with the mcap writer, profile ``ros1``, a sensor_msgs/Image channel
with a ``ros1msg`` schema; the sqlite3 one with rosbags' rosbag2 writer) and given to every
command in a subprocess, the console script as a user runs it: exit 2, nothing on stdout,
exactly one line on stderr naming the file and the kind.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from parproj_ros.ros.bag import BagError, BagReader

pytestmark = pytest.mark.ros

#: The console script installed next to the interpreter (.venv/bin/parproj).
PARPROJ = Path(sys.executable).with_name("parproj")

#: ROS 1's sensor_msgs/Image definition (ros1msg), with its Header.
ROS1_IMAGE = b"""std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
uint32 seq
time stamp
string frame_id
"""

ROS1_KIND = "a ROS 1 bag in MCAP"
SQLITE_KIND = "a rosbag2 sqlite3 bag"


def ros1_image(seq: int, width: int = 4, height: int = 2) -> bytes:
    """A ROS 1 serialized mono8 sensor_msgs/Image (little-endian, length-prefixed strings)."""
    frame, enc = b"left", b"mono8"
    pixels = bytes(range(width * height))
    return b"".join(
        (
            struct.pack("<III", seq, seq, 0),  # seq, stamp sec, stamp nsec
            struct.pack("<I", len(frame)) + frame,
            struct.pack("<II", height, width),
            struct.pack("<I", len(enc)) + enc,
            struct.pack("<BI", 0, width),
            struct.pack("<I", len(pixels)) + pixels,
        )
    )


def write_ros1_mcap(path: Path, *, profile: str = "ros1") -> Path:
    """A ROS 1 recording in MCAP: a left/image_strip channel of three images."""
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile=profile, library="tests/ros/test_foreign_bags.py")
        sid = w.register_schema(name="sensor_msgs/Image", encoding="ros1msg", data=ROS1_IMAGE)
        cid = w.register_channel(topic="/left/image_strip", message_encoding="ros1", schema_id=sid)
        for i in range(3):
            t = 1_000_000_000 + i * 1_000_000
            w.add_message(channel_id=cid, log_time=t, publish_time=t, data=ros1_image(i))
        w.finish()
    return path


def write_sqlite_bag(folder: Path) -> Path:
    """A rosbag2 sqlite3 bag (rosbags' writer): a navigation topic of two Odometry messages."""
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Rosbag2Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    odometry = store.types["nav_msgs/msg/Odometry"]
    header = store.types["std_msgs/msg/Header"]
    stamp = store.types["builtin_interfaces/msg/Time"]
    pose_cov = store.types["geometry_msgs/msg/PoseWithCovariance"]
    twist_cov = store.types["geometry_msgs/msg/TwistWithCovariance"]
    pose, twist = store.types["geometry_msgs/msg/Pose"], store.types["geometry_msgs/msg/Twist"]
    point, quat = (
        store.types["geometry_msgs/msg/Point"],
        store.types["geometry_msgs/msg/Quaternion"],
    )
    vec = store.types["geometry_msgs/msg/Vector3"]

    with Rosbag2Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection("/navigation", odometry.__msgtype__, typestore=store)
        for i in range(2):
            msg = odometry(
                header=header(stamp=stamp(sec=i, nanosec=0), frame_id="map"),
                child_frame_id="base_link",
                pose=pose_cov(
                    pose=pose(
                        position=point(x=float(i), y=0.0, z=600.0),
                        orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                    covariance=np.zeros(36),
                ),
                twist=twist_cov(
                    twist=twist(linear=vec(x=1.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36),
                ),
            )
            w.write(conn, i * 1_000_000_000, store.serialize_cdr(msg, odometry.__msgtype__))
    return folder


def ros1_mcap(tmp: Path) -> Path:
    return write_ros1_mcap(tmp / "ros1.mcap")


def ros1_mcap_no_profile(tmp: Path) -> Path:
    """A ROS 1 recording whose writer left the profile empty: known by its encodings."""
    return write_ros1_mcap(tmp / "ros1_noprofile.mcap", profile="")


def sqlite_folder(tmp: Path) -> Path:
    return write_sqlite_bag(tmp / "sq_bag")


def sqlite_file(tmp: Path) -> Path:
    (db3,) = write_sqlite_bag(tmp / "sq_bag").glob("*.db3")
    return db3


def sqlite_folder_without_metadata(tmp: Path) -> Path:
    folder = write_sqlite_bag(tmp / "sq_bag")
    (folder / "metadata.yaml").unlink()
    return folder


#: (name, maker, the kind its refusal names).
FOREIGN: list[tuple[str, Callable[[Path], Path], str]] = [
    ("ros1_mcap", ros1_mcap, ROS1_KIND),
    ("ros1_mcap_no_profile", ros1_mcap_no_profile, ROS1_KIND),
    ("sqlite3_folder", sqlite_folder, SQLITE_KIND),
    ("sqlite3_db3_file", sqlite_file, SQLITE_KIND),
    ("sqlite3_folder_no_metadata", sqlite_folder_without_metadata, SQLITE_KIND),
]

#: Every command that reads a bag, as argv after ``parproj`` (BAG: the bag, OUT: a new path).
COMMANDS: dict[str, list[str]] = {
    "process": ["process", "BAG", "-o", "OUT", "-q"],
    "replay": ["replay", "BAG", "--rate", "0", "-q"],
    "evaluate": ["evaluate", "BAG"],
    "dsm": ["dsm", "BAG", "-o", "OUT"],
    "fuse": ["fuse", "BAG", "BAG", "-o", "OUT"],
}


@pytest.mark.parametrize(("name", "make", "kind"), FOREIGN, ids=[f[0] for f in FOREIGN])
def test_bag_reader_refuses_a_foreign_bag_by_name(
    tmp_path: Path, name: str, make: Callable[[Path], Path], kind: str
) -> None:
    """The one place: BagReader's error is one line, the path first, the kind and the advice."""
    bag = make(tmp_path)
    with pytest.raises(BagError) as info:
        BagReader(bag)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{bag}: {kind}"), text
    assert "rosbags-convert" in text and "--dst-storage mcap" in text, text
    assert info.value.path == str(bag)


def test_the_ros1_refusal_names_what_marks_it(tmp_path: Path) -> None:
    """Profile, message encoding and schema encoding are named as the file has them."""
    with pytest.raises(BagError, match=r"\(profile 'ros1'\)"):
        BagReader(ros1_mcap(tmp_path))
    with pytest.raises(BagError, match=r"\(message encoding 'ros1', schema encoding 'ros1msg'\)"):
        BagReader(ros1_mcap_no_profile(tmp_path))


def test_the_advice_for_sqlite_converts_to_a_bag_that_reads(tmp_path: Path) -> None:
    """The command the refusal gives (rosbags-convert) makes an MCAP bag BagReader reads."""
    bag = sqlite_folder(tmp_path)
    with pytest.raises(BagError) as info:
        BagReader(bag)
    assert f"rosbags-convert --src {bag} --dst OUT --dst-storage mcap" in str(info.value)
    out = tmp_path / "converted"
    convert = Path(sys.executable).with_name("rosbags-convert")
    subprocess.run(
        [convert, "--src", bag, "--dst", out, "--dst-storage", "mcap"],
        check=True,
        capture_output=True,
        timeout=60,
    )
    reader = BagReader(out)
    assert reader.topics() == {"/navigation": "nav_msgs/msg/Odometry"}
    xs = [m.msg.pose.pose.position.x for m in reader.messages()]
    assert xs == [0.0, 1.0]


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize(("name", "make", "kind"), FOREIGN, ids=[f[0] for f in FOREIGN])
def test_every_command_refuses_a_foreign_bag_in_one_line(
    tmp_path: Path, name: str, make: Callable[[Path], Path], kind: str, command: str
) -> None:
    """Exit 2, nothing on stdout (nothing published or written), one stderr line: file, kind."""
    bag = make(tmp_path)
    out = tmp_path / "out"
    argv = [str(bag) if a == "BAG" else str(out) if a == "OUT" else a for a in COMMANDS[command]]
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    p = subprocess.run([str(PARPROJ), *argv], capture_output=True, text=True, timeout=60, env=env)
    lines = p.stderr.splitlines()
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert p.stdout == "", p.stdout
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith(f"parproj {command}: {bag}: {kind}"), lines[0]
    assert not out.exists()
