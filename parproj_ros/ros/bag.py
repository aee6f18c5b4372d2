"""rosbag2-compatible MCAP bags: writing, reading, and recovering cut-off recordings.

A bag is a folder ``<name>/`` holding ``<name>_0.mcap`` and ``metadata.yaml`` (rosbag2 format
version 9, storage identifier ``mcap``), laid out the way rosbag2's MCAP storage plugin writes it:

* MCAP profile ``ros2``; one schema per message type, named like ``sensor_msgs/msg/Image``, with
  encoding ``ros2msg`` and as text the type's ``.msg`` file followed, for every nested type, by a
  line of 80 ``=``, a line ``MSG: <type>`` and that type's ``.msg`` file. The nested types are
  found, ordered and named exactly as rosbag2's ``LocalMessageDefinitionSource`` does it: the
  dependencies of each definition in sorted order, depth first, each type once, under the name
  written in the field declaration (``MSG: std_msgs/Header``, not ``std_msgs/msg/Header``). When a
  ``.msg`` file is missing the whole definition falls back to ``ros2idl``, as in rosbag2.
* channels with message encoding ``cdr`` and metadata ``offered_qos_profiles`` (the YAML text
  rosbag2 writes) and ``topic_type_hash`` (RIHS01 hash from the type's installed ``.json``).
* a ``rosbag2`` metadata record holding the serialized bag metadata, chunked and indexed data
  (zstd chunk compression by default) and a summary section.

The ``.msg`` files are looked up in ``share/<package>/msg/`` of the ament prefixes
(``AMENT_PREFIX_PATH``), of the prefix the package's Python module is installed in, and of
``sys.prefix``; so interface packages installed into the virtual environment later (for example
``parproj_msgs``) work without configuration.

Reading goes through the records one by one rather than through the summary index, so a file cut
off mid-write (a recorder that was killed: no footer, no summary, maybe half a chunk) still yields
every message that is complete in the file, including those in the readable part of a cut-off
compressed chunk. What was lost is reported in :attr:`BagReader.recovery`.

All times are integer nanoseconds (``*_ns``); for rosbag2 bags they are nanoseconds since the Unix
epoch of the recording host's clock (the log time of each message).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import importlib.util
import json
import os
import re
import shlex
import shutil
import stat
import struct
import sys
import threading
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, NamedTuple, cast

import mcap
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Header, Schema
from mcap.writer import CompressionType, Writer

from ..core import contract
from ..io.direct import DirectFile
from .cdr import CdrError, parse_image

__all__ = [
    "QOS_PRESETS",
    "BagError",
    "BagMessage",
    "BagReader",
    "BagWriter",
    "RawMessage",
    "Recovery",
    "get_message_class",
    "message_definition",
    "msgtype_of",
    "qos_yaml",
]

#: rosbag2 metadata format version written to ``metadata.yaml``.
ROSBAG2_VERSION = 9
#: Default MCAP chunk size (bytes, uncompressed) before a chunk is compressed and written.
DEFAULT_CHUNK_SIZE = 4 * 1024 * 1024

QosName = Literal["reliable", "sensor_data", "transient_local"]
Compression = Literal["zstd", "lz4", "none"]

# RMW_DURATION_INFINITE as rosbag2 writes it for the offered profiles of a Fast DDS publisher.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}

#: QoS presets that ``BagWriter.add_topic`` records as the offered profile of a topic (the rclpy
#: defaults: ``QoSProfile(depth=10)``, ``qos_profile_sensor_data``, and a latched depth-1 topic;
#: the interface contract's :data:`~parproj_ros.core.contract.BAG_QOS`).
QOS_PRESETS: dict[str, dict[str, Any]] = {
    name: q.as_dict() for name, q in contract.BAG_QOS.items()
}

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")
_CHUNK_HEAD = struct.Struct("<QQQI")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
#: Largest uncompressed chunk read (bytes): a CDR message is under 4 GiB (32-bit lengths), and
#: writers close a chunk at a few MB or at the one message larger than that.
MAX_CHUNK_RECORDS = 2**32


#: Largest ``metadata.yaml`` read (bytes); rosbag2 writes a few kB per file and topic.
MAX_METADATA_BYTES = 16 * 1024 * 1024


class BagError(ValueError):
    """A file or folder is not a readable bag, or a bag is used the wrong way.

    Attributes:
        path: the bag, file or folder at fault, when known; the message then starts with it.
    """

    def __init__(self, message: str, path: str | os.PathLike[str] | None = None) -> None:
        self.path = None if path is None else str(path)
        if self.path is not None and not message.startswith(self.path):
            message = f"{self.path}: {message}"
        super().__init__(message)


# --------------------------------------------------------------------------------------------
# Message types: Python classes, .msg definitions as rosbag2 stores them, type hashes
# --------------------------------------------------------------------------------------------

_ROS_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_TYPE_2 = re.compile(rf"^({_ROS_NAME})/({_ROS_NAME})$")
_TYPE_3 = re.compile(rf"^({_ROS_NAME})/({_ROS_NAME})/({_ROS_NAME})$")
# The two regular expressions of rosbag2_cpp/local_message_definition_source.cpp.
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
_PRIMITIVES = frozenset(
    {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
     "uint32", "int64", "uint64", "string"}
)  # fmt: skip
_DELIMITER = "=" * 80 + "\n"

_class_cache: dict[str, type] = {}
_definition_cache: dict[str, tuple[str, str]] = {}


def _split_type(msgtype: str) -> tuple[str, str, str]:
    """Split ``pkg/msg/Type`` or ``pkg/Type`` into (package, namespace, name)."""
    if m := _TYPE_3.match(msgtype):
        return m.group(1), m.group(2), m.group(3)
    if m := _TYPE_2.match(msgtype):
        return m.group(1), "msg", m.group(2)
    raise ValueError(f"not a ROS interface type name: {msgtype!r} (expected pkg/msg/Type)")


def msgtype_of(msg: Any) -> str:
    """The type name (``pkg/msg/Type``) of an rclpy message object or class."""
    cls = msg if isinstance(msg, type) else type(msg)
    parts = cls.__module__.split(".")
    if len(parts) < 2:
        raise TypeError(f"{cls!r} is not a generated ROS 2 message class")
    return f"{parts[0]}/{parts[1]}/{cls.__name__}"


def get_message_class(msgtype: str) -> type | None:
    """The Python class of a message type, or None when it cannot be imported.

    Uses ``rosidl_runtime_py.utilities.get_message`` when that package is installed, otherwise
    imports ``<pkg>.msg`` (which is all that function does). Failures are not cached, so a package
    installed while the process runs is found on the next call.

    Args:
        msgtype: ``pkg/msg/Type`` (``pkg/Type`` is accepted too).

    Returns:
        The message class, or None.

    """
    cls = _class_cache.get(msgtype)
    if cls is not None:
        return cls
    try:
        pkg, ns, name = _split_type(msgtype)
    except ValueError:
        return None
    try:
        from rosidl_runtime_py.utilities import get_message  # type: ignore[import-not-found]

        cls = get_message(f"{pkg}/{ns}/{name}")
    except (ImportError, AttributeError, ValueError):
        try:
            cls = getattr(importlib.import_module(f"{pkg}.{ns}"), name)
        except (ImportError, AttributeError, ValueError):
            return None
    if not isinstance(cls, type):
        return None
    _class_cache[msgtype] = cls
    return cls


def _share_dirs(package: str) -> list[Path]:
    """Candidate ``share/<package>`` folders, in the order ament's index would be searched."""
    prefixes: list[Path] = [
        Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p
    ]
    with contextlib.suppress(ImportError, ValueError, AttributeError):
        spec = importlib.util.find_spec(package)
        if spec is not None and spec.origin:
            prefixes.extend(
                p for p in Path(spec.origin).parents if (p / "share" / package).is_dir()
            )
    prefixes += [Path(sys.prefix), Path(sys.base_prefix)]
    out: list[Path] = []
    for prefix in prefixes:
        d = prefix / "share" / package
        if d not in out and d.is_dir():
            out.append(d)
    return out


