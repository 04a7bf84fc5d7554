"""sphshot pipeline: job spec, shot cache, stages, executors and the CLI."""
