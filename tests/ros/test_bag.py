"""rosbag2 MCAP bags: our writer and reader against rosbags and mcap-ros2-support, truncation."""

from __future__ import annotations

import shutil
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.reader import SeekingReader, make_reader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import Image

from parproj_ros.ros.bag import (
    BagError,
    BagReader,
    BagWriter,
    _chunk_records,
    message_definition,
    qos_yaml,
)

pytestmark = pytest.mark.ros  # messages built and (de)serialized with rclpy

T0 = 1_700_000_000_000_000_000  # ns
DT = 50_000_000  # ns between frames
N_FRAMES = 12
UNKNOWN_TYPE = "unknown_pkg/msg/Foo"
UNKNOWN_DEF = "int32 a\nstring b\n"


# ------------------------------------------------------------------ test data


def make_image(i: int) -> Image:
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    img = (1000 + 20 * xx + 10 * yy + i).astype("<u2")  # a smooth ramp: compresses well
    m = Image()
    m.header.stamp.sec = 1_700_000_000 + i
    m.header.stamp.nanosec = 1000 * i
    m.header.frame_id = "scanner"
    m.height, m.width = h, w
    m.encoding = "mono16"
    m.is_bigendian = 0
    m.step = 2 * w
    m.data = img.tobytes()
    return m


def make_odom(i: int) -> Odometry:
    m = Odometry()
    m.header.stamp.sec = 1_700_000_000 + i
    m.header.frame_id = "map"
    m.child_frame_id = "base_link"
    m.pose.pose.position.x = 1000.0 + 7.5 * i
    m.pose.pose.position.y = -250.25 * i
    m.pose.pose.position.z = 680_000.0
    m.pose.pose.orientation.z = np.sin(0.01 * i)
    m.pose.pose.orientation.w = np.cos(0.01 * i)
    m.pose.covariance = [float(k) / (i + 1) for k in range(36)]
    m.twist.twist.linear.x = 6800.0
    m.twist.twist.angular.z = -1e-4 * i
    m.twist.covariance = [0.5] * 36
    return m


def make_diag(i: int) -> DiagnosticArray:
    m = DiagnosticArray()
    m.header.stamp.sec = 1_700_000_000 + i
    for k, level in enumerate((DiagnosticStatus.OK, DiagnosticStatus.WARN)):
        s = DiagnosticStatus()
        s.level = level
        s.name = f"parproj/check{k}"
        s.message = f"frame {i} status {k}"
        s.hardware_id = "sim"
        s.values = [KeyValue(key="sigma0_px", value=f"{0.1 * i:.3f}"), KeyValue(key="k", value="")]
        m.status.append(s)
    return m


def foo_cdr(a: int, b: str) -> bytes:
    raw = b.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<iI", a, len(raw)) + raw


def write_sample(path: Path, frames: int = N_FRAMES, **kw: Any) -> dict[tuple[str, int], Any]:
    """Write the sample bag; return {(topic, log_time_ns): message or (a, b)} in write order."""
    written: dict[tuple[str, int], Any] = {}
    with BagWriter(path, **kw) as bag:
        bag.add_topic("/scanner/image", "sensor_msgs/msg/Image", qos="sensor_data")
        bag.add_topic("/nav/odom", "nav_msgs/msg/Odometry")
        bag.add_topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", "transient_local")
        bag.add_topic("/mystery", UNKNOWN_TYPE, definition=UNKNOWN_DEF)
        for i in range(frames):
            t = T0 + i * DT
            for topic, msg in (
                ("/scanner/image", make_image(i)),
                ("/nav/odom", make_odom(i)),
                ("/diagnostics", make_diag(i)),
            ):
                bag.write(topic, msg, t + 1)
                written[(topic, t + 1)] = msg
            if i % 3 == 0:
                bag.write_raw("/mystery", foo_cdr(i, f"foo{i}"), t + 2)
                written[("/mystery", t + 2)] = (i, f"foo{i}")
    return written


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[tuple[str, int], Any]]:
    path = tmp_path_factory.mktemp("bags") / "sample"
    written = write_sample(path)
    return path, written


# ------------------------------------------------------------------ comparison helpers


def plain(obj: Any, ref: Any) -> dict[str, Any]:
    """Field values of ``obj`` (any decoder's message) structured like the rclpy ``ref``."""
    return {
        name: _value(getattr(obj, name), getattr(ref, name), ftype)
        for name, ftype in ref.get_fields_and_field_types().items()
    }