class _DefinitionNotFoundError(LookupError):
    pass


def _load_definition(name: str, fmt: str) -> tuple[str, list[str]]:
    """Text and sorted dependency names of one interface file, as rosbag2 parses them."""
    pkg, ns, type_name = _split_type(name)
    for share in _share_dirs(pkg):
        path = share / ns / f"{type_name}.{fmt}"
        if path.is_file():
            text = path.read_text(encoding="utf-8")
            break
    else:
        raise _DefinitionNotFoundError(f"{name} ({fmt}): no share/{pkg}/{ns}/{type_name}.{fmt}")
    deps: set[str] = set()
    if fmt == "msg":
        for m in _MSG_FIELD_TYPE.finditer(text):
            t = m.group(1)
            if t not in _PRIMITIVES:
                deps.add(t if "/" in t else f"{pkg}/{t}")
    else:
        deps.update(m.group(1) for m in _IDL_INCLUDE.finditer(text))
    return text, sorted(deps)


def _full_text(root: str, fmt: str) -> str:
    """rosbag2's ``get_full_text``: the root definition and its dependencies, depth first."""
    seen: set[str] = set()
    tag = "MSG: " if fmt == "msg" else "IDL: "

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise BagError(f"maximum recursion depth reached resolving {root}")
        text, deps = _load_definition(name, fmt)
        for dep in deps:
            if dep not in seen:
                seen.add(dep)
                text += "\n" + _DELIMITER + tag + dep + "\n" + append(dep, depth - 1)
        return text

    body = append(root, 50)
    return body if fmt == "msg" else _DELIMITER + tag + root + "\n" + body


def message_definition(msgtype: str) -> tuple[str, str]:
    """The schema of a message type as rosbag2 writes it into an MCAP file.

    Args:
        msgtype: ``pkg/msg/Type``.

    Returns:
        (schema encoding, schema text): ``("ros2msg", ...)`` from the installed ``.msg`` files, or
        ``("ros2idl", ...)`` when some ``.msg`` file is missing but the ``.idl`` files exist.

    Raises:
        LookupError: Neither the ``.msg`` nor the ``.idl`` definitions are installed.
        ValueError: ``msgtype`` is not a type name.

    """
    cached = _definition_cache.get(msgtype)
    if cached is not None:
        return cached
    try:
        result = ("ros2msg", _full_text(msgtype, "msg"))
    except _DefinitionNotFoundError as msg_err:
        try:
            result = ("ros2idl", _full_text(msgtype, "idl"))
        except _DefinitionNotFoundError as idl_err:
            raise LookupError(
                f"no interface definition for {msgtype}: {msg_err}; {idl_err} (searched "
                "AMENT_PREFIX_PATH, the package's install prefix and sys.prefix)"
            ) from None
    _definition_cache[msgtype] = result
    return result


def _type_hash(msgtype: str) -> str:
    """The RIHS01 type description hash from the type's installed ``.json``, or ``""``."""
    try:
        pkg, ns, name = _split_type(msgtype)
    except ValueError:
        return ""
    full = f"{pkg}/{ns}/{name}"
    for share in _share_dirs(pkg):
        path = share / ns / f"{name}.json"
        if path.is_file():
            with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
                for entry in json.loads(path.read_text(encoding="utf-8"))["type_hashes"]:
                    if entry["type_name"] == full:
                        return str(entry["hash_string"])
    return ""


# --------------------------------------------------------------------------------------------
# YAML as yaml-cpp (rosbag2) emits it
# --------------------------------------------------------------------------------------------

_PLAIN = re.compile(r"^[A-Za-z_/][A-Za-z0-9_/.\-]*$")
_YAML_WORDS = {"true", "false", "yes", "no", "on", "off", "null", "y", "n"}


def _yaml_scalar(value: Any) -> str:
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    text = str(value)
    if _PLAIN.match(text) and text.lower() not in _YAML_WORDS:
        return text
    return json.dumps(text)


def _yaml_lines(value: Any, indent: int) -> list[str]:
    pad = " " * indent
    lines: list[str] = []
    if isinstance(value, Mapping):
        for key, item in value.items():
            if isinstance(item, Mapping | list) and item:
                lines.append(f"{pad}{key}:")
                lines += _yaml_lines(item, indent + 2)
            elif isinstance(item, Mapping | list):
                lines.append(f"{pad}{key}: {'{}' if isinstance(item, Mapping) else '[]'}")
            else:
                lines.append(f"{pad}{key}: {_yaml_scalar(item)}")
    else:
        for item in value:
            if isinstance(item, Mapping | list) and item:
                sub = _yaml_lines(item, indent + 2)
                lines.append(f"{pad}- {sub[0][indent + 2 :]}")
                lines += sub[1:]
            else:
                lines.append(f"{pad}- {_yaml_scalar(item)}")
    return lines


def _qos_profiles(qos: str) -> list[dict[str, Any]]:
    if qos not in QOS_PRESETS:
        raise ValueError(f"unknown QoS preset {qos!r}; one of {sorted(QOS_PRESETS)}")
    p = QOS_PRESETS[qos]
    return [
        {
            "history": p["history"],
            "depth": p["depth"],
            "reliability": p["reliability"],
            "durability": p["durability"],
            "deadline": dict(_INFINITE),
            "lifespan": dict(_INFINITE),
            "liveliness": "automatic",
            "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False,
        }
    ]


def qos_yaml(qos: str) -> str:
    """The ``offered_qos_profiles`` channel metadata of a QoS preset (yaml-cpp layout).

    Args:
        qos: One of :data:`QOS_PRESETS`.

    Returns:
        The YAML text rosbag2 (metadata version 9) stores in the MCAP channel.

    """
    return "\n".join(_yaml_lines(_qos_profiles(qos), 0))


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


@dataclass
class _Topic:
    name: str
    msgtype: str
    qos: str
    channel_id: int
    type_hash: str
    count: int = 0
    sequence: int = 0
    compression: str | None = None  # chunk compression of its messages (None: the bag's)


#: Chunk compression names -> mcap's CompressionType.
_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                 "none": CompressionType.NONE, "": CompressionType.NONE}  # fmt: skip


