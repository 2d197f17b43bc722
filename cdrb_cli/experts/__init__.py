"""Experts that produce demonstrations: the scripted maze planner and stable-baselines3 SAC(+HER) policies."""
