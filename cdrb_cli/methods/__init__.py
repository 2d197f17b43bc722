"""Method side: planners that learn from demonstration windows and sample whole trajectories.

Each method owns its loss and its sampler behind the small interface of :class:`cdrb_cli.methods.base.Method`."""

from __future__ import annotations

METHODS = ("cdrb", "diffuser", "mlp")


def build_method(config, spec, normalizer, buffer_points=None, device="cpu"):
    name = config.method.name
    if name == "cdrb":
        from cdrb_cli.methods.cdrb import CDRB

        return CDRB(config, spec, normalizer, buffer_points, device)
    if name == "diffuser":
        from cdrb_cli.methods.diffuser import Diffuser

        return Diffuser(config, spec, normalizer, device=device)
    if name == "mlp":
        from cdrb_cli.methods.mlp import MLPPlanner

        return MLPPlanner(config, spec, normalizer, device=device)
    raise ValueError(name)
