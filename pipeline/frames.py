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
    outside = sorted(set(f for f in frames if f not in shot))
    if outside:
        which = f"frames {format_frames(outside)}" if len(outside) > 1 else f"frame {outside[0]}"
        raise UsageError(f"{what}: {text.strip()} asks for {which}, outside the shot's range "
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


def chunk_from(first: int, size: int, frames, what: str) -> list[int]:
    """`size` frames of `frames` (ascending) starting at `first`, which must be one of them."""
    frames = list(frames)
    if first not in frames:
        raise UsageError(f"{what}: frame {first} is outside the shot's frame range "
                         f"{format_frames(frames)}")
    return [f for f in frames if f >= first][:size]


def _env_int(env, name: str, minimum: int | None = None, default: int | None = None) -> int:
    """An integer environment variable; `default` when it is unset or empty."""
    if not env.get(name) and default is not None:
        return default
    try:
        value = int(env[name])
    except ValueError:
        raise UsageError(f"{name}: expected an integer, got {env[name]!r}") from None
    if minimum is not None and value < minimum:
        raise UsageError(f"{name}: expected an integer >= {minimum}, got {value}")
    return value


def frames_from_env(env, shot: range, chunk: int | None) -> tuple[list[int], str] | None:
    """The frames of a farm task from its environment, or None outside a farm task.

    - OpenCue: ``CUE_IFRAME`` is the chunk's first frame, ``CUE_CHUNK`` its size and
      ``CUE_RANGE`` the layer's frame range (a chunk takes the next frames of that range).
    - SLURM array jobs: ``SLURM_ARRAY_TASK_ID`` is the chunk's first frame (submit with
      ``--array=START-END:CHUNK``) and the chunk size is ``--chunk`` or ``SPHSHOT_CHUNK``.

    Returns the frames and a line saying where they came from.
    """
    if "CUE_IFRAME" in env:
        first = _env_int(env, "CUE_IFRAME")
        size = chunk or _env_int(env, "CUE_CHUNK", minimum=1, default=1)
        layer = parse_frames(env["CUE_RANGE"], shot, "CUE_RANGE") if env.get("CUE_RANGE") else list(shot)
        frames = chunk_from(first, size, layer, "CUE_IFRAME")
        return frames, f"CUE_IFRAME={first} (chunk {size})"
    if "SLURM_ARRAY_TASK_ID" in env:
        first = _env_int(env, "SLURM_ARRAY_TASK_ID")
        size = chunk or _env_int(env, "SPHSHOT_CHUNK", minimum=1, default=1)
        frames = chunk_from(first, size, shot, "SLURM_ARRAY_TASK_ID")
        return frames, f"SLURM_ARRAY_TASK_ID={first} (chunk {size})"
    return None


def select_frames(arg: str | None, chunk: int | None, shot: range, env) -> tuple[list[int], str | None]:
    """The frames a `sphshot run` works on: --frames, else the farm's environment, else the shot.

    With --chunk N, --frames names the chunk's first frame only.
    """
    if arg is not None:
        if chunk:
            m = _PART.match(arg)
            if not m or m.group(2) is not None or "," in arg:
                raise UsageError(f"--frames: with --chunk, expected a single start frame, got {arg!r}")
            return chunk_from(int(m.group(1)), chunk, shot, "--frames"), None
        return parse_frames(arg, shot), None
    found = frames_from_env(env, shot, chunk)
    if found is not None:
        return found
    if chunk:
        raise UsageError("--chunk: needs a start frame from --frames, CUE_IFRAME or SLURM_ARRAY_TASK_ID")
    return list(shot), None