class BagWriter:
    """Writes a rosbag2 bag folder with one MCAP file.

    Use as a context manager; leaving the block (also through an exception) writes the MCAP
    summary and ``metadata.yaml``. Writing is thread-safe.

    Example:
        >>> with BagWriter(Path("out/run1")) as bag:  # doctest: +SKIP
        ...     bag.add_topic("/image", "sensor_msgs/msg/Image", qos="sensor_data")
        ...     bag.write("/image", image_msg, stamp_ns=1_700_000_000_000_000_000)

    Args:
        path: The bag folder to create; the MCAP file is ``path / (path.name + "_0.mcap")``.
        chunk_size: Uncompressed MCAP chunk size (bytes) at which a chunk is compressed and
            written; a message larger than that makes a chunk of its own.
        compression: Chunk compression: ``"zstd"`` (rosbag2's choice), ``"lz4"`` or ``"none"``.
        topic_compression: Chunk compression per topic, where it differs from ``compression``
            (e.g. ``{"left/image_strip": "lz4"}``; also :meth:`add_topic`'s ``compression``).
            Each chunk holds messages of one compression: a change closes the current chunk.
            On this 2-core machine (13.8 MB uint16 images, one thread): zstd writes 180-360
            MB/s and keeps 60-80 % of the size, lz4 220-960 MB/s and 75-100 %, none 800-1200
            MB/s; the IKONOS sensor delivers 360 MB/s (README, "Recording large images").
        overwrite: Replace an existing bag folder (only one holding nothing but ``metadata.yaml``
            and ``.mcap`` files). Otherwise an existing ``path`` is an error.
        ros_distro: Recorded in the metadata; default ``$ROS_DISTRO`` or ``"kilted"``.
        custom_data: Free key/value strings recorded in the metadata (``custom_data``).
        direct: Write the MCAP file past the page cache (``O_DIRECT``,
            :class:`~parproj_ros.io.direct.DirectFile`), where the file system allows it
            (:attr:`direct` tells): for large outputs, which otherwise take fresh memory for
            every page written.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False or it is not a bag.
        ValueError: Unknown compression or a chunk size below 1.

    """

    def __init__(
        self,
        path: Path | str,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: Compression | str = "zstd",
        topic_compression: Mapping[str, Compression | str] | None = None,
        overwrite: bool = False,
        ros_distro: str | None = None,
        custom_data: Mapping[str, str] | None = None,
        direct: bool = False,
    ) -> None:
        self.path = Path(path)
        kinds = _COMPRESSIONS
        for c in [compression, *(topic_compression or {}).values()]:
            if c not in kinds:
                raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', not {c!r}")
        self._compression = str(compression)
        self._chunk_compression = str(compression)  # of the chunk being filled
        self._topic_compression = {k: str(v) for k, v in (topic_compression or {}).items()}
        if chunk_size < 1:
            raise ValueError("chunk_size must be positive (bytes)")
        if self.path.exists():
            bag_like = self.path.is_dir() and all(
                p.is_file() and (p.name == "metadata.yaml" or p.suffix == ".mcap")
                for p in self.path.iterdir()
            )
            if not (overwrite and bag_like):
                raise FileExistsError(f"{self.path} exists already; not overwriting")
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True)
        self.mcap_path = self.path / f"{self.path.name}_0.mcap"
        self.ros_distro = ros_distro or os.environ.get("ROS_DISTRO") or "kilted"
        self.custom_data = dict(custom_data or {})
        self._lock = threading.Lock()
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._start_ns: int | None = None
        self._end_ns: int | None = None
        self._closed = False
        self._file: Any = DirectFile(self.mcap_path) if direct else self.mcap_path.open("xb")
        self._writer = Writer(
            cast(Any, self._file), chunk_size=chunk_size, compression=kinds[compression]
        )
        self._writer.start(profile="ros2", library=f"parproj_ros bag.py; mcap-python {_mcap_v()}")

    @property
    def direct(self) -> bool:
        """Whether the MCAP file is written past the page cache (``direct`` and allowed)."""
        return bool(getattr(self._file, "direct", False))

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def add_topic(
        self,
        name: str,
        msgtype: str,
        qos: QosName | str = "reliable",
        *,
        definition: str | None = None,
        encoding: str = "ros2msg",
        compression: Compression | str | None = None,
    ) -> None:
        """Declare a topic (an MCAP channel, with its type's schema written once).

        Args:
            name: Topic name, e.g. ``/scanner/image``.
            msgtype: ``pkg/msg/Type``.
            qos: The offered QoS recorded for the topic: a key of :data:`QOS_PRESETS`.
            definition: Schema text to store instead of looking the type's definition up (for
                types whose interface files are not installed; use with :meth:`write_raw`).
            encoding: Schema encoding of ``definition`` (``ros2msg`` or ``ros2idl``).
            compression: Chunk compression of this topic's messages (default: the bag's, or
                ``topic_compression``'s).

        Raises:
            BagError: The topic exists with another type, or the bag is closed.
            LookupError: ``definition`` is None and the type's definition is not installed.
            ValueError: Unknown QoS preset or malformed type name.

        """
        _split_type(msgtype)
        metadata = {"offered_qos_profiles": qos_yaml(qos), "topic_type_hash": _type_hash(msgtype)}
        with self._lock:
            self._check_open()
            if name in self._topics:
                if self._topics[name].msgtype != msgtype:
                    raise BagError(f"topic {name} has type {self._topics[name].msgtype} already")
                return
            schema_id = self._schemas.get(msgtype)
            if schema_id is None:
                if definition is None:
                    enc, text = message_definition(msgtype)
                else:
                    enc, text = encoding, definition
                schema_id = self._writer.register_schema(msgtype, enc, text.encode())
                self._schemas[msgtype] = schema_id
            channel_id = self._writer.register_channel(name, "cdr", schema_id, metadata)
            chosen = compression if compression is not None else self._topic_compression.get(name)
            if chosen is not None and chosen not in _COMPRESSIONS:
                raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', not {chosen!r}")
            self._topics[name] = _Topic(
                name, msgtype, qos, channel_id, metadata["topic_type_hash"],
                compression=None if chosen is None else str(chosen),
            )  # fmt: skip

    def add_topics(self, topics: Iterable[contract.Topic]) -> None:
        """Declare topics of the interface contract (:mod:`parproj_ros.core.contract`).

        Each with its name, type and recorded QoS (``Topic.recorded``), in the order given.

        Raises:
            BagError: A topic exists with another type, or the bag is closed.
        """
        for t in topics:
            self.add_topic(t.name, t.msgtype, t.recorded)

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Serialize an rclpy message and append it.

        A topic not declared yet is added with the message's type and the ``reliable`` preset.

        Args:
            topic: Topic name.
            msg: rclpy message object.
            stamp_ns: Log time (ns since the epoch); also used as the publish time.

        Raises:
            TypeError: The message type differs from the topic's type.

        """
        from rclpy.serialization import serialize_message

        msgtype = msgtype_of(msg)
        known = self._topics.get(topic)
        if known is None:
            self.add_topic(topic, msgtype)
        elif known.msgtype != msgtype:
            raise TypeError(f"topic {topic} has type {known.msgtype}, got a {msgtype}")
        self.write_raw(topic, serialize_message(msg), stamp_ns)

    def write_raw(self, topic: str, data: bytes, stamp_ns: int) -> None:
        """Append an already CDR-serialized message to a declared topic.

        Args:
            topic: Topic name (declared with :meth:`add_topic`).
            data: CDR bytes including the 4-byte encapsulation header.
            stamp_ns: Log time (ns since the epoch); also used as the publish time.

        Raises:
            BagError: Unknown topic or closed bag.
            ValueError: Negative time stamp.

        """
        stamp_ns = int(stamp_ns)
        if stamp_ns < 0:
            raise ValueError(f"stamp_ns must be >= 0 (ns since the epoch), got {stamp_ns}")
        with self._lock:
            self._check_open()
            t = self._topics.get(topic)
            if t is None:
                raise BagError(f"topic {topic} was not added (add_topic) before writing")
            t.sequence = (t.sequence + 1) & 0xFFFFFFFF
            self._use_compression(t.compression or self._compression)
            self._writer.add_message(
                t.channel_id, log_time=stamp_ns, data=bytes(data), publish_time=stamp_ns,
                sequence=t.sequence,
            )  # fmt: skip
            t.count += 1
            self._start_ns = stamp_ns if self._start_ns is None else min(self._start_ns, stamp_ns)
            self._end_ns = stamp_ns if self._end_ns is None else max(self._end_ns, stamp_ns)

    def _use_compression(self, compression: str) -> None:
        """Make the chunk being filled one of ``compression`` (lock held).

        mcap's Writer has one compression for all its chunks: a change closes the current
        chunk and sets the Writer's (name-mangled) compression, both in mcap 1.6's writer.py.
        """
        if compression == self._chunk_compression:
            return
        w = self._writer
        finalize = getattr(w, "_Writer__finalize_chunk", None)
        if finalize is None or not hasattr(w, "_Writer__compression"):
            raise BagError(
                "per-topic chunk compression needs mcap's Writer internals (mcap 1.6); "
                "this mcap has none: write the bag with one compression"
            )
        finalize()
        w._Writer__compression = _COMPRESSIONS[compression]
        self._chunk_compression = compression

    def flush(self) -> None:
        """Write the chunk in progress and flush the file (a later cut loses nothing before)."""
        with self._lock:
            self._check_open()
            self._writer.flush()  # type: ignore[no-untyped-call]

    def message_counts(self) -> dict[str, int]:
        """Messages written so far per topic."""
        with self._lock:
            return {name: t.count for name, t in self._topics.items()}

    def topics(self) -> dict[str, str]:
        """Declared topics: {name: msgtype}."""
        with self._lock:
            return {name: t.msgtype for name, t in self._topics.items()}

    def close(self) -> None:
        """Finish the MCAP file (rosbag2 metadata record, summary, footer), write metadata.yaml.

        Safe to call more than once.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                meta = self._metadata()
                self._writer.add_metadata(
                    "rosbag2", {"serialized_metadata": "\n".join(_yaml_lines(meta, 0))}
                )
                self._writer.finish()  # type: ignore[no-untyped-call]
            finally:
                self._file.close()
            text = "\n".join(_yaml_lines({"rosbag2_bagfile_information": meta}, 0)) + "\n"
            (self.path / "metadata.yaml").write_text(text, encoding="utf-8")

    def _check_open(self) -> None:
        if self._closed:
            raise BagError(f"bag {self.path} is closed")

    def _metadata(self) -> dict[str, Any]:
        count = sum(t.count for t in self._topics.values())
        start, duration = 2**63 - 1, 0  # rosbag2's values for an empty bag
        if self._start_ns is not None and self._end_ns is not None:
            start, duration = self._start_ns, self._end_ns - self._start_ns
        topics = [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": _qos_profiles(t.qos),
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.count,
            }
            for t in self._topics.values()
        ]
        return {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": topics,
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.mcap_path.name],
            "files": [
                {
                    "path": self.mcap_path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": count,
                }
            ],
            "custom_data": self.custom_data or None,
            "ros_distro": self.ros_distro,
        }


