"""ros/cdr.py: sensor_msgs/Image read from its CDR bytes equals what rclpy deserializes."""

from __future__ import annotations

import array
from typing import Any

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from parproj_ros.ros import conversions as conv
from parproj_ros.ros.cdr import CdrError, ImageView, parse_image

pytestmark = pytest.mark.ros  # compared with rclpy's own (de)serialization


def _image(frame_id: str, encoding: str, h: int, w: int, itemsize: int, pad: int = 0) -> Image:
    rng = np.random.default_rng(len(frame_id) * 7 + h)
    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = -3 if h == 1 else 1_700_000_123, 999_999_999
    m.header.frame_id = frame_id
    m.height, m.width, m.encoding = h, w, encoding
    m.is_bigendian = int(len(frame_id) % 2)
    m.step = w * itemsize + pad
    m.data = array.array("B", rng.integers(0, 256, m.step * h, dtype=np.uint8).tobytes())
    return m


# frame ids of every length mod 4 (the fields after them land on every alignment), and
# encodings of odd and even lengths
CASES = [
    ("", "mono16", 3, 5, 2, 0),
    ("a", "mono8", 4, 7, 1, 1),
    ("ab", "16UC1", 1, 9, 2, 0),
    ("abc", "32FC1", 2, 3, 4, 4),
    ("left_cam", "mono16", 500, 64, 2, 0),
    ("vue gauche é", "mono8", 0, 0, 1, 0),
]


@pytest.mark.parametrize(("frame_id", "encoding", "h", "w", "itemsize", "pad"), CASES)
def test_parse_image_equals_rclpy(
    frame_id: str, encoding: str, h: int, w: int, itemsize: int, pad: int
) -> None:
    msg = _image(frame_id, encoding, h, w, itemsize, pad)
    raw = serialize_message(msg)
    ref = deserialize_message(raw, Image)
    got = parse_image(raw)
    assert isinstance(got, ImageView)
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (
        ref.header.stamp.sec,
        ref.header.stamp.nanosec,
    )
    assert got.header.frame_id == ref.header.frame_id
    assert (got.height, got.width, got.encoding, got.is_bigendian, got.step) == (
        ref.height,
        ref.width,
        ref.encoding,
        ref.is_bigendian,
        ref.step,
    )
    assert got.data.tobytes() == bytes(ref.data)
    assert got.data.base is not None  # a view on the bytes, not a copy
    if h and w and encoding in conv.ENCODING_DTYPES:
        np.testing.assert_array_equal(conv.image_to_array(got), conv.image_to_array(ref))


def test_every_truncation_is_a_cdr_error() -> None:
    raw = serialize_message(_image("abc", "mono16", 2, 3, 2))
    for n in range(len(raw)):
        with pytest.raises(CdrError, match="truncated"):
            parse_image(raw[:n])


def test_big_endian_cdr_is_read() -> None:
    """An XCDR1 big-endian message (encapsulation 00 00), written here field by field."""
    import struct

    body = b"".join(
        [
            struct.pack(">iI", 12, 34),
            struct.pack(">I", 4) + b"cam\x00",
            struct.pack(">II", 1, 2),
            struct.pack(">I", 7) + b"mono16\x00",
            b"\x01",  # at offset 35: the step (offset 36) needs no padding
            struct.pack(">I", 4),
            struct.pack(">I", 4) + b"\x01\x02\x03\x04",
        ]
    )
    got = parse_image(b"\x00\x00\x00\x00" + body)
    assert got is not None
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (12, 34, "cam")
    assert (got.height, got.width, got.encoding, got.is_bigendian, got.step) == (
        1,
        2,
        "mono16",
        1,
        4,
    )
    np.testing.assert_array_equal(conv.image_to_array(got), [[0x0102, 0x0304]])


def test_other_encapsulations_are_left_to_rclpy() -> None:
    raw = bytearray(serialize_message(_image("a", "mono8", 1, 1, 1)))
    raw[1] = 0x07  # XCDR2 little-endian
    assert parse_image(bytes(raw)) is None


