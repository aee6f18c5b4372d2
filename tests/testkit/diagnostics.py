"""Reading diagnostic statuses (DiagnosticStatus messages, or the same fields) in assertions."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def level(s: Any) -> int:
    """A status's level as an int (rclpy gives the byte field as bytes)."""
    return s.level[0] if isinstance(s.level, bytes | bytearray) else int(s.level)


def show(sts: Iterable[Any]) -> str:
    """Statuses one a line, for assertion messages."""
    return "\n".join(f"  [{level(s)}] {s.name}: {s.message}" for s in sts) or "  (none)"