def _mcap_v() -> str:
    return getattr(mcap, "__version__", "") or _dist_version("mcap")


def _dist_version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "?"


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------


@dataclass
class Recovery:
    """What a reader found complete in the MCAP file(s) of a bag.

    Attributes:
        complete: Every file ends with a footer and the closing magic, and no chunk failed its
            CRC or decompression.
        messages_read: Complete messages present in the file(s) (the ones the reader yields).
            For a file with a summary section this is the summary's count; a chunk found
            corrupt while reading is reported afterwards in ``corrupt_chunks`` and ``error``.
        truncated_bytes: Bytes at the end of the file(s) that are not complete records (the
            cut-off record, or an incomplete record header).
        missing_bytes: Bytes the cut-off record declares but which are not in the file (None if
            the cut is inside a record header, so the size is unknown).
        partial_chunk_messages: Messages salvaged from the readable start of a cut-off chunk
            (included in ``messages_read``).
        corrupt_chunks: Complete chunks skipped because of a CRC or decompression error.
        messages_expected: Message count that ``metadata.yaml`` states, when it exists.
        error: What was wrong, or None.

    """

    complete: bool = True
    messages_read: int = 0
    truncated_bytes: int = 0
    missing_bytes: int | None = 0
    partial_chunk_messages: int = 0
    corrupt_chunks: int = 0
    messages_expected: int | None = None
    error: str | None = None

    @property
    def messages_lost(self) -> int | None:
        """``messages_expected - messages_read`` when the metadata states a count, else None."""
        if self.messages_expected is None:
            return None
        return max(0, self.messages_expected - self.messages_read)

    def describe(self) -> str:
        """What was lost, in words: the error, and the messages lost when the count is known."""
        lost = self.messages_lost
        count = "" if lost is None else f"{lost} of {self.messages_expected} messages lost, "
        return f"cut off or damaged ({self.error}): {count}{self.messages_read} complete read"

    def _fail(self, error: str) -> None:
        self.complete = False
        self.error = error if self.error is None else f"{self.error}; {error}"


class BagMessage(NamedTuple):
    """A deserialized message: topic, rclpy message object, log time (ns)."""

    topic: str
    msg: Any
    log_time_ns: int


class RawMessage(NamedTuple):
    """A serialized message: topic, type name, CDR bytes, log time (ns)."""

    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int


class _Msg(NamedTuple):
    channel_id: int
    log_time: int
    data: bytes


@dataclass
class _FileIndex:
    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    recovery: Recovery = field(default_factory=Recovery)
    #: {chunk start offset: channel ids with messages in it}, from the summary's chunk indexes
    #: (None: no summary, or chunks without message indexes)
    chunk_channels: dict[int, frozenset[int]] | None = None

    def msgtype(self, channel: Channel) -> str:
        schema = self.schemas.get(channel.schema_id)
        return schema.name if schema is not None else ""


def _records(data: bytes | memoryview) -> Iterator[tuple[int, memoryview]]:
    """Complete (opcode, body) records of a chunk's record stream; a cut-off tail is dropped."""
    view = memoryview(data)
    pos, size = 0, len(view)
    while pos + 9 <= size:
        opcode, length = _RECORD_HEAD.unpack_from(view, pos)
        end = pos + 9 + length
        if end > size:
            return
        yield opcode, view[pos + 9 : end]
        pos = end


def _partial_decompress(compression: str, data: bytes) -> bytes:
    """Decompress as much as possible of the start of a cut-off compressed chunk."""
    if compression == "":
        return data
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    if compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
    raise BagError(f"unsupported chunk compression {compression!r}")


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"opcode 0x{opcode:02x}"


