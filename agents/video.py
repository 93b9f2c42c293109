"""mp4 videos of evaluation episodes: the environment's ``rgb_array`` render (ViewPlanning:
the scene with the camera frustum and the fused points; InstrumentGrasp: pads shaded by
force) with the task's text read-out of the figures that matter (its
:class:`agents.task_reports.TaskReport`), written with OpenCV."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from agents.contestants import slug
from agents.evaluation import make_env, seed_sampling

FONT = cv2.FONT_HERSHEY_SIMPLEX

VIDEOS_FOLDER = "videos"


def _annotate(frame: np.ndarray, title: str, lines: Sequence[str]) -> np.ndarray:
    frame = np.ascontiguousarray(frame[..., ::-1])  # RGB -> OpenCV's BGR
    for row, text in enumerate([title, *lines]):
        origin = (10, 24 + 24 * row)
        cv2.putText(frame, text, origin, FONT, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(frame, text, origin, FONT, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return frame


def record_videos(
    contestants, seeds: Iterable[int], out: Path, deterministic: bool = True
) -> list[Path]:
    """One mp4 per contestant under ``out/videos/``, its episodes of ``seeds`` one after
    another, acting as the report's episodes do (``deterministic``, or sampled from torch's
    generator seeded with each episode's seed); returns the written paths."""
    folder = Path(out) / VIDEOS_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    # Not at the top: agents.task_reports imports agents.report_folder, which imports this
    # module's VIDEOS_FOLDER.
    from agents.task_reports import report_for

    seeds = list(seeds)
    written = []
    for contestant in contestants:
        env = make_env(contestant.env_id, contestant.env_kwargs, render_mode="rgb_array")
        fps = env.metadata.get("render_fps", 20)
        presentation = report_for(contestant.env_id)
        repeat, dt = presentation.frame_timing(env, fps)
        path = folder / f"{slug(contestant.label)}.mp4"
        writer = None
        try:
            policy = contestant.make_policy(env)
            for seed in seeds:
                observation, info = env.reset(seed=int(seed))
                seed_sampling(int(seed), deterministic)  # so the video is the report's episode
                if hasattr(policy, "reset"):
                    policy.reset(seed=int(seed))
                step, done = 0, False
                while True:
                    frame = _annotate(
                        env.render(),
                        f"{contestant.label}  seed {seed}",
                        presentation.readout(info, step * dt),
                    )
                    if writer is None:
                        height, width = frame.shape[:2]
                        writer = cv2.VideoWriter(
                            str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height)
                        )
                    for _ in range(repeat):
                        writer.write(frame)
                    if done:
                        break
                    action, _ = policy.predict(observation, deterministic=deterministic)
                    observation, _, terminated, truncated, info = env.step(action)
                    step += 1
                    done = terminated or truncated
        finally:
            if writer is not None:
                writer.release()
            env.close()
        written.append(path)
    return written
