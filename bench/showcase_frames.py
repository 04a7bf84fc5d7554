#!/usr/bin/env python3
"""Carry a few sim frames of a big shot from a GPU node back to where it is surfaced and
rendered, within the device's transfer limits (8 files of 16 MiB).

A 1.25M-particle sim frame is about 50 MB of HDF5. `pack` keeps what the surface and render
stages read, rounded: positions as 16-bit fractions of the domain box (37 um in the
showcase's 2.4 m, a hundredth of its 4 mm radius), velocity and density as float16 (three
significant digits: 0.05 % of the water's volume per particle), the fluid index as uint8;
pressure and ids are dropped. The particles are sorted by a coarse cell first, which lets lzma
find the repeats. `unpack` writes them back as the shot's sim frames, stamped as the cache
stamps a frame the sim stage wrote (pipeline.cache), so `sphshot run JOB --stage surface+
--frames ...` takes them from there. The stamp says which parameters made a frame, not where
it was computed: keep such a shot's output apart (its own shot.output).

    python3 bench/showcase_frames.py pack SIM_DIR OUT_DIR --frames 24,48 --max-mb 15.5
    .venv/bin/python bench/showcase_frames.py unpack JOB PACKED_FILE...
"""
from __future__ import annotations

import argparse
import io
import json
import lzma
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)

FORMAT = "sphshot-packed-frame-1"


def pack_frame(src: Path, dst: Path, lo, hi) -> int:
    """Write one sim frame (HDF5) as a packed file; returns its size in bytes."""
    from pipeline.formats import read_frame

    data, attrs = read_frame(src)
    pos = data["position"].astype(np.float64)
    vel, rho, fluid = data["velocity"], data["density"], data["fluid"]
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    q = np.clip(np.rint((pos - lo) / (hi - lo) * 65535), 0, 65535).astype(np.uint16)
    order = np.lexsort((q[:, 2] >> 9, q[:, 1] >> 9, q[:, 0] >> 9))     # 128 coarse cells an axis
    header = {"format": FORMAT, "n": len(pos), "lo": lo.tolist(), "hi": hi.tolist(), "attrs": attrs}
    buf = io.BytesIO()
    for a in (q[order], vel[order].astype(np.float16), rho[order].astype(np.float16),
              fluid[order].astype(np.uint8)):
        np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    tmp = dst.with_name(dst.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write((json.dumps(header, default=lambda v: v.item()) + "\n").encode())     # numpy scalars
        fh.write(lzma.compress(buf.getvalue(), preset=6))
    tmp.replace(dst)
    return dst.stat().st_size


def read_packed(path: Path) -> tuple[dict, dict]:
    """(frame datasets as formats.FRAME_DATASETS, attributes) of a packed file."""
    with open(path, "rb") as fh:
        header = json.loads(fh.readline())
        if header.get("format") != FORMAT:
            raise ValueError(f"{path}: not a packed sim frame ({FORMAT})")
        buf = io.BytesIO(lzma.decompress(fh.read()))
    q, vel, rho, fluid = (np.load(buf, allow_pickle=False) for _ in range(4))
    lo, hi = np.asarray(header["lo"]), np.asarray(header["hi"])
    n = header["n"]
    data = {"position": (lo + q.astype(np.float64) / 65535 * (hi - lo)).astype(np.float32),
            "velocity": vel.astype(np.float32), "density": rho.astype(np.float32),
            "pressure": np.zeros(n, np.float32), "id": np.arange(n, dtype=np.int32),
            "fluid": fluid.astype(np.int32)}
    return data, header["attrs"]


def pack(args) -> None:
    sim_dir, out = Path(args.sim_dir), Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lo, hi = json.loads(args.box)
    for frame in [int(x) for x in args.frames.split(",") if x]:
        src = sim_dir / f"{args.name}.{frame:04d}.h5"
        if not src.is_file():
            print(f"pack: {src} not there, skipped", flush=True)
            continue
        dst = out / f"{args.name}_{frame:04d}.sphpack"
        size = pack_frame(src, dst, lo, hi)
        if size > args.max_mb * 2**20:
            dst.unlink()
            print(f"pack: frame {frame}: {size / 2**20:.1f} MiB is over {args.max_mb} MiB, dropped", flush=True)
        else:
            print(f"pack: frame {frame}: {src.stat().st_size / 2**20:.1f} MiB -> {size / 2**20:.1f} MiB", flush=True)


def unpack(args) -> None:
    from pipeline import cache
    from pipeline.formats import write_frame
    from pipeline.spec import load_spec

    spec = load_spec(Path(args.job), [])
    shot = cache.ShotCache(spec)
    for p in args.files:
        data, attrs = read_packed(Path(p))
        frame = int(attrs["frame"])
        final = shot.paths.sim_frame(frame)
        final.parent.mkdir(parents=True, exist_ok=True)
        write_frame(final, data, attrs)
        cache.stamp(final, shot.hashes["sim"])
        print(f"unpack: frame {frame} -> {final}", flush=True)
    shot.record("sim")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("sim_dir")
    p.add_argument("out_dir")
    p.add_argument("--name", default="showcase", help="the shot's name (sim frames are NAME.NNNN.h5)")
    p.add_argument("--frames", required=True, help="comma-separated frame numbers")
    p.add_argument("--box", default="[[0, 0, 0], [2.4, 1.2, 1.0]]", help="the domain box [[lo], [hi]] in m")
    p.add_argument("--max-mb", type=float, default=15.5)
    u = sub.add_parser("unpack")
    u.add_argument("job")
    u.add_argument("files", nargs="+")
    args = ap.parse_args()
    pack(args) if args.cmd == "pack" else unpack(args)


if __name__ == "__main__":
    main()
