"""``python -m docgen.pictures``: render one picture of each task into docs/images/.

ViewPlanning after two views (the fused points and the camera's frustum drawn in);
InstrumentGrasp mid-lift under the privileged scripted grasp, pads shaded by their force.
Seeded, so the same code draws the same pictures.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import liuxing_envs  # noqa: E402, F401  (registers the ids)
from docgen.results import ROOT  # noqa: E402

IMAGES = ROOT / "docs" / "images"
SEED = 3


def view_planning_picture() -> np.ndarray:
    """ViewPlanning-v1 after two views of a held-out object."""
    env = gym.make("ViewPlanning-v1", object_set="held_out", render_mode="rgb_array")
    env.reset(seed=SEED)
    for view in ((0.5, 0.2, 0.0), (-0.5, 0.4, 0.0)):
        env.step(np.array(view, dtype=np.float32))
    frame = env.render()
    env.close()
    return frame


def instrument_grasp_picture(steps: int = 150) -> np.ndarray:
    """InstrumentGrasp-v1 after ``steps`` control steps of the privileged scripted grasp."""
    from agents.grasp_baselines import PrivilegedGrasp

    env = gym.make("InstrumentGrasp-v1", render_mode="rgb_array")
    observation, _ = env.reset(seed=SEED)
    expert = PrivilegedGrasp(env.unwrapped)
    expert.reset(seed=SEED)
    for _ in range(steps):
        observation, _, terminated, truncated, _ = env.step(expert.act(observation))
        if terminated or truncated:
            break
    frame = env.render()
    env.close()
    return frame


def main() -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    for name, draw in (
        ("view_planning.png", view_planning_picture),
        ("instrument_grasp.png", instrument_grasp_picture),
    ):
        Image.fromarray(draw()).save(IMAGES / name, optimize=True)
        print(f"wrote {(IMAGES / name).relative_to(ROOT)}")


if __name__ == "__main__":
    main()
