"""Surfacing: particles to colour field, OpenVDB grids and marching-cubes meshes."""
