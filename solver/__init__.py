"""Taichi SPH solver (Müller, Charypar & Gross 2003, weakly compressible with Tait's equation)."""
