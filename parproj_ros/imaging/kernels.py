"""The resampling kernels: one table (:data:`KERNELS`) of name, OpenCV flag, support, meaning.

The ``interpolation`` parameter's choices and description (parproj_ros/core/params.py), the
OpenCV flag of the resampling (:func:`parproj_ros.imaging.resample.kernel_flag`), the lines a
streamed block keeps on each side (:func:`max_support_lines`) and the table in
docs/extending.md (:func:`kernels_markdown`) all come from here. Adding a kernel is one row
(docs/extending.md).

No numpy and no OpenCV here (the flag is named, resolved by imaging/resample.py): the parameter
table imports this module, and ``parproj`` starts without them.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kernel:
    """One resampling kernel of ``cv2.warpAffine`` / ``cv2.remap``.

    Attributes:
        name: the value of the ``interpolation`` parameter.
        opencv: name of the OpenCV flag (an attribute of ``cv2``, e.g. ``"INTER_CUBIC"``).
        support_lines: s: at source line y the kernel reads lines floor(y) - s + 1 ..
            floor(y) + s (bilinear 1, bicubic 2, Lanczos-4 4); a block keeps that many lines
            around those its tiles reach (tests/imaging/test_kernels.py checks it is enough and
            needed).
        description: what it does, for the docs.

    """

    name: str
    opencv: str
    support_lines: int
    description: str


#: The kernels, by parameter value; the first is the default.
KERNELS: dict[str, Kernel] = {
    k.name: k
    for k in (
        Kernel("linear", "INTER_LINEAR", 1, "bilinear, 2 x 2 source pixels"),
        Kernel("cubic", "INTER_CUBIC", 2, "bicubic, 4 x 4 source pixels: sharper, can overshoot"),
    )
}


def kernel(name: str) -> Kernel:
    """The row of ``name``.

    Raises:
        ValueError: not a kernel of :data:`KERNELS` (the known ones named).

    """
    try:
        return KERNELS[name]
    except KeyError:
        raise ValueError(
            f"interpolation {name!r}: not a resampling kernel (known: {', '.join(KERNELS)})"
        ) from None


def choices_text() -> str:
    """The kernel names in words, as the parameter's description gives them: ``'a' or 'b'``."""
    return " or ".join(repr(n) for n in KERNELS)


def max_support_lines() -> int:
    """The widest support of all kernels, lines (what a streamed block keeps on each side)."""
    return max(k.support_lines for k in KERNELS.values())


def kernels_markdown() -> str:
    """The kernel table as markdown (docs/extending.md holds it; a test compares)."""
    rows = [
        "| interpolation | OpenCV flag | support lines | kernel |",
        "|---|---|---|---|",
    ]
    rows += [
        f"| `{k.name}` | `cv2.{k.opencv}` | {k.support_lines} | {k.description} |"
        for k in KERNELS.values()
    ]
    return "\n".join(rows)


__all__ = ["KERNELS", "Kernel", "choices_text", "kernel", "kernels_markdown", "max_support_lines"]
