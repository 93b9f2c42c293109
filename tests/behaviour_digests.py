"""SHA-256 digests of what the envs do, to show what a refactor kept and what it changed.

Each configuration makes the *unwrapped* env (explicit kwargs, no registered time limit),
seeds its action space, and steps it with sampled actions for ``STEPS`` steps, resetting with
consecutive seeds at every episode end and every ``RESET_EVERY`` steps. Everything the env
returns is hashed: observations key by key, rewards, both flags and ``info`` (keys sorted,
values canonicalised). A digest per episode locates the first difference.

    python -m tests.behaviour_digests --out tests/data/behaviour_digests.json
    python -m tests.behaviour_digests --compare tests/data/behaviour_digests.json

Digests depend on the machine (CPU instructions change the last bits of MuJoCo's and
OpenGL's arithmetic): compare runs on one machine, recording the reference there from the
commit before the change when it was recorded elsewhere.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import liuxing_envs  # noqa: F401  (registers the ids)

REPO = Path(__file__).resolve().parents[1]
#: The env kwargs the shipped grasp policy was trained with on InstrumentGrasp-v0 (they are
#: InstrumentGrasp-v1's defaults).
SHIPPED_GRASP_TASK = {
    "obs_mode": "state",
    "reach_sharpness": 3.0,
    "gripper_control": "force",
    "max_grip_force": 3.0,
    "arm_stiffness": 0.1,
    "max_translation": 0.01,
    "max_yaw": 0.1,
    "servo_damping_ratio": 0.7,
    "force_penalty": 2.0,
    "failure_penalty": 50,
    "approach_lead_limit": 0.00025,
    "approach_lead_slope": 0.3,
    "approach_guard_fingers": True,
}
STEPS = 300
RESET_EVERY = 100
VIEW = {"objects": ["box", "mug", "cylinder"], "scales": [1.0, 1.2], "coverage_samples": 2048}
GRASP = {"instruments": ["scalpel", "tissue_forceps"]}
#: name: (env id, kwargs). Each backend, discrete actions, dynamic motion, privileged and
#: free-space observations, each grasp observation mode, and the shipped grasp policy's task.
CONFIGURATIONS = {
    "view-raycast": ("ViewPlanning-v0", {**VIEW, "depth_backend": "raycast"}),
    "view-gl": ("ViewPlanning-v0", {**VIEW, "depth_backend": "gl"}),
    "view-discrete": (
        "ViewPlanning-v0",
        {**VIEW, "depth_backend": "raycast", "action_mode": "discrete"},
    ),
    "view-dynamic": ("ViewPlanning-v0", {**VIEW, "depth_backend": "raycast", "motion": "dynamic"}),
    "view-privileged-free-space": (
        "ViewPlanning-v0",
        {**VIEW, "depth_backend": "raycast", "privileged": True, "observe_free_space": True},
    ),
    "grasp-state": ("InstrumentGrasp-v0", {**GRASP, "obs_mode": "state"}),
    "grasp-depth": ("InstrumentGrasp-v0", {**GRASP, "obs_mode": "depth"}),
    "grasp-rgbd": ("InstrumentGrasp-v0", {**GRASP, "obs_mode": "rgbd"}),
    "grasp-shipped-task": ("InstrumentGrasp-v0", {**GRASP, **SHIPPED_GRASP_TASK}),
}


def canonical(value) -> bytes:
    """Bytes that tell values apart by type, shape and content, the same in every process."""
    if isinstance(value, dict):
        return (
            b"{"
            + b"".join(
                canonical(str(key)) + b":" + canonical(value[key]) for key in sorted(value, key=str)
            )
            + b"}"
        )
    if isinstance(value, (list, tuple)):
        return b"[" + b",".join(canonical(item) for item in value) + b"]"
    if isinstance(value, str):
        return b"s" + value.encode()
    if value is None:
        return b"None"
    array = np.asarray(value)
    if array.dtype == object:
        return b"r" + repr(value).encode()
    if array.dtype.kind in "fc":
        array = array.astype(np.float64 if array.dtype.kind == "f" else np.complex128)
    return f"a{array.dtype.str}{array.shape}".encode() + np.ascontiguousarray(array).tobytes()


def digest_of(env_id: str, kwargs: dict, steps: int = STEPS) -> dict:
    env = gym.make(env_id, **kwargs).unwrapped
    env.action_space.seed(0)
    total, episode = hashlib.sha256(), hashlib.sha256()
    episodes, seed, since_reset = [], 0, 0
    try:
        obs, info = env.reset(seed=seed)
        episode.update(canonical(obs) + canonical(info))
        for _ in range(steps):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            episode.update(canonical([obs, float(reward), terminated, truncated, info]))
            since_reset += 1
            if terminated or truncated or since_reset == RESET_EVERY:
                episodes.append(episode.hexdigest())
                total.update(episode.digest())
                seed, since_reset, episode = seed + 1, 0, hashlib.sha256()
                obs, info = env.reset(seed=seed)
                episode.update(canonical(obs) + canonical(info))
    finally:
        env.close()
    episodes.append(episode.hexdigest())
    total.update(episode.digest())
    return {"digest": total.hexdigest(), "episodes": episodes}


def machine() -> dict:
    cpu = (
        next(
            (
                line.split(":", 1)[1].strip()
                for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")
            ),
            platform.processor(),
        )
        if Path("/proc/cpuinfo").exists()
        else platform.processor()
    )
    import mujoco

    return {"cpu": cpu, "python": platform.python_version(), "mujoco": mujoco.__version__,
            "numpy": np.__version__}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="write the digests to this JSON file")
    parser.add_argument("--compare", type=Path, help="compare with the digests in this file")
    parser.add_argument("--only", nargs="+", choices=sorted(CONFIGURATIONS), help="configurations")
    args = parser.parse_args(argv)
    names = args.only or list(CONFIGURATIONS)
    results = {}
    for name in names:
        env_id, kwargs = CONFIGURATIONS[name]
        results[name] = {"env_id": env_id, "kwargs": kwargs, **digest_of(env_id, kwargs)}
        print(f"{name}: {results[name]['digest']}", flush=True)
    document = {"steps": STEPS, "reset_every": RESET_EVERY, "machine": machine(), "runs": results}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(document, indent=1) + "\n")
    if not args.compare:
        return 0
    reference = json.loads(args.compare.read_text())
    differing = 0
    for name, result in results.items():
        before = reference["runs"].get(name)
        if before is None:
            print(f"{name}: not in {args.compare}")
            continue
        if before["digest"] == result["digest"]:
            print(f"{name}: same")
            continue
        differing += 1
        first = next(
            (
                i
                for i, (a, b) in enumerate(
                    zip(before["episodes"], result["episodes"], strict=False)
                )
                if a != b
            ),
            min(len(before["episodes"]), len(result["episodes"])),
        )
        print(f"{name}: DIFFERENT from episode {first} on")
    if reference.get("machine") != document["machine"]:
        print(f"note: recorded on {reference.get('machine')}, run on {document['machine']}")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