def _value(v: Any, r: Any, ftype: str) -> Any:
    if hasattr(r, "get_fields_and_field_types"):
        return plain(v, r)
    if ftype == "octet":
        return v[0] if isinstance(v, bytes | bytearray) else int(v)
    if ftype.startswith("sequence<") or ftype.endswith("]"):
        items, refs = list(v), list(r)
        if refs and hasattr(refs[0], "get_fields_and_field_types"):
            return [plain(a, b) for a, b in zip(items, refs, strict=True)]
        return [x.item() if hasattr(x, "item") else x for x in items]
    return v.item() if hasattr(v, "item") else v


def assert_same(obj: Any, ref: Any) -> None:
    assert plain(obj, ref) == plain(ref, ref)


# ------------------------------------------------------------------ layout and metadata


def test_folder_layout_and_metadata(bag: tuple[Path, dict]) -> None:
    path, written = bag
    assert sorted(p.name for p in path.iterdir()) == ["metadata.yaml", "sample_0.mcap"]
    meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9
    assert meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["sample_0.mcap"]
    assert meta["message_count"] == len(written)
    times = [t for _, t in written]
    assert meta["starting_time"]["nanoseconds_since_epoch"] == min(times)
    assert meta["duration"]["nanoseconds"] == max(times) - min(times)
    assert meta["files"][0]["path"] == "sample_0.mcap"
    assert meta["files"][0]["message_count"] == len(written)
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/scanner/image"]["message_count"] == N_FRAMES
    img = topics["/scanner/image"]["topic_metadata"]
    assert img["type"] == "sensor_msgs/msg/Image"
    assert img["serialization_format"] == "cdr"
    assert img["offered_qos_profiles"][0]["reliability"] == "best_effort"
    assert img["type_description_hash"].startswith("RIHS01_")
    assert topics["/mystery"]["topic_metadata"]["type_description_hash"] == ""


def test_mcap_records_as_rosbag2_writes_them(bag: tuple[Path, dict]) -> None:
    path, _ = bag
    with (path / "sample_0.mcap").open("rb") as f:
        reader = SeekingReader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert len(schemas) == len(summary.schemas) == 4  # one schema per type
        for name in ("sensor_msgs/msg/Image", "nav_msgs/msg/Odometry"):
            assert schemas[name].encoding == "ros2msg"
            assert schemas[name].data.decode() == message_definition(name)[1]
        assert schemas[UNKNOWN_TYPE].data.decode() == UNKNOWN_DEF
        for ch in summary.channels.values():
            assert ch.message_encoding == "cdr"
            assert set(ch.metadata) == {"offered_qos_profiles", "topic_type_hash"}
        image_ch = next(c for c in summary.channels.values() if c.topic == "/scanner/image")
        assert image_ch.metadata["offered_qos_profiles"] == qos_yaml("sensor_data")
        assert yaml.safe_load(image_ch.metadata["offered_qos_profiles"])[0]["depth"] == 5
        meta = list(reader.iter_metadata())
        assert [m.name for m in meta] == ["rosbag2"]
        inner = yaml.safe_load(meta[0].metadata["serialized_metadata"])
        assert inner["version"] == 9
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}


def test_schema_text_matches_rosbag2_layout() -> None:
    enc, text = message_definition("std_msgs/msg/Header")
    header = _share_file("std_msgs", "Header")
    time = _share_file("builtin_interfaces", "Time")
    assert enc == "ros2msg"
    assert text == header + "\n" + "=" * 80 + "\nMSG: builtin_interfaces/Time\n" + time
    # Odometry: dependencies sorted, depth first, each once, named as in the field declaration
    _, odom = message_definition("nav_msgs/msg/Odometry")
    assert [ln for ln in odom.splitlines() if ln.startswith("MSG: ")] == [
        "MSG: geometry_msgs/PoseWithCovariance",
        "MSG: geometry_msgs/Pose",
        "MSG: geometry_msgs/Point",
        "MSG: geometry_msgs/Quaternion",
        "MSG: geometry_msgs/TwistWithCovariance",
        "MSG: geometry_msgs/Twist",
        "MSG: geometry_msgs/Vector3",
        "MSG: std_msgs/Header",
        "MSG: builtin_interfaces/Time",
    ]
    assert odom.count("=" * 80 + "\n") == 9


