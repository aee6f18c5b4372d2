"""Ground control point files (CSV or YAML), read into :class:`~..core.results.GroundPoint`.

CSV: a header line and one row per observation of a point in a scene::

    id,X,Y,Z,check,scene_id,line,sample
    g01,1520.3,-880.0,412.7,0,left_0000,1033.25,517.5

X, Y, Z are object coordinates in metres (the node's frame_id); check is 0/1 (or true/false);
line and sample are continuous pixel coordinates in the scene (pixel centres at integers).
Rows with the same id are one point (its X, Y, Z and check must agree).

YAML::

    points:
      - id: g01
        xyz: [1520.3, -880.0, 412.7]
        check: false
        observations: {left_0000: [1033.25, 517.5], right_0000: [998.0, 520.1]}

Files are UTF-8 text of at most :data:`MAX_GCP_FILE_BYTES` (16 MiB: about 200,000 CSV rows);
anything else that is not a regular file (a folder, a FIFO, a device) is refused before it is
opened for reading, so loading never blocks. Every problem raises :class:`GcpFileError`, whose
message starts with the file's path.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from ..core.results import GroundPoint

#: Largest GCP file read, bytes.
MAX_GCP_FILE_BYTES = 16 * 1024 * 1024


class GcpFileError(ValueError):
    """A GCP file that cannot be used, with the line or entry at fault.

    Attributes:
        path: the file (the message starts with it), when known.
    """

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else str(path)
        if self.path is not None and not message.startswith(self.path):
            message = f"{self.path}: {message}"
        super().__init__(message)


def _bool(text: object) -> bool:
    t = str(text).strip().lower()
    if t in ("1", "true", "yes", "y", "check"):
        return True
    if t in ("0", "false", "no", "n", "", "gcp"):
        return False
    raise GcpFileError(f"check flag {text!r} is not 0/1/true/false")


def load_gcp_file(path: str | Path) -> list[GroundPoint]:
    """Read a .csv or .yaml/.yml GCP file (format in the module docstring)."""
    p = Path(path)
    from .files import InputError, decode_utf8, read_bounded

    try:
        text = decode_utf8(p, read_bounded(p, MAX_GCP_FILE_BYTES, "GCP file"))
    except InputError as err:
        raise GcpFileError(err.problem, p) from None
    if p.suffix.lower() in (".yaml", ".yml"):
        return _load_yaml(p, text)
    try:
        return _load_csv(p, text)
    except csv.Error as err:
        raise GcpFileError(f"not CSV ({err})", p) from None


def _load_csv(path: Path, text: str) -> list[GroundPoint]:
    points: dict[str, GroundPoint] = {}
    with io.StringIO(text, newline="") as fh:
        reader = csv.DictReader(fh)
        need = {"id", "X", "Y", "Z", "scene_id", "line", "sample"}
        missing = need - set(reader.fieldnames or [])
        if missing:
            raise GcpFileError(f"{path}: missing columns {sorted(missing)}", path)
        for row in reader:
            n = reader.line_num  # the file's line, blank lines included
            short = sorted(k for k in need if row.get(k) is None)
            if short:
                raise GcpFileError(f"{path}:{n}: no value for {short}", path)
            try:
                xyz = np.array([float(row["X"]), float(row["Y"]), float(row["Z"])])
                obs = (float(row["line"]), float(row["sample"]))
                check = _bool(row.get("check") or "0")
            except (TypeError, ValueError) as err:
                raise GcpFileError(f"{path}:{n}: {err}", path) from err
            if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(obs))):
                raise GcpFileError(f"{path}:{n}: non-finite value", path)
            pid = row["id"].strip()
            old = points.get(pid)
            if old is None:
                points[pid] = GroundPoint(pid, xyz, check, {row["scene_id"].strip(): obs})
            else:
                if not np.allclose(old.xyz, xyz, rtol=0.0, atol=1e-6) or old.check != check:
                    raise GcpFileError(
                        f"{path}:{n}: point {pid} repeated with other X Y Z/check", path
                    )
                old.observations[row["scene_id"].strip()] = obs
    return list(points.values())


def _load_yaml(path: Path, text: str) -> list[GroundPoint]:
    import yaml

    try:
        doc = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise GcpFileError(f"{path}: not YAML ({first})", path) from err
    if not isinstance(doc, dict) or not isinstance(doc.get("points"), list):
        raise GcpFileError(f"{path}: expected a mapping with a 'points' list", path)
    out = []
    for i, item in enumerate(doc["points"]):
        if not isinstance(item, dict):
            raise GcpFileError(f"{path}: points[{i}]: expected a mapping (id, xyz, ...)", path)
        observations = item.get("observations") or {}
        if not isinstance(observations, dict):
            raise GcpFileError(
                f"{path}: points[{i}]: observations must map scene ids to [line, sample]", path
            )
        try:
            xyz = np.asarray(item["xyz"], dtype=float)
            obs = {str(k): (float(v[0]), float(v[1])) for k, v in observations.items()}
            gp = GroundPoint(str(item["id"]), xyz, _bool(item.get("check", False)), obs)
        except (KeyError, TypeError, ValueError, IndexError, OverflowError) as err:
            raise GcpFileError(f"{path}: points[{i}]: {err!r}", path) from err
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            raise GcpFileError(f"{path}: points[{i}]: xyz must be 3 finite numbers", path)
        bad = [k for k, v in obs.items() if not np.all(np.isfinite(v))]
        if bad:
            raise GcpFileError(f"{path}: points[{i}]: non-finite observation in {bad}", path)
        out.append(gp)
    return out


def save_gcp_csv(points: list[GroundPoint], path: str | Path) -> None:
    """Write points in the CSV format above."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "X", "Y", "Z", "check", "scene_id", "line", "sample"])
        for p in points:
            for sid, (line, sample) in p.observations.items():
                w.writerow(
                    [
                        p.id,
                        *(f"{v:.6f}" for v in p.xyz),
                        int(p.check),
                        sid,
                        f"{line:.6f}",
                        f"{sample:.6f}",
                    ]
                )
