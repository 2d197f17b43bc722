"""Orchestration: many runs of the pipeline at once. `grid` expands an experiment file into the stage graph and
runs it (a local pool or Ray), `select` chooses settings on the tuning stream, `quickstart` runs the whole pipeline
on one maze."""
