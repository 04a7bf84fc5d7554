"""Sim frame and checkpoint files (HDF5): the contract between the sim stage and the others.

Frame datasets: position (N,3) f32 m, velocity (N,3) f32 m/s, density (N,) f32 kg/m^3,
pressure (N,) f32 Pa, id (N,) i32, fluid (N,) i32. Attributes: frame, time (s),
particle_radius (m), fluid_names, fluid_rest_density (kg/m^3), fluid_mass (kg), plus the
solver's counters. Checkpoints add the solver's exact state (half-step velocity, last
acceleration, particle order) and its time-step controller.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from .cache import atomic_path

FRAME_DATASETS = {"position": np.float32, "velocity": np.float32, "density": np.float32,
                  "pressure": np.float32, "id": np.int32, "fluid": np.int32}


def write_h5(final: Path, datasets: dict[str, np.ndarray], attrs: dict) -> Path:
    with atomic_path(final) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, v in datasets.items():
                f.create_dataset(k, data=v)
            for k, v in attrs.items():
                f.attrs[k] = v
    return final


def write_frame(final: Path, data: dict[str, np.ndarray], attrs: dict) -> Path:
    return write_h5(final, {k: np.asarray(data[k], dtype=t) for k, t in FRAME_DATASETS.items()}, attrs)


def read_h5(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with h5py.File(path, "r") as f:
        data = {k: f[k][()] for k in f.keys()}
        attrs = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in f.attrs.items()}
    attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
    if "fluid_names" in attrs:
        attrs["fluid_names"] = [n.decode() if isinstance(n, bytes) else str(n) for n in attrs["fluid_names"]]
    return data, attrs


read_frame = read_h5