def _scan(
    index: _FileIndex,
    recovery: Recovery,
    *,
    validate_crcs: bool = True,
    start_ns: int | None = None,
    end_ns: int | None = None,
    stop_at_data_end: bool = False,
    skip_chunks: frozenset[int] = frozenset(),
) -> Iterator[_Msg]:
    """Walk an MCAP file record by record, yielding its complete messages in file order.

    Schemas and channels met on the way are added to ``index``; problems are recorded in
    ``recovery``. Chunks entirely outside [start_ns, end_ns), and those starting at an offset
    in ``skip_chunks`` (none of the wanted topics in them), are not read.
    """
    path = index.path
    size = path.stat().st_size
    chunk_buf = _ReusedBuffer()

    def in_range(t: int) -> bool:
        return (start_ns is None or t >= start_ns) and (end_ns is None or t < end_ns)

    def handle(opcode: int, body: memoryview) -> Iterator[_Msg]:
        if opcode == Opcode.MESSAGE and len(body) >= _MESSAGE_HEAD.size:
            channel_id, _seq, log_time, _pub = _MESSAGE_HEAD.unpack_from(body)
            if in_range(log_time):
                yield _Msg(channel_id, log_time, bytes(body[_MESSAGE_HEAD.size :]))
        elif opcode == Opcode.SCHEMA:
            schema = Schema.read(ReadDataStream(BytesIO(body)))
            index.schemas.setdefault(schema.id, schema)
        elif opcode == Opcode.CHANNEL:
            channel = Channel.read(ReadDataStream(BytesIO(body)))
            index.channels.setdefault(channel.id, channel)

    with path.open("rb") as f:
        if f.read(8) != _MAGIC:
            raise BagError("not an MCAP file (bad magic)", path)
        pos = 8
        while True:
            head = f.read(9)
            if len(head) < 9:
                recovery.truncated_bytes += size - pos
                recovery.missing_bytes = None if head else 0
                where = "inside a record header" if head else "after a complete record"
                recovery._fail(f"{path.name}: no footer, file ends at byte {size} {where}")
                return
            opcode, length = _RECORD_HEAD.unpack(head)
            end = pos + 9 + length
            if end > size:
                recovery.truncated_bytes += size - pos
                recovery.missing_bytes = (recovery.missing_bytes or 0) + end - size
                recovery._fail(
                    f"{path.name}: cut off {end - size} bytes before the end of a "
                    f"{_opcode_name(opcode)} record at byte {pos} (file size {size})"
                )
                if opcode == Opcode.CHUNK:
                    for msg in _salvage_chunk(f.read(size - pos - 9), handle):
                        recovery.partial_chunk_messages += 1
                        yield msg
                return
            if opcode == Opcode.CHUNK and length >= _CHUNK_HEAD.size:
                t0, t1, _, _ = _CHUNK_HEAD.unpack(f.read(_CHUNK_HEAD.size))
                if (
                    (start_ns is not None and t1 < start_ns)
                    or (end_ns is not None and t0 >= end_ns)
                    or pos in skip_chunks
                ):
                    f.seek(end)
                else:
                    f.seek(pos + 9)
                    yield from _chunk(
                        chunk_buf.read(f, length), handle, recovery, validate_crcs, path, pos
                    )
            elif opcode == Opcode.DATA_END and stop_at_data_end:
                return
            elif opcode == Opcode.FOOTER:
                f.seek(end)
                if f.read(8) != _MAGIC:
                    recovery.truncated_bytes += size - end
                    recovery._fail(f"{path.name}: closing magic missing after the footer")
                return
            elif opcode in (Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL):
                yield from handle(opcode, memoryview(f.read(length)))
            else:
                f.seek(end)
            pos = end


_Handler = Callable[[int, memoryview], Iterator["_Msg"]]


