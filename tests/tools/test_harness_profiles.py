"""tools.harness.join_ros_domain: which Fast DDS profile each run gets (bench, overload test)."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pytest

from tools.harness import FAST_REPAIR_PROFILE, SHM_PROFILE, join_ros_domain

KEY = "FASTDDS_DEFAULT_PROFILES_FILE"


@pytest.fixture(autouse=True)
def environ_restored() -> Iterator[None]:
    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


def test_profile_selection(tmp_path: Path) -> None:
    env = join_ros_domain(150, tmp_path / "log", fast_repair=True)
    assert env[KEY] == os.environ[KEY] == str(FAST_REPAIR_PROFILE)
    env = join_ros_domain(150, tmp_path / "log", shm=True, fast_repair=True)
    assert env[KEY] == str(SHM_PROFILE)  # shared memory wins: large samples leave UDP
    env = join_ros_domain(150, tmp_path / "log")
    assert KEY not in env and KEY not in os.environ
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_fast_repair_profile_sets_only_the_writers_heartbeat() -> None:
    """A default data_writer profile with heartbeat_period 0.1 s, and nothing else (no
    transport, no QoS that ROS sets), in the schema's element names (fastdds_profiles.xsd:
    writerTimesType)."""
    ns = {"d": "http://www.eprosima.com"}
    root = ET.parse(FAST_REPAIR_PROFILE).getroot()
    (profiles,) = root.findall("d:profiles", ns)
    (writer,) = list(profiles)
    assert writer.tag == "{http://www.eprosima.com}data_writer"
    assert writer.get("is_default_profile") == "true"
    (times,) = list(writer)
    (period,) = list(times)
    assert period.tag.endswith("heartbeat_period")
    sec = int(period.findtext("d:sec", namespaces=ns) or "")
    nanosec = int(period.findtext("d:nanosec", namespaces=ns) or "")
    assert sec + nanosec * 1e-9 == pytest.approx(0.1)