def _share_file(pkg: str, name: str) -> str:
    import sys

    return (Path(sys.prefix) / "share" / pkg / "msg" / f"{name}.msg").read_text()


def test_definitions_found_through_ament_prefix_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # rosbag2's own test case (rosbag2_test_msgdefs ComplexMsg), in a prefix of our making
    msg_dir = tmp_path / "share" / "fake_defs_pkg" / "msg"
    msg_dir.mkdir(parents=True)
    (msg_dir / "ComplexMsg.msg").write_text("fake_defs_pkg/BasicMsg b\n")
    (msg_dir / "BasicMsg.msg").write_text("float32 c\n")
    idl_dir = tmp_path / "share" / "fake_idl_pkg" / "msg"
    idl_dir.mkdir(parents=True)
    basic_idl = "module fake_idl_pkg {\n  module msg {\n    struct BasicIdl {\n        float x;\n    };\n  };\n};\n"  # noqa: E501
    complex_idl = '#include "fake_idl_pkg/msg/BasicIdl.idl"\n\nmodule fake_idl_pkg {};\n'
    (idl_dir / "BasicIdl.idl").write_text(basic_idl)
    (idl_dir / "ComplexIdl.idl").write_text(complex_idl)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    assert message_definition("fake_defs_pkg/msg/ComplexMsg") == (
        "ros2msg",
        "fake_defs_pkg/BasicMsg b\n\n" + "=" * 80 + "\nMSG: fake_defs_pkg/BasicMsg\nfloat32 c\n",
    )
    sep = "=" * 80 + "\n"
    assert message_definition("fake_idl_pkg/msg/ComplexIdl") == (
        "ros2idl",
        sep + "IDL: fake_idl_pkg/msg/ComplexIdl\n" + complex_idl + "\n"
        + sep + "IDL: fake_idl_pkg/msg/BasicIdl\n" + basic_idl,
    )  # fmt: skip
    with pytest.raises(LookupError):
        message_definition("fake_defs_pkg/msg/Missing")


# ------------------------------------------------------------------ reading back


def test_direct_writing_gives_the_same_bag(tmp_path: Path) -> None:
    """The same messages written past the page cache (``direct``) and through it: the same
    records, read by our reader and by mcap's."""
    write_sample(tmp_path / "a" / "sample")
    write_sample(tmp_path / "b" / "sample", direct=True)
    with BagWriter(tmp_path / "probe", direct=True) as probe:
        assert probe.direct  # this machine's disk takes O_DIRECT
    with BagWriter(tmp_path / "cached") as cached:
        assert not cached.direct
    got = []
    for d in ("a", "b"):
        path = tmp_path / d / "sample"
        ours = [(m.topic, m.log_time_ns, bytes(m.data)) for m in BagReader(path).raw_messages()]
        with (path / "sample_0.mcap").open("rb") as f:
            theirs = [
                (c.topic, m.log_time, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)
            ]
        assert ours == theirs and len(ours) > 30
        got.append(ours)
    # rclpy leaves its alignment padding unset: messages it serialized are compared by topic,
    # time and size; those written as bytes ("/mystery") byte for byte.
    a, b = ([(t, ns, len(d) if t != "/mystery" else d) for t, ns, d in g] for g in got)
    assert a == b


def test_our_reader(bag: tuple[Path, dict]) -> None:
    path, written = bag
    reader = BagReader(path)
    assert reader.topics() == {
        "/scanner/image": "sensor_msgs/msg/Image",
        "/nav/odom": "nav_msgs/msg/Odometry",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
        "/mystery": UNKNOWN_TYPE,
    }
    counts = {"/scanner/image": N_FRAMES, "/nav/odom": N_FRAMES, "/diagnostics": N_FRAMES,
              "/mystery": 4}  # fmt: skip
    assert reader.message_counts() == counts
    assert reader.recovery.complete and reader.recovery.error is None
    assert reader.recovery.messages_read == reader.recovery.messages_expected == len(written)
    assert reader.qos("/scanner/image") == "sensor_data"
    assert reader.qos("/diagnostics") == "transient_local"
    assert reader.qos("/nav/odom") == "reliable"
    assert reader.unknown_types() == {"/mystery": UNKNOWN_TYPE}
    got = list(reader.messages())
    assert [(t, ts) for t, _, ts in got] == [k for k in written if k[0] != "/mystery"]
    for topic, msg, ts in got:
        assert type(msg) is type(written[(topic, ts)])
        assert_same(msg, written[(topic, ts)])
    img = next(m for t, m, _ in got if t == "/scanner/image")
    assert np.frombuffer(img.data, "<u2").reshape(48, 64)[1, 1] == 1030
    # the unknown type is skipped and counted, not fatal; its raw bytes are still there
    assert reader.skipped == {"/mystery": 4}
    raw = [r for r in reader.raw_messages("/mystery")]
    assert [r.data for r in raw] == [foo_cdr(i, f"foo{i}") for i in range(0, N_FRAMES, 3)]
    assert {r.msgtype for r in raw} == {UNKNOWN_TYPE}