class _ReusedBuffer:
    """Chunk records read one at a time into the same memory.

    A 13 MB strip is a chunk of its own: read with ``f.read`` each would be a fresh 13 MB
    allocation in the reading thread, whose pages the process may have to fault in afresh
    (core/memory.py). A chunk's records are copied out (message bytes) or parsed before the
    next chunk is read, so nothing refers to the memory when it is read into again.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def read(self, f: Any, n: int) -> memoryview:
        """The next ``n`` bytes of ``f`` (fewer at its end), a view valid until the next read.

        The memory grows to the largest chunk; after one over 64 MB (a whole image) it is
        made smaller again for a chunk of under a quarter of it.
        """
        if len(self._buf) < n or (len(self._buf) > 64 * 2**20 and n < len(self._buf) // 4):
            self._buf = bytearray(n)
        view = memoryview(self._buf)[:n]
        got = f.readinto(view)
        return view[: got or 0]


def _chunk(
    body: bytes | memoryview,
    handle: _Handler,
    recovery: Recovery,
    validate_crcs: bool,
    path: Path,
    offset: int,
) -> Iterator[_Msg]:
    try:
        data = _chunk_records(body, validate_crcs)
    except (McapError, zstandard.ZstdError, ValueError, RuntimeError, MemoryError) as exc:
        recovery.corrupt_chunks += 1
        recovery._fail(f"{path.name}: chunk at byte {offset} skipped: {exc}")
        return
    for opcode, rec in _records(data):
        yield from handle(opcode, rec)


def _chunk_records(body: bytes | memoryview, validate_crc: bool) -> bytes | memoryview:
    """The records of a Chunk record's ``body``: decompressed, or a view on ``body``.

    mcap's ``Chunk.read`` copies the records out of the body first: 13 MB more per full-size
    strip, into memory the process may have to fault in afresh (core/memory.py).

    Raises:
        ValueError: the record is cut off, or the records' CRC-32 is not the one recorded.
        McapError: an unknown compression.
        zstandard.ZstdError, RuntimeError: the compressed records do not decompress.
    """
    view = memoryview(body)
    fixed = _CHUNK_HEAD.size
    if len(view) < fixed + 4:
        raise ValueError("chunk record too short")
    _t0, _t1, size, crc = _CHUNK_HEAD.unpack_from(view)
    (clen,) = _U32.unpack_from(view, fixed)
    at = fixed + 4 + clen
    if len(view) < at + 8:
        raise ValueError("chunk record too short")
    compression = bytes(view[fixed + 4 : at]).decode("utf-8", "replace")
    if size > MAX_CHUNK_RECORDS:  # a damaged size would make the decompressor allocate it
        raise ValueError(f"chunk declares {size} bytes of records, over {MAX_CHUNK_RECORDS}")
    (rlen,) = _U64.unpack_from(view, at)
    packed = view[at + 8 : at + 8 + rlen]
    if len(packed) != rlen:
        raise ValueError(f"chunk records: {len(packed)} bytes of {rlen}")
    data: bytes | memoryview
    if compression == "":
        data = packed
    elif compression == "zstd":
        # The frame's own content size, when it has one, is what zstandard allocates.
        if zstandard.frame_content_size(packed) > size:
            raise ValueError(f"zstd frame larger than the {size} bytes of records declared")
        data = zstandard.decompress(packed, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame

        if lz4.frame.get_frame_info(packed)["content_size"] > size:
            raise ValueError(f"lz4 frame larger than the {size} bytes of records declared")
        data = lz4.frame.decompress(packed)
    else:
        raise McapError(f"unsupported chunk compression {compression!r}")
    if len(data) != size:
        raise ValueError(f"chunk records: {len(data)} bytes, {size} recorded")
    if validate_crc and crc != 0 and (actual := zlib.crc32(data)) != crc:
        raise ValueError(f"chunk CRC-32 {actual:#010x}, {crc:#010x} recorded")
    return data


def _salvage_chunk(available: bytes, handle: _Handler) -> Iterator[_Msg]:
    """Messages of the readable start of a cut-off chunk record."""
    fixed = _CHUNK_HEAD.size
    if len(available) < fixed + 4:
        return
    (clen,) = struct.unpack_from("<I", available, fixed)
    data_at = fixed + 4 + clen + 8
    if len(available) < data_at:
        return
    compression = available[fixed + 4 : fixed + 4 + clen].decode("utf-8", "replace")
    try:
        data = _partial_decompress(compression, available[data_at:])
    except Exception:  # any decoder error: nothing can be salvaged
        return
    for opcode, rec in _records(data):
        yield from handle(opcode, rec)


#: What a corrupt MCAP file can make the record parsers raise (mcap, struct, zstd, decoding).
_CORRUPT = (
    McapError, struct.error, zstandard.ZstdError, ValueError, EOFError, KeyError, IndexError,
    UnicodeDecodeError, OverflowError, MemoryError, TypeError, AttributeError, AssertionError,
)  # fmt: skip


@contextlib.contextmanager
def _corrupt_is_bag_error(path: Path) -> Iterator[None]:
    """Turn whatever a damaged file makes the parsers raise into a :class:`BagError`."""
    try:
        yield
    except BagError:
        raise
    except OSError as err:
        raise BagError(f"cannot be read: {err.strerror or err}", path) from err
    except _CORRUPT as err:
        raise BagError(f"corrupt MCAP file ({type(err).__name__}: {err})", path) from err


def _guarded(messages: Iterator[_Msg], path: Path) -> Iterator[_Msg]:
    """``messages`` with the errors of a damaged file turned into :class:`BagError`."""
    with _corrupt_is_bag_error(path):
        yield from messages


def _regular_size(path: Path) -> int:
    """The size of a regular file; :class:`BagError` for a folder, FIFO or device.

    Only ``stat`` is used (nothing is opened), so a FIFO cannot block the reader.
    """
    try:
        st = path.stat()
    except OSError as err:
        raise BagError(f"cannot be read: {err.strerror or err}", path) from err
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (FIFO or device)"
        raise BagError(f"{kind}: not an MCAP file", path)
    return st.st_size


# --------------------------------------------------------------------------------------------
# Foreign bags: refused by name, with what to do (every command reads bags through BagReader)
# --------------------------------------------------------------------------------------------

#: The first 16 bytes of every SQLite 3 database, hence of a rosbag2 ``.db3`` file.
SQLITE_MAGIC = b"SQLite format 3\x00"
#: A rosbag2 sqlite3 bag: what it is and what to do (``{src}``: the bag, shell-quoted).
SQLITE_BAG = (
    "a rosbag2 sqlite3 bag, not MCAP: convert it with `rosbags-convert --src {src} --dst OUT "
    "--dst-storage mcap` or `ros2 bag convert` (storage_id mcap), then give OUT"
)
#: A ROS 1 recording in MCAP: what to do (after what marks it).
ROS1_ADVICE = (
    "parproj reads ROS 2 bags (CDR messages); convert the ROS 1 recording's .bag with "
    "`rosbags-convert --src REC.bag --dst OUT --dst-storage mcap`, then give OUT"
)
#: The MCAP profile, message encoding and schema encoding of ROS 1 data.
ROS1_PROFILE, ROS1_ENCODING, ROS1_SCHEMA_ENCODING = "ros1", "ros1", "ros1msg"
#: Largest MCAP header record read for its profile (bytes; a writer puts two short strings).
_MAX_HEADER_BYTES = 1 << 20


def _sqlite_bag_error(path: Path) -> BagError:
    """The one-line refusal of a rosbag2 sqlite3 bag (a ``.db3`` file or its folder)."""
    return BagError(SQLITE_BAG.format(src=shlex.quote(str(path))), path)


def _is_sqlite(path: Path) -> bool:
    """Whether ``path`` is a regular file starting with SQLite's magic (no FIFO is opened)."""
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            return False
        with path.open("rb") as f:
            return f.read(len(SQLITE_MAGIC)) == SQLITE_MAGIC
    except OSError:
        return False


def _check_folder_storage(folder: Path, metadata: Mapping[str, Any] | None) -> None:
    """Refuse a rosbag2 folder of another storage than MCAP, by name.

    ``metadata``'s ``storage_identifier`` (``sqlite3``), the ``.db3`` files it lists, or, with
    no ``.mcap`` file listed or present, a ``.db3`` file in the folder.

    Raises:
        BagError: a rosbag2 sqlite3 bag, or a storage other than ``mcap`` named by metadata.yaml.
    """
    storage = (metadata or {}).get("storage_identifier")
    listed = [str(p) for p in (metadata or {}).get("relative_file_paths") or []]
    if storage == "sqlite3" or any(p.endswith(".db3") for p in listed):
        raise _sqlite_bag_error(folder)
    if isinstance(storage, str) and storage not in ("", "mcap"):
        raise BagError(
            f"a rosbag2 bag of storage {storage!r} (metadata.yaml), not MCAP: convert it with "
            "`ros2 bag convert` (storage_id mcap), then give the result",
            folder,
        )
    if not listed and not any(folder.glob("*.mcap")) and any(folder.glob("*.db3")):
        raise _sqlite_bag_error(folder)


def _mcap_profile(f: Any) -> str | None:
    """The profile of the MCAP header record at the file position (after the magic), or None.

    The position is left after the header record (or where it was, if there is none).
    """
    start = f.tell()
    head = f.read(9)
    if len(head) == 9:
        opcode, length = _RECORD_HEAD.unpack(head)
        if opcode == Opcode.HEADER and length <= _MAX_HEADER_BYTES:
            body = f.read(length)
            if len(body) == length:
                with contextlib.suppress(McapError, ValueError, struct.error, EOFError):
                    return str(Header.read(ReadDataStream(BytesIO(body))).profile)
    f.seek(start)
    return None


def _ros1_marks(
    profile: str | None, schemas: Iterable[Schema], channels: Iterable[Channel]
) -> list[str]:
    """What marks an MCAP file as ROS 1 data: its profile and encodings (empty: none)."""
    marks = [f"profile {ROS1_PROFILE!r}"] if profile == ROS1_PROFILE else []
    if any(ch.message_encoding == ROS1_ENCODING for ch in channels):
        marks.append(f"message encoding {ROS1_ENCODING!r}")
    if any(s.encoding == ROS1_SCHEMA_ENCODING for s in schemas):
        marks.append(f"schema encoding {ROS1_SCHEMA_ENCODING!r}")
    return marks


def _ros1_bag_error(path: Path, marks: list[str]) -> BagError:
    """The one-line refusal of a ROS 1 recording in MCAP."""
    return BagError(f"a ROS 1 bag in MCAP ({', '.join(marks)}): {ROS1_ADVICE}", path)


