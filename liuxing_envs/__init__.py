"""liuxing_envs: Gymnasium environments for active perception and gentle manipulation on MuJoCo."""

__version__ = "0.1.0"
