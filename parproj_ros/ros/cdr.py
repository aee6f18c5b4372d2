"""Images to and from CDR bytes without rclpy's message objects (the hot path's two copies).

Reading: sensor_msgs/Image straight from its CDR bytes, the pixels as a view (no copy).
Writing: parproj_msgs/NormalizedBlock (a streamed block, carrying a sensor_msgs/Image) as CDR
bytes in one copy of the pixels, published with ``Publisher.publish(bytes)`` and written to
bags with ``BagWriter.write_raw``.

``rclpy.serialization.deserialize_message`` builds an Image by copying the CDR bytes into a C
message and the C message into a Python ``array.array``: 8.7 ms per 500 x 13816 mono16 strip
(13.8 MB) on the 2-core machine, with the GIL held; at the IKONOS rate (26 strips/s) that is a
quarter of a core taken from the worker. :func:`parse_image` reads the few fixed fields and
returns the pixels as a ``numpy`` view on the bytes it was given: 5 us per strip.

The layout read is ROS 2's CDR (XCDR1, plain): a 4-byte encapsulation header (``00 01``
little-endian, ``00 00`` big-endian, then two option bytes) and then, aligned on their size
counted from the end of that header::

    int32 stamp.sec, uint32 stamp.nanosec, string frame_id,
    uint32 height, uint32 width, string encoding, uint8 is_bigendian, uint32 step,
    sequence<uint8> data

(a string is a uint32 length that counts its terminating NUL, then the bytes and the NUL). Other
encapsulations (XCDR2, parameter lists) are not read here: :func:`parse_image` returns None and
the caller deserializes with rclpy. :func:`serialize_block` writes little-endian plain CDR,
padding bytes zero. Both are checked field by field against rclpy's own (de)serialization, and
the blocks also by mcap-ros2-support's decoder, in ``tests/ros/test_cdr.py``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Encapsulation identifiers read here: plain CDR, big- and little-endian.
_CDR_BE, _CDR_LE = b"\x00\x00", b"\x00\x01"
_HEADER = 4


class CdrError(ValueError):
    """CDR bytes that are not a well-formed sensor_msgs/Image, with what was wrong."""


@dataclass
class Stamp:
    """builtin_interfaces/Time: seconds and nanoseconds."""

    sec: int = 0
    nanosec: int = 0


@dataclass
class Header:
    """std_msgs/Header: stamp and frame id."""

    stamp: Stamp = field(default_factory=Stamp)
    frame_id: str = ""


@dataclass
class ImageView:
    """The fields of a sensor_msgs/Image; ``data`` a uint8 view on the CDR bytes (read-only).

    Has the attributes the conversions read from an rclpy Image (``header.stamp``,
    ``header.frame_id``, ``height``, ``width``, ``encoding``, ``is_bigendian``, ``step``,
    ``data``), so it goes wherever a received Image goes.
    """

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: NDArray[np.uint8]


class _Cursor:
    """Reads aligned CDR primitives from ``buf``, every read checked against its length."""

    def __init__(self, buf: memoryview, endian: str) -> None:
        self.buf = buf
        self.pos = _HEADER
        self.endian = endian

    def _align(self, size: int) -> None:
        rel = self.pos - _HEADER
        self.pos += (-rel) % size

    def _need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > len(self.buf):
            raise CdrError(
                f"truncated: {what} needs {n} bytes at offset {self.pos}, "
                f"the message has {len(self.buf)}"
            )

    def u32(self, what: str, signed: bool = False) -> int:
        self._align(4)
        self._need(4, what)
        (v,) = struct.unpack_from(self.endian + ("i" if signed else "I"), self.buf, self.pos)
        self.pos += 4
        return int(v)

    def u8(self, what: str) -> int:
        self._need(1, what)
        v = self.buf[self.pos]
        self.pos += 1
        return int(v)

    def string(self, what: str) -> str:
        n = self.u32(f"{what} length")
        self._need(n, what)
        raw = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        if n and raw[-1:] == b"\x00":
            raw = raw[:-1]
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise CdrError(f"{what} is not UTF-8 ({err})") from None

    def octets(self, what: str) -> NDArray[np.uint8]:
        n = self.u32(f"{what} length")
        self._need(n, what)
        arr = np.frombuffer(self.buf, dtype=np.uint8, count=n, offset=self.pos)
        self.pos += n
        return arr


def parse_image(data: bytes | bytearray | memoryview) -> ImageView | None:
    """A sensor_msgs/Image from its serialized bytes, the pixels not copied.

    Args:
        data: The CDR bytes as received (``raw=True`` subscription) or stored in a bag,
            encapsulation header included. They must not change while the view is used.

    Returns:
        The image, or None when the encapsulation is not plain CDR (deserialize it with rclpy).

    Raises:
        CdrError: the bytes end before a field, or a string is not UTF-8.
    """
    buf = memoryview(data).cast("B")
    if len(buf) < _HEADER:
        raise CdrError(f"truncated: {len(buf)} bytes, not even the encapsulation header")
    kind = bytes(buf[:2])
    if kind not in (_CDR_BE, _CDR_LE):
        return None
    c = _Cursor(buf, "<" if kind == _CDR_LE else ">")
    sec = c.u32("header.stamp.sec", signed=True)
    nanosec = c.u32("header.stamp.nanosec")
    frame_id = c.string("header.frame_id")
    height = c.u32("height")
    width = c.u32("width")
    encoding = c.string("encoding")
    is_bigendian = c.u8("is_bigendian")
    step = c.u32("step")
    pixels = c.octets("data")
    return ImageView(
        Header(Stamp(sec, nanosec), frame_id), height, width, encoding, is_bigendian, step, pixels
    )


class _Writer:
    """Appends aligned little-endian CDR primitives (alignment counted after the header)."""

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def _align(self, size: int) -> None:
        self.buf += bytes((-(len(self.buf) - _HEADER)) % size)

    def u32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", v)

    def f64(self, v: float) -> None:
        self._align(8)
        self.buf += struct.pack("<d", v)

    def u8(self, v: int) -> None:
        self.buf += struct.pack("<B", v)

    def string(self, v: str) -> None:
        raw = v.encode("utf-8")
        self.u32(len(raw) + 1)
        self.buf += raw + b"\x00"

    def stamp(self, ns: int) -> None:
        sec, nanosec = divmod(int(ns), 1_000_000_000)
        self.i32(sec)
        self.u32(nanosec)


def serialize_block(
    *,
    frame_id: str,
    stamp_ns: int,
    pair_id: str,
    side: str,
    col0: int,
    full_width: int,
    full_height: int,
    pixel_size: float,
    x_origin: float,
    y_origin: float,
    index: int,
    last: bool,
    encoding: str,
    pixels: NDArray[np.generic],
) -> bytes:
    """A parproj_msgs/NormalizedBlock as CDR bytes (encapsulation header included).

    The header and the image's header carry ``frame_id`` and ``stamp_ns`` (ns since the epoch,
    >= 0); ``pixels`` is the image, (height, width), C-contiguous and little-endian, of that
    ``encoding`` (``conversions.block_to_cdr`` checks both). The pixels are copied once, into
    the returned bytes.
    """
    px = pixels
    w = _Writer()
    w.stamp(stamp_ns)
    w.string(frame_id)
    w.string(pair_id)
    w.string(side)
    for v in (col0, full_width, full_height):
        w.u32(int(v))
    for f in (pixel_size, x_origin, y_origin):
        w.f64(float(f))
    w.u32(int(index))
    w.u8(1 if last else 0)
    w.stamp(stamp_ns)  # image.header
    w.string(frame_id)
    w.u32(int(px.shape[0]))
    w.u32(int(px.shape[1]))
    w.string(encoding)
    w.u8(0)  # is_bigendian
    w.u32(int(px.shape[1] * px.itemsize))
    w.u32(int(px.nbytes))
    return b"".join((w.buf, px.reshape(-1).view(np.uint8).data))


def read_image(raw: Any) -> Any:
    """A received Image, read from its CDR bytes (:func:`parse_image`): an :class:`ImageView`.

    Bytes that are not plain CDR are deserialized by rclpy; an Image already deserialized is
    returned as it is.

    Raises:
        CdrError: the bytes are not a well-formed Image.
    """
    if not isinstance(raw, bytes | bytearray | memoryview):
        return raw
    view = parse_image(raw)
    if view is not None:
        return view
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    try:
        return deserialize_message(bytes(raw), Image)
    except Exception as err:  # rclpy raises assorted exception types for bad CDR
        raise CdrError(f"rclpy could not deserialize it: {type(err).__name__}: {err}") from None