def _read_metadata(meta_path: Path) -> dict[str, Any] | None:
    """The ``rosbag2_bagfile_information`` mapping of a ``metadata.yaml``, checked.

    Raises:
        BagError: the file is not a regular file, larger than :data:`MAX_METADATA_BYTES`, not
            UTF-8, not YAML, or its fields do not have rosbag2's types.
    """
    from ..io.files import InputError, decode_utf8, read_bounded

    try:
        text = decode_utf8(meta_path, read_bounded(meta_path, MAX_METADATA_BYTES, "metadata.yaml"))
    except InputError as err:
        raise BagError(err.problem, meta_path) from None
    try:
        loaded = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise BagError(f"not YAML ({first})", meta_path) from None
    if loaded is None:
        return None
    if not isinstance(loaded, dict):
        raise BagError(
            f"expected a mapping with rosbag2_bagfile_information, got {type(loaded).__name__}",
            meta_path,
        )
    info = loaded.get("rosbag2_bagfile_information")
    if info is None:
        raise BagError("no rosbag2_bagfile_information: not rosbag2 metadata", meta_path)
    if not isinstance(info, dict):
        raise BagError(
            f"rosbag2_bagfile_information is a {type(info).__name__}, not a mapping", meta_path
        )
    files = info.get("relative_file_paths")
    if files is not None and not (
        isinstance(files, list) and all(isinstance(f, str) and f.strip() for f in files)
    ):
        raise BagError("relative_file_paths must be a list of file names", meta_path)
    count = info.get("message_count")
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 0):
        raise BagError(f"message_count must be a count, got {count!r}", meta_path)
    return info


def _index_file(path: Path, validate_crcs: bool) -> _FileIndex:
    """Topics, counts and completeness of one MCAP file.

    From its summary section when the file has one, otherwise by reading it through.
    """
    index = _FileIndex(path)
    size = _regular_size(path)
    with path.open("rb") as f:
        magic = f.read(len(SQLITE_MAGIC))
        if magic == SQLITE_MAGIC:
            raise _sqlite_bag_error(path)
        if magic[:8] != _MAGIC:
            raise BagError("not an MCAP file (bad magic)", path)
        f.seek(8)
        profile = _mcap_profile(f)
        if profile == ROS1_PROFILE:  # refused before anything else is read
            raise _ros1_bag_error(path, _ros1_marks(profile, (), ()))
        f.seek(max(0, size - 8))
        closed = size >= 8 + 9 + 20 + 8 and f.read(8) == _MAGIC
        summary = None
        if closed:
            f.seek(0)
            try:
                summary = SeekingReader(f).get_summary()
            except (McapError, ValueError, struct.error, OSError, EOFError):
                summary = None
    if summary is not None and summary.statistics is not None and summary.channels:
        stats = summary.statistics
        index.schemas.update(summary.schemas)
        index.channels.update(summary.channels)
        index.counts = {cid: int(n) for cid, n in stats.channel_message_counts.items()}
        if stats.message_count:
            index.start_ns, index.end_ns = stats.message_start_time, stats.message_end_time
        index.recovery.messages_read = int(stats.message_count)
        chunks = summary.chunk_indexes
        if chunks and all(ci.message_index_offsets for ci in chunks):
            index.chunk_channels = {
                int(ci.chunk_start_offset): frozenset(ci.message_index_offsets) for ci in chunks
            }
    else:
        for msg in _scan(index, index.recovery, validate_crcs=validate_crcs):
            index.counts[msg.channel_id] = index.counts.get(msg.channel_id, 0) + 1
            t = msg.log_time
            index.start_ns = t if index.start_ns is None else min(index.start_ns, t)
            index.end_ns = t if index.end_ns is None else max(index.end_ns, t)
            index.recovery.messages_read += 1
    marks = _ros1_marks(profile, index.schemas.values(), index.channels.values())
    if marks:
        raise _ros1_bag_error(path, marks)
    return index


