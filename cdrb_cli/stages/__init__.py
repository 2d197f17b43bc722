"""Library functions behind each CLI command: collect, cluster, train, plan, evaluate, report, pipeline."""
