"""Sensors of the suite's envs: depth capture and fusion pipelines."""