class BagReader:
    """Reads a rosbag2 MCAP bag (folder) or a single ``.mcap`` file, also a cut-off one.

    Opening reads the summary section of each file, or, for a file without one (a recording
    that was cut off), reads the file through once to count what is complete; the result is in
    :attr:`recovery`. Messages are yielded in file order (the order they were written, as
    ``ros2 bag play`` does by default).

    Args:
        path: A bag folder (with or without ``metadata.yaml``) or an ``.mcap`` file.
        validate_crcs: Check chunk CRCs while reading; a bad chunk is skipped and reported.

    Attributes:
        path: The path given.
        files: The MCAP files, in reading order.
        metadata: The ``rosbag2_bagfile_information`` mapping of ``metadata.yaml``, or None.
        recovery: What was complete, what was lost (:class:`Recovery`).
        skipped: Messages skipped by the last :meth:`messages` pass per topic, because their
            type cannot be imported (see :meth:`unknown_types`).
        decode_errors: Messages per topic that failed to deserialize in the last pass.

    Raises:
        FileNotFoundError: No such path, no MCAP file in the folder, or a file listed in
            ``metadata.yaml`` is missing.
        BagError: A file is not MCAP; a rosbag2 sqlite3 bag (a ``.db3`` file, or a folder
            whose metadata.yaml or files say so) or a ROS 1 recording in MCAP (profile
            ``ros1``, message encoding ``ros1``, schema encoding ``ros1msg``), each refused
            in one line saying what it is and how to convert it.

    """

    def __init__(self, path: Path | str, *, validate_crcs: bool = True) -> None:
        self.path = Path(path)
        self.validate_crcs = validate_crcs
        self.metadata: dict[str, Any] | None = None
        if self.path.is_dir():
            meta_path = self.path / "metadata.yaml"
            if meta_path.exists() or meta_path.is_symlink():
                self.metadata = _read_metadata(meta_path)
            _check_folder_storage(self.path, self.metadata)
            listed = (self.metadata or {}).get("relative_file_paths")
            if listed:
                self.files = [self.path / Path(p).name for p in listed]
                missing = [str(p) for p in self.files if not p.exists()]
                if missing:
                    raise FileNotFoundError(
                        errno.ENOENT, f"bag files listed in metadata.yaml missing: {missing}",
                        str(meta_path),
                    )  # fmt: skip
            else:
                self.files = sorted(self.path.glob("*.mcap"))
                if not self.files:
                    raise FileNotFoundError(
                        errno.ENOENT, "no .mcap file in the folder (not a bag)", str(self.path)
                    )
        elif self.path.exists():
            self.files = [self.path]
        else:
            raise FileNotFoundError(
                errno.ENOENT, "no bag (no such file or folder)", str(self.path)
            )
        self._indexes = []
        for p in self.files:
            with _corrupt_is_bag_error(p):
                self._indexes.append(_index_file(p, validate_crcs))
        self.recovery = Recovery()
        for idx in self._indexes:
            r = idx.recovery
            self.recovery.messages_read += r.messages_read
            self.recovery.truncated_bytes += r.truncated_bytes
            self.recovery.partial_chunk_messages += r.partial_chunk_messages
            self.recovery.corrupt_chunks += r.corrupt_chunks
            if r.missing_bytes is None or self.recovery.missing_bytes is None:
                self.recovery.missing_bytes = None
            else:
                self.recovery.missing_bytes += r.missing_bytes
            if not r.complete:
                self.recovery._fail(r.error or f"{idx.path.name}: incomplete")
        if self.metadata and isinstance(self.metadata.get("message_count"), int):
            self.recovery.messages_expected = self.metadata["message_count"]
        self.skipped: dict[str, int] = {}
        self.decode_errors: dict[str, int] = {}

    def __enter__(self) -> BagReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        return None

    # -- what is in the bag ------------------------------------------------------------------

    def topics(self) -> dict[str, str]:
        """All topics: {name: msgtype}."""
        out: dict[str, str] = {}
        for idx in self._indexes:
            for ch in idx.channels.values():
                out.setdefault(ch.topic, idx.msgtype(ch))
        return out

    def message_counts(self) -> dict[str, int]:
        """Complete messages per topic (every topic listed, possibly with 0)."""
        out = dict.fromkeys(self.topics(), 0)
        for idx in self._indexes:
            for cid, n in idx.counts.items():
                ch = idx.channels.get(cid)
                if ch is not None:
                    out[ch.topic] = out.get(ch.topic, 0) + n
        return out

    @property
    def message_count(self) -> int:
        """Complete messages in the bag."""
        return sum(self.message_counts().values())

    @property
    def start_ns(self) -> int | None:
        """Earliest log time (ns), None for an empty bag."""
        times = [i.start_ns for i in self._indexes if i.start_ns is not None]
        return min(times) if times else None

    @property
    def end_ns(self) -> int | None:
        """Latest log time (ns), None for an empty bag."""
        times = [i.end_ns for i in self._indexes if i.end_ns is not None]
        return max(times) if times else None

    def definitions(self) -> dict[str, tuple[str, str]]:
        """Stored schemas: {msgtype: (encoding, text)}."""
        out: dict[str, tuple[str, str]] = {}
        for idx in self._indexes:
            for s in idx.schemas.values():
                out.setdefault(s.name, (s.encoding, s.data.decode("utf-8", "replace")))
        return out

    def offered_qos_profiles(self, topic: str) -> list[dict[str, Any]]:
        """The offered QoS profiles recorded for a topic (parsed ``offered_qos_profiles``)."""
        for idx in self._indexes:
            for ch in idx.channels.values():
                if ch.topic == topic:
                    text = ch.metadata.get("offered_qos_profiles", "")
                    try:
                        loaded = yaml.safe_load(text) if text else None
                    except (yaml.YAMLError, RecursionError):
                        loaded = None  # unreadable offer: the default QoS
                    return list(loaded) if isinstance(loaded, list) else []
        raise KeyError(topic)

    def qos(self, topic: str) -> str:
        """The :data:`QOS_PRESETS` name matching a topic's recorded offer.

        ``sensor_data`` for best effort, ``transient_local`` for latched, else ``reliable``.
        """
        profiles = self.offered_qos_profiles(topic)
        if any(str(p.get("reliability")) in ("best_effort", "2") for p in profiles):
            return "sensor_data"
        if profiles and all(
            str(p.get("durability")) in ("transient_local", "1") for p in profiles
        ):
            return "transient_local"
        return "reliable"

    def message_encodings(self) -> dict[str, str]:
        """Each topic's message encoding (``cdr`` in a ROS 2 bag): {name: encoding}."""
        out: dict[str, str] = {}
        for idx in self._indexes:
            for ch in idx.channels.values():
                out.setdefault(ch.topic, ch.message_encoding)
        return out

    def unknown_types(self) -> dict[str, str]:
        """Topics whose message type cannot be imported here: {topic: msgtype}."""
        return {t: m for t, m in self.topics().items() if get_message_class(m) is None}

    # -- messages ----------------------------------------------------------------------------

    def raw_messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Serialized messages in file order.

        Args:
            topics: Topic names to keep (None: all).
            start_ns: Keep messages logged at or after this time (ns).
            end_ns: Keep messages logged before this time (ns).

        Yields:
            (topic, msgtype, CDR bytes, log time in ns).

        """
        wanted = {topics} if isinstance(topics, str) else (set(topics) if topics else None)
        for index in self._indexes:
            # a copy: the pass re-reads channel records and must not disturb the index
            pass_index = _FileIndex(index.path, dict(index.schemas), dict(index.channels))
            rec = Recovery()
            skip: frozenset[int] = frozenset()
            if wanted is not None and index.chunk_channels is not None:
                ids = {cid for cid, ch in index.channels.items() if ch.topic in wanted}
                skip = frozenset(
                    start for start, chans in index.chunk_channels.items() if not chans & ids
                )  # e.g. the cameras of a bag of strips: its first chunk only, not 2.5 GB
            scan = _scan(
                pass_index,
                rec,
                validate_crcs=self.validate_crcs,
                start_ns=start_ns,
                end_ns=end_ns,
                stop_at_data_end=index.recovery.complete,
                skip_chunks=skip,
            )
            for m in _guarded(scan, index.path):
                ch = pass_index.channels.get(m.channel_id)
                if ch is None or (wanted is not None and ch.topic not in wanted):
                    continue
                yield RawMessage(ch.topic, pass_index.msgtype(ch), m.data, m.log_time)
            if not rec.complete and index.recovery.complete and rec.error:
                # damage the summary did not show (a chunk failing its CRC): report it
                index.recovery._fail(rec.error)
                index.recovery.corrupt_chunks = rec.corrupt_chunks
                self.recovery._fail(rec.error)
                self.recovery.corrupt_chunks += rec.corrupt_chunks

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        image_views: bool = False,
    ) -> Iterator[BagMessage]:
        """Deserialized messages (rclpy objects) in file order.

        Messages of types that cannot be imported are skipped and counted in :attr:`skipped`;
        messages that fail to deserialize are counted in :attr:`decode_errors`.

        Args:
            topics: Topic names to keep (None: all).
            start_ns: Keep messages logged at or after this time (ns).
            end_ns: Keep messages logged before this time (ns).
            image_views: sensor_msgs/Image messages as :class:`~.cdr.ImageView` (the pixels a
                view on the bag's bytes; 5 us instead of rclpy's 8.7 ms per full-size strip).

        Yields:
            (topic, message object, log time in ns).

        """
        from rclpy.serialization import deserialize_message

        self.skipped = {}
        self.decode_errors = {}
        classes: dict[str, type | None] = {}
        for topic, msgtype, data, t in self.raw_messages(topics, start_ns, end_ns):
            if image_views and msgtype == "sensor_msgs/msg/Image":
                try:
                    view = parse_image(data)
                except CdrError:
                    self.decode_errors[topic] = self.decode_errors.get(topic, 0) + 1
                    continue
                if view is not None:
                    yield BagMessage(topic, view, t)
                    continue
            if msgtype not in classes:
                classes[msgtype] = get_message_class(msgtype)
            cls = classes[msgtype]
            if cls is None:
                self.skipped[topic] = self.skipped.get(topic, 0) + 1
                continue
            try:
                msg: Any = deserialize_message(data, cls)
            except Exception:  # rclpy raises assorted exception types for bad CDR
                self.decode_errors[topic] = self.decode_errors.get(topic, 0) + 1
                continue
            yield BagMessage(topic, msg, t)
