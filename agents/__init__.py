"""Agents for the liuxing_envs suite: scripted baselines (and, later, SB3 training code)."""
