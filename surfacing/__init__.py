"""Surface reconstruction library: particles -> block-sparse color field -> marching-cubes
mesh and OpenVDB grids. Plain parameters in (surfacing.reconstruct.SurfaceParams), arrays
out, typed errors (surfacing.grid.SurfacingError). It knows nothing of job files or caches."""
