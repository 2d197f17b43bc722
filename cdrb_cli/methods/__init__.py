"""Method side: planners (whole trajectories) and policies (an action per step), each in its own module behind
the interface of :mod:`cdrb_cli.methods.base`, registered in :data:`cdrb_cli.methods.registry.METHODS`."""