def test_damaged_messages_raise_only_cdr_errors() -> None:
    """A valid message with random bytes changed, cut or added: an image or a CdrError."""
    good = serialize_message(_image("cam", "mono16", 2, 3, 2))
    rng = np.random.default_rng(5)
    outcomes = {"image": 0, "error": 0}
    for _ in range(3000):
        raw = bytearray(good)
        for _ in range(int(rng.integers(1, 4))):
            raw[int(rng.integers(4, len(raw)))] = int(rng.integers(0, 256))
        cut = int(rng.integers(-8, 8))
        raw = raw[:cut] if cut < 0 else raw + bytes(cut)
        try:
            got = parse_image(bytes(raw))
        except CdrError:
            outcomes["error"] += 1
            continue
        assert got is not None
        assert got.data.size <= len(raw)
        outcomes["image"] += 1
    assert outcomes["image"] > 0 and outcomes["error"] > 0  # both paths were taken


# ---- NormalizedBlock written as CDR -------------------------------------------------------------


def _block(dtype: np.dtype, shape: tuple[int, int], side: str, pair_id: str) -> Any:
    from parproj_ros.core.results import BlockResult
    from parproj_ros.imaging.resample import OutputGrid

    rng = np.random.default_rng(shape[0] * 31 + shape[1])
    img = (rng.random(shape) * 3000).astype(dtype)
    grid = OutputGrid(width=shape[1] * 3 + 1, height=shape[0], pixel=0.8, x_origin=12.25,
                      y_origin=-3.5)  # fmt: skip
    return BlockResult(pair_id, side, 2, shape[1], img, grid, 1_700_000_001_234_567_891, True)


BLOCKS = [
    (np.dtype(np.uint16), (7, 5), "left", "a+b"),
    (np.dtype(np.uint8), (3, 9), "right", "scene_0001+scene_0002"),
    (np.dtype(np.float32), (4, 4), "left", "é"),
    (np.dtype(">u2"), (2, 3), "right", ""),  # big-endian pixels: refused, as by block_to_msg
]


@pytest.mark.parametrize(("dtype", "shape", "side", "pair_id"), BLOCKS)
def test_block_cdr_is_the_message(
    dtype: np.dtype, shape: tuple[int, int], side: str, pair_id: str
) -> None:
    """block_to_cdr's bytes, deserialized by rclpy, are block_to_msg's message, field by
    field; and rclpy serializes that message to the same bytes (padding included)."""
    from parproj_msgs.msg import NormalizedBlock

    blk = _block(dtype, shape, side, pair_id)
    if dtype.byteorder == ">":
        with pytest.raises(conv.ConversionError):  # as block_to_msg: not an Image pixel type
            conv.block_to_cdr(blk, frame_id="cam")
        return
    raw = conv.block_to_cdr(blk, frame_id="cam")
    ref = conv.block_to_msg(blk, frame_id="cam")
    got = deserialize_message(raw, NormalizedBlock)
    assert got == ref
    np.testing.assert_array_equal(conv.image_to_array(got.image), blk.image)
    again = serialize_message(got)
    assert len(again) == len(raw)


def test_block_cdr_read_by_mcap_ros2() -> None:
    """An independent decoder (mcap-ros2-support, from the message definition) reads it."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    from parproj_ros.ros.bag import message_definition

    blk = _block(np.dtype(np.uint16), (6, 4), "right", "p1+p2")
    enc, text = message_definition("parproj_msgs/msg/NormalizedBlock")
    schema = Schema(id=1, name="parproj_msgs/msg/NormalizedBlock", encoding=enc,
                    data=text.encode())  # fmt: skip
    decode = DecoderFactory().decoder_for("cdr", schema)
    assert decode is not None
    m = decode(conv.block_to_cdr(blk, frame_id="cam"))
    assert (m.pair_id, m.side, m.col0, m.index, m.last) == ("p1+p2", "right", 4, 2, True)
    assert (m.full_width, m.full_height, m.pixel_size, m.x_origin, m.y_origin) == (
        13, 6, 0.8, 12.25, -3.5
    )  # fmt: skip
    assert m.header.frame_id == m.image.header.frame_id == "cam/normalized_right"
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_001, 234_567_891)
    assert (m.image.height, m.image.width, m.image.encoding, m.image.step) == (6, 4, "mono16", 8)
    np.testing.assert_array_equal(
        np.frombuffer(bytes(m.image.data), "<u2").reshape(6, 4), blk.image
    )