def test_topic_and_time_filters(bag: tuple[Path, dict]) -> None:
    path, _ = bag
    reader = BagReader(path / "sample_0.mcap")  # a single file works too
    start, end = T0 + 3 * DT, T0 + 7 * DT + 1  # frames 3..6 (stamp t+1), end exclusive
    got = list(reader.messages(["/nav/odom", "/diagnostics"], start_ns=start, end_ns=end))
    assert [(t, ts) for t, _, ts in got] == [
        (topic, T0 + i * DT + 1) for i in range(3, 7) for topic in ("/nav/odom", "/diagnostics")
    ]
    assert reader.start_ns == T0 + 1
    assert reader.end_ns == T0 + (N_FRAMES - 1) * DT + 1


def test_topic_filter_reads_only_chunks_holding_the_topics(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A topic filter skips, by the summary's chunk indexes, the chunks without those topics
    (the cameras of a bag of strips: one chunk read, not every strip); without a summary (a
    cut-off file) every chunk is read, and the messages are the same."""
    import parproj_ros.ros.bag as bagmod

    path = tmp_path / "two"
    with BagWriter(path, chunk_size=1000, topic_compression={"/nav/odom": "lz4"}) as bw:
        bw.add_topic("/scanner/image", "sensor_msgs/msg/Image")
        bw.add_topic("/nav/odom", "nav_msgs/msg/Odometry")
        bw.write("/nav/odom", make_odom(0), T0)
        for i in range(6):  # images: chunks of their own
            bw.write("/scanner/image", make_image(i), T0 + (i + 1) * DT)
        bw.write("/nav/odom", make_odom(1), T0 + 10 * DT)
    read: list[int] = []
    real = bagmod._chunk

    def counting(body: bytes, *args: Any) -> Any:
        read.append(len(body))
        return real(body, *args)

    monkeypatch.setattr(bagmod, "_chunk", counting)
    mcap_file = path / "two_0.mcap"
    got = [(t, ts) for t, _, ts in BagReader(path).messages(["/nav/odom"])]
    assert got == [("/nav/odom", T0), ("/nav/odom", T0 + 10 * DT)]
    assert len(read) == 2  # the two odometry chunks
    read.clear()
    list(BagReader(path).messages())
    assert len(read) >= 8
    # cut off before the summary: no chunk index, every chunk read, the same messages
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap_file.read_bytes()[: mcap_file.stat().st_size - 200])
    read.clear()
    again = [(t, ts) for t, _, ts in BagReader(cut).messages(["/nav/odom"])]
    assert again == got and len(read) >= 8


def test_rosbags_reads_the_folder(bag: tuple[Path, dict]) -> None:
    path, written = bag
    kilted = get_typestore(Stores.ROS2_KILTED)
    own = get_typestore(Stores.EMPTY)  # built only from the definitions stored in the bag
    seen = set()
    with RosbagsReader(path) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert {t: c.msgtype for t, c in conns.items()} == BagReader(path).topics()
        assert conns["/scanner/image"].msgcount == N_FRAMES
        assert conns["/scanner/image"].ext.offered_qos_profiles[0].depth == 5
        assert reader.message_count == len(written)
        for c in reader.connections:
            assert c.msgdef.data  # our schema text parses as .msg for rosbags
            own.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        for conn, ts, raw in reader.messages():
            ref = written[(conn.topic, ts)]
            decoded = own.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == "/mystery":
                assert (decoded.a, decoded.b) == ref
            else:
                assert_same(kilted.deserialize_cdr(raw, conn.msgtype), ref)
                assert_same(decoded, ref)
            seen.add((conn.topic, ts))
    assert seen == set(written)


def test_mcap_ros2_decodes_with_our_schema_text(bag: tuple[Path, dict]) -> None:
    path, written = bag
    seen = set()
    with (path / "sample_0.mcap").open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            ref = written[(channel.topic, message.log_time)]
            assert schema is not None and schema.name == BagReader(path).topics()[channel.topic]
            if channel.topic == "/mystery":
                assert (decoded.a, decoded.b) == ref
            else:
                assert_same(decoded, ref)
            seen.add((channel.topic, message.log_time))
    assert seen == set(written)


def test_chunks_are_compressed(bag: tuple[Path, dict]) -> None:
    path, written = bag
    raw_bytes = sum(len(serialize_message(m)) for k, m in written.items() if k[0] != "/mystery")
    image_bytes = sum(len(m.data) for k, m in written.items() if k[0] == "/scanner/image")
    size = (path / "sample_0.mcap").stat().st_size
    assert size < image_bytes < raw_bytes
    assert size < 0.5 * raw_bytes
    plain_path = path.parent / "uncompressed"
    write_sample(plain_path, compression="none")
    assert (plain_path / "uncompressed_0.mcap").stat().st_size > raw_bytes
    assert [m for _, m, _ in BagReader(plain_path).messages()] == [
        m for _, m, _ in BagReader(path).messages()
    ]


def test_custom_interface_package(tmp_path: Path) -> None:
    """Types of parproj_msgs (built into the venv): found, stored, decoded by all three readers."""
    import parproj_msgs.msg as msgs  # built into the venv by ./dev setup (CI included)

    classes = [getattr(msgs, n) for n in dir(msgs) if not n.startswith("_")]
    classes = [c for c in classes if hasattr(c, "get_fields_and_field_types")]
    assert classes
    path = tmp_path / "custom"
    written = {}
    with BagWriter(path) as bag:
        for k, cls in enumerate(classes):
            msg = cls()
            topic = f"/custom/{cls.__name__.lower()}"
            bag.write(topic, msg, T0 + k)
            written[(topic, T0 + k)] = msg
    reader = BagReader(path)
    assert reader.unknown_types() == {}
    for topic, msg, ts in reader.messages():
        assert_same(msg, written[(topic, ts)])
    with (path / "custom_0.mcap").open("rb") as f:
        mr = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in mr.iter_decoded_messages():
            assert_same(decoded, written[(channel.topic, message.log_time)])
    own = get_typestore(Stores.EMPTY)
    with RosbagsReader(path) as rb:
        for c in rb.connections:
            own.register(get_types_from_msg(c.msgdef.data, c.msgtype))
        for conn, ts, raw in rb.messages():
            assert_same(own.deserialize_cdr(raw, conn.msgtype), written[(conn.topic, ts)])


# ------------------------------------------------------------------ cut-off recordings


def file_order(mcap_path: Path) -> list[tuple[str, int]]:
    with mcap_path.open("rb") as f:
        return [
            (ch.topic, msg.log_time)
            for _, ch, msg in make_reader(f).iter_messages(log_time_order=False)
        ]


def message_record_ends(mcap_path: Path) -> list[int]:
    """File offsets at which each message record ends, in file order (uncompressed chunks)."""
    ends: list[tuple[int, int]] = []
    with mcap_path.open("rb") as f:
        data_start = 0
        for record in StreamReader(f, emit_chunks=True).records:
            if isinstance(record, Chunk):
                assert record.compression == ""
                data_start = f.tell() - len(record.data)
                chunk_data = record.data
            elif isinstance(record, MessageIndex):
                for _, offset in record.records:
                    (length,) = struct.unpack_from("<Q", chunk_data, offset + 1)
                    ends.append((offset, data_start + offset + 9 + length))
    return [e for _, e in sorted(ends)]


@pytest.mark.parametrize("compression", ["zstd", "none"])
@pytest.mark.parametrize("chunk_size", [16 * 1024, 4 * 1024 * 1024])
def test_cut_off_file_yields_complete_messages(
    tmp_path: Path, compression: str, chunk_size: int
) -> None:
    path = tmp_path / "rec"
    written = write_sample(path, compression=compression, chunk_size=chunk_size)
    full = path / "rec_0.mcap"
    order = file_order(full)
    assert len(order) == len(written)
    data = full.read_bytes()
    cut = int(0.6 * len(data))
    cut_dir = tmp_path / "cut"
    cut_dir.mkdir()
    (cut_dir / "rec_0.mcap").write_bytes(data[:cut])
    shutil.copy(path / "metadata.yaml", cut_dir / "metadata.yaml")

    reader = BagReader(cut_dir)
    rec = reader.recovery
    assert not rec.complete
    assert rec.error and "cut off" in rec.error
    assert 0 < rec.truncated_bytes < len(data) - cut + chunk_size + 200_000
    assert rec.missing_bytes and rec.missing_bytes > 0
    assert rec.messages_expected == len(written)
    got = list(reader.raw_messages())
    assert len(got) == rec.messages_read == sum(reader.message_counts().values())
    assert rec.messages_lost == len(written) - len(got)
    # a prefix of the file, in order, and every decoded value intact
    assert [(t, ts) for t, _, _, ts in got] == order[: len(got)]
    for topic, msg, ts in reader.messages():
        assert_same(msg, written[(topic, ts)])
    assert reader.skipped.get("/mystery", 0) == sum(1 for t, *_ in got if t == "/mystery")
    with full.open("rb") as f:
        summary = SeekingReader(f).get_summary()
    assert summary is not None
    if compression == "none":
        # exactly the messages whose records end before the cut
        assert len(got) == sum(1 for end in message_record_ends(full) if end <= cut)
    else:
        whole = [c for c in summary.chunk_indexes if c.chunk_start_offset + c.chunk_length <= cut]
        in_whole_chunks = 0
        with full.open("rb") as f:
            for c in whole:
                f.seek(c.chunk_start_offset + c.chunk_length)
                stream = StreamReader(f, skip_magic=True).records
                for _ in c.message_index_offsets:
                    in_whole_chunks += len(next(stream).records)  # type: ignore[attr-defined]
        assert len(got) == in_whole_chunks + rec.partial_chunk_messages


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_cut_inside_the_only_chunk(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "rec"
    # 4 MiB chunks: one chunk of about 1.5 MB, which zstd / lz4 compress as a series of blocks
    written = write_sample(path, frames=200, compression=compression)
    full = path / "rec_0.mcap"
    with full.open("rb") as f:
        summary = SeekingReader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) == 1
    chunk = summary.chunk_indexes[0]
    cut = chunk.chunk_start_offset + int(0.6 * chunk.chunk_length)
    cut_file = tmp_path / "cut.mcap"
    cut_file.write_bytes(full.read_bytes()[:cut])
    reader = BagReader(cut_file)
    rec = reader.recovery
    assert not rec.complete and "CHUNK record" in (rec.error or "")
    assert rec.truncated_bytes == cut - chunk.chunk_start_offset
    assert rec.missing_bytes == chunk.chunk_length - (cut - chunk.chunk_start_offset)
    assert rec.messages_expected is None  # a bare file: no metadata.yaml
    got = list(reader.messages())
    # salvaged from the readable start of the chunk (a streaming decompressor for zstd / lz4)
    assert 0 < rec.partial_chunk_messages == rec.messages_read < len(written)
    assert len(got) + sum(reader.skipped.values()) == rec.messages_read
    assert [(t, ts) for t, _, ts in got] == [
        k for k in file_order(full)[: rec.messages_read] if k[0] != "/mystery"
    ]
    for topic, msg, ts in got:
        assert_same(msg, written[(topic, ts)])


def test_file_without_summary_and_footer(tmp_path: Path) -> None:
    path = tmp_path / "rec"
    written = write_sample(path, chunk_size=16 * 1024)
    full = path / "rec_0.mcap"
    with full.open("rb") as f:
        summary = SeekingReader(f).get_summary()
    assert summary is not None
    data_end = max(c.chunk_start_offset + c.chunk_length + c.message_index_length
                   for c in summary.chunk_indexes)  # fmt: skip
    cut = tmp_path / "nofooter.mcap"
    cut.write_bytes(full.read_bytes()[:data_end])  # a recorder killed between chunks
    reader = BagReader(cut)
    assert not reader.recovery.complete
    assert reader.recovery.truncated_bytes == 0
    assert reader.recovery.missing_bytes == 0
    assert reader.recovery.messages_read == len(written)
    assert reader.message_counts()["/scanner/image"] == N_FRAMES
    assert len(list(reader.messages())) == len(written) - 4  # all but the unknown type


def with_second_chunk_damaged(
    tmp_path: Path, damage: Callable[[bytearray, int, int], None], compression: str = "zstd"
) -> BagReader:
    """The sample bag in 16 KiB chunks, its second chunk record damaged in place.

    ``damage(data, start, length)``: changes the file's bytes; the chunk record starts at
    ``start`` (its opcode) and is ``length`` bytes long.
    """
    path = tmp_path / "rec"
    write_sample(path, chunk_size=16 * 1024, compression=compression)
    full = path / "rec_0.mcap"
    with full.open("rb") as f:
        summary = SeekingReader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    bad = summary.chunk_indexes[1]
    data = bytearray(full.read_bytes())
    damage(data, bad.chunk_start_offset, bad.chunk_length)
    full.write_bytes(bytes(data))
    return BagReader(path)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_corrupt_chunk_is_skipped_and_reported(tmp_path: Path, compression: str) -> None:
    def flip(data: bytearray, start: int, length: int) -> None:
        data[start + length - 20] ^= 0xFF  # inside the (packed) records

    reader = with_second_chunk_damaged(tmp_path, flip, compression)
    got = list(reader.raw_messages())
    assert 0 < len(got) < reader.recovery.messages_read
    assert not reader.recovery.complete and reader.recovery.corrupt_chunks == 1
    assert "skipped" in (reader.recovery.error or "")
    if compression == "none":  # nothing to decompress: the CRC finds it
        assert "CRC-32" in (reader.recovery.error or "")


def test_chunk_declaring_a_huge_size_is_skipped(tmp_path: Path) -> None:
    """A damaged uncompressed_size (2**40 bytes) is not handed to the decompressor."""

    def huge(data: bytearray, start: int, length: int) -> None:
        struct.pack_into("<Q", data, start + 9 + 16, 2**40)  # uncompressed_size

    reader = with_second_chunk_damaged(tmp_path, huge)
    got = list(reader.raw_messages())
    assert 0 < len(got) < reader.recovery.messages_read
    assert reader.recovery.corrupt_chunks == 1
    assert "over 4294967296" in (reader.recovery.error or "")


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_compressed_frame_larger_than_its_chunk_is_refused(compression: str) -> None:
    """A frame whose own header claims more than the chunk's uncompressed_size is refused
    before decompression (the decompressor allocates what the frame claims); the chunk is then
    skipped as damaged (``_chunk`` turns the ValueError into a skipped chunk, above)."""
    import lz4.frame
    import zstandard

    records = b"\x05" + b"x" * 4999  # what the frame holds: 5000 bytes
    packed = zstandard.compress(records) if compression == "zstd" else lz4.frame.compress(records)

    def body(declared: int) -> bytes:
        head = struct.pack("<QQQI", 0, 1, declared, 0)
        name = compression.encode()
        return head + struct.pack("<I", len(name)) + name + struct.pack("<Q", len(packed)) + packed

    assert bytes(_chunk_records(body(5000), True)) == records
    with pytest.raises(ValueError, match="frame larger than the 1000 bytes"):
        _chunk_records(body(1000), True)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_chunks_of_changing_sizes_read_as_mcaps_reader_reads_them(
    tmp_path: Path, compression: str
) -> None:
    """Chunk records are read into reused memory: every message still comes out intact.

    Messages larger than the chunk size make chunks of their own, smaller ones share chunks:
    the chunk sizes go up and down. The messages are all kept and compared at the end, against
    mcap's own reader, so that a message still viewing memory read into again would show.
    """
    path = tmp_path / "sizes"
    rng = np.random.default_rng(11)
    sizes = [70_000, 3_000, 250_000, 10, 9, 120_000, 5_000, 64 * 1024, 1, 300_000, 200]
    with BagWriter(path, compression=compression, chunk_size=64 * 1024) as bw:
        bw.add_topic("blob", "std_msgs/msg/String")
        for i, n in enumerate(sizes * 3):
            bw.write_raw("blob", rng.integers(0, 256, n, dtype=np.uint8).tobytes(), T0 + i)
    got = [(m.data, m.log_time_ns) for m in BagReader(path).raw_messages()]
    with (path / "sizes_0.mcap").open("rb") as f:
        theirs = [(bytes(m.data), m.log_time) for _, _, m in make_reader(f).iter_messages()]
    assert len(got) == len(sizes) * 3
    assert got == theirs
    assert all(type(d) is bytes for d, _ in got)


def test_not_a_bag(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(BagError):
        BagReader(junk)
    with pytest.raises(FileNotFoundError):
        BagReader(tmp_path / "nothing")


# ------------------------------------------------------------------ writer behaviour


def test_writer_finishes_the_bag_on_error(tmp_path: Path) -> None:
    path = tmp_path / "crash"
    with pytest.raises(RuntimeError), BagWriter(path) as bag:
        bag.write("/nav/odom", make_odom(0), T0)  # topic added on first write
        raise RuntimeError("simulated failure")
    reader = BagReader(path)
    assert reader.recovery.complete
    assert reader.topics() == {"/nav/odom": "nav_msgs/msg/Odometry"}
    with RosbagsReader(path) as rb:
        assert rb.message_count == 1


def test_writer_refuses_misuse(tmp_path: Path) -> None:
    path = tmp_path / "b"
    with BagWriter(path) as bag:
        bag.add_topic("/odom", "nav_msgs/msg/Odometry")
        with pytest.raises(TypeError):
            bag.write("/odom", make_image(0), T0)
        with pytest.raises(BagError):
            bag.write_raw("/undeclared", b"\x00\x01\x00\x00", T0)
        with pytest.raises(ValueError):
            bag.add_topic("/x", "nav_msgs/msg/Odometry", qos="fast")
        with pytest.raises(LookupError):
            bag.add_topic("/y", "no_such_pkg/msg/Nothing")
    with pytest.raises(FileExistsError):
        BagWriter(path)
    with BagWriter(path, overwrite=True) as bag:
        bag.write("/odom", make_odom(1), T0)
    assert BagReader(path).message_counts() == {"/odom": 1}


def test_chunk_compression_per_topic(tmp_path: Path) -> None:
    """Issue 11: image topics may be written with lz4 or none while the rest stays zstd."""
    from std_msgs.msg import String

    path = tmp_path / "mixed"
    with BagWriter(path, topic_compression={"a": "none"}) as bw:
        bw.add_topic("a", "std_msgs/msg/String")
        bw.add_topic("b", "std_msgs/msg/String")
        bw.add_topic("c", "std_msgs/msg/String", compression="lz4")
        for i in range(5):
            for t in "abc":
                m = String()
                m.data = f"{t}{i}" * 100
                bw.write(t, m, 10 + i)
    with open(next(path.glob("*.mcap")), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes  # type: ignore[union-attr]
    assert {c.compression for c in chunks} == {"", "zstd", "lz4"}
    got = [(m.topic, m.msg.data) for m in BagReader(path).messages()]
    assert got == [(t, f"{t}{i}" * 100) for i in range(5) for t in "abc"]
    with pytest.raises(ValueError):
        BagWriter(tmp_path / "bad", topic_compression={"a": "gzip"})


def test_image_views_read_strips_and_count_broken_ones(tmp_path: Path) -> None:
    """messages(image_views=True): Images as cdr.ImageView equal to rclpy's; a cut Image is
    counted in decode_errors (reported by ``parproj process``), the others still read."""
    from rclpy.serialization import serialize_message

    from parproj_ros.ros import conversions as conv
    from parproj_ros.ros.cdr import ImageView

    path = tmp_path / "views"
    with BagWriter(path) as bw:
        bw.add_topic("/scanner/image", "sensor_msgs/msg/Image")
        bw.add_topic("/nav/odom", "nav_msgs/msg/Odometry")
        bw.write("/scanner/image", make_image(0), T0)
        bw.write_raw("/scanner/image", serialize_message(make_image(1))[:40], T0 + DT)
        bw.write("/nav/odom", make_odom(2), T0 + 2 * DT)
        bw.write("/scanner/image", make_image(3), T0 + 3 * DT)
    reader = BagReader(path)
    got = list(reader.messages(image_views=True))
    assert [(m.topic, m.log_time_ns) for m in got] == [
        ("/scanner/image", T0),
        ("/nav/odom", T0 + 2 * DT),
        ("/scanner/image", T0 + 3 * DT),
    ]
    assert isinstance(got[0].msg, ImageView) and isinstance(got[1].msg, Odometry)
    assert reader.decode_errors == {"/scanner/image": 1}
    ref = [m.msg for m in BagReader(path).messages(["/scanner/image"])]
    for view, msg in zip((got[0].msg, got[2].msg), ref, strict=True):
        assert view.header.frame_id == msg.header.frame_id
        np.testing.assert_array_equal(conv.image_to_array(view), conv.image_to_array(msg))
