"""Frame ranges as farm managers write them: `12`, `1-48`, `1-48x4`, `1-10,20-24`."""
from __future__ import annotations

import re

from .errors import UsageError

_PART = re.compile(r"^\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*(?:x\s*(\d+)\s*)?)?$")


def parse_frames(text: str, shot: range, what: str = "--frames") -> list[int]:
    """Parse a frame range and check it lies inside the shot's frame range."""
    frames: list[int] = []
    for part in text.split(","):
        m = _PART.match(part)
        if not m:
            raise UsageError(f"{what}: expected A, A-B or A-BxSTEP (comma-separated), got {text!r}")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        step = int(m.group(3)) if m.group(3) else 1
        if b < a:
            raise UsageError(f"{what}: range end must be >= start, got {a}-{b}")
        if step < 1:
            raise UsageError(f"{what}: step must be >= 1, got {step}")
        frames.extend(range(a, b + 1, step))
    outside = [f for f in frames if f not in shot]
    if outside:
        raise UsageError(f"{what}: frame {outside[0]} is outside the shot's range "
                         f"{shot.start}-{shot.stop - 1}")
    return sorted(set(frames))


def format_frames(frames) -> str:
    """Compact form for messages: 1-4,7,9-10."""
    frames = sorted(frames)
    if not frames:
        return "none"
    out, start, prev = [], frames[0], frames[0]
    for f in frames[1:] + [None]:
        if f is not None and f == prev + 1:
            prev = f
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if f is not None:
            start = prev = f
    return ",".join(out)
