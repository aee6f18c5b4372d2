"""OSSIM ``.geom`` keyword lists (ossimRpcModel, ossimPleiadesModel, ...): read and write.

OSSIM image coordinates are 0-based with pixel centres at integers: no pixel shift.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..model import _A_TO_B, _COEFF_NAMES, _SCALARS, FloatArray, RPCModel
from .base import RPCFormatSpec, RPCValues, model_from_values, number


def read_keyword_list(path: str | Path) -> dict[str, str]:
    """An OSSIM keyword list (``key: value`` lines) as a dict of stripped strings."""
    out: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep and key.strip():
            out[key.strip()] = value.strip()
    return out


def detect(path: Path, head: bytes) -> bool:
    """A ``line_num_coeff_00:`` key (an optional ``prefix.`` before it) starts a line."""
    full = path.read_text(encoding="utf-8", errors="replace")
    pattern = r"^\s*([\w.]*\.)?line_num_coeff_00\s*:"
    return re.search(pattern, full, re.IGNORECASE | re.MULTILINE) is not None


def read(path: Path) -> RPCValues:
    """The values of an OSSIM keyword list with an RPC.

    Keys ``line_off``, ..., ``height_scale``, ``line_num_coeff_00`` .. ``_19`` etc. (an optional
    ``prefix.`` is accepted); ``polynomial_format: A`` coefficients are reordered to RPC00B;
    ``bias_error`` and ``rand_error`` when present.

    Raises:
        RPCFormatError: a value is malformed (file, key and value named).

    """
    kwl = read_keyword_list(path)
    flat: dict[str, str] = {}
    for key, value in kwl.items():
        flat.setdefault(key.rsplit(".", 1)[-1].lower(), value)
    values: RPCValues = {n: number(flat[n], n, path) for n in _SCALARS if n in flat}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name}_{i:02d}" for i in range(20)]
        if all(k in flat for k in keys):
            coeffs[name] = np.array([number(flat[k], k, path) for k in keys])
    if flat.get("polynomial_format", "B").strip().upper() == "A":
        coeffs = {k: v[_A_TO_B] for k, v in coeffs.items()}
    values.update(coeffs)
    if "bias_error" in flat:
        values["err_bias"] = number(flat["bias_error"], "bias_error", path)
    if "rand_error" in flat:
        values["err_rand"] = number(flat["rand_error"], "rand_error", path)
    return values


def read_geom(path: str | Path) -> RPCModel:
    """Read an OSSIM ``.geom`` keyword list with an RPC (:func:`read`).

    Raises:
        RPCFormatError: a key is missing or malformed.

    """
    return model_from_values(read(Path(path)), path)


def write_geom(
    path: str | Path, rpc: RPCModel, *, lines: int | None = None, samples: int | None = None
) -> None:
    """Write an OSSIM ``.geom`` keyword list (type ossimRpcModel, polynomial_format B).

    Values are written with Python's shortest round-trip repr, so reading gives the same bits.

    Args:
        path: output file.
        rpc: the model.
        lines: image lines (written as ``number_lines`` when given).
        samples: image samples (``number_samples``).

    """
    out = ["type:  ossimRpcModel", "polynomial_format:  B"]
    out += [f"bias_error:  {rpc.err_bias!r}", f"rand_error:  {rpc.err_rand!r}"]
    out += [f"{n}:  {getattr(rpc, n)!r}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [f"{name}_{i:02d}:  {float(c)!r}" for i, c in enumerate(getattr(rpc, name))]
    if lines is not None:
        out.append(f"number_lines:  {int(lines)}")
    if samples is not None:
        out.append(f"number_samples:  {int(samples)}")
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


FORMAT = RPCFormatSpec(
    name="geom",
    label=".geom",
    detect=detect,
    read=read,
    write=write_geom,
    extensions=(".geom",),
    sidecar_suffixes=(".geom", ".GEOM"),
)
