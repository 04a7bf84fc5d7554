"""SPH solver library: plain parameters in (solver.params), arrays out, typed errors
(solver.errors). It knows nothing of job files, caches or the command line."""
