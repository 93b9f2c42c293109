"""Expert demonstrations in an off-policy learner's replay buffer (SAC from demonstrations).

InstrumentGrasp's reward is dense only up to the handle: a grasp pays nothing until both
pads press on it, and a random policy of 5 continuous dimensions essentially never turns the
jaws across a 10 mm handle, lowers them to within millimetres of the tray and closes them
below 5 N. Without demonstrations SAC learned to hover at the handle (docs/design/training.md).

Before the first update a new run's replay buffer is filled with episodes of a scripted
expert, with Gaussian noise on its actions so that the buffer also holds near-misses and what
follows them. The noise's standard deviation sweeps from 0 (first episode) to
``action_noise`` (last) on the arm's dimensions, and to ``gripper_noise`` on the gripper's: a
grasp is a millimetre-precise contact task. With gripper noise 0 the privileged expert
succeeded in 18/20 episodes with an arm std of 0.02 (0.4 mm per step), 10/20 with 0.05 and
5/20 with 0.1; an equal std on the gripper (0.05 = 2 mm of opening) left 7 successes in 100
episodes of a 0-0.1 sweep. A single noise level would give either few failures or few
successes. They are ordinary transitions of the training env (same kwargs, same reward),
stored raw like every other transition, and the observation normaliser's statistics start
from them. They are ordinary rows of SAC's ring buffer (and of its checkpoints): once the run
has added ``buffer_size`` rows less theirs, its own transitions overwrite them, oldest first
(with ``sac.yml``'s 300k rows and about 10k demonstration transitions, from about step 290k
on), and a configuration whose demonstrations alone would fill the buffer is refused. SAC
itself is unchanged: its actor and critic learn from uniform samples of the buffer.

Configured by the ``demonstrations`` harness key of a hyper-parameter entry::

    demonstrations:
      expert: privileged-grasp   # one of the task's experts (agents.evaluation.TASKS)
      episodes: 50               # seeded: seed + DEMONSTRATION_SEED_OFFSET + i
      action_noise: 0.1          # largest std of the noise on each arm dimension
      gripper_noise: 0.005       # largest std of the noise on the gripper dimension
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import torch
from stable_baselines3.common.logger import Logger

from agents.config import ConfigError, int_at_least, number_in, require_known
from agents.evaluation import TASKS, make_env, task_for

DEFAULTS = {"episodes": 50, "action_noise": 0.1, "gripper_noise": 0.005, "pretrain_steps": 0}
PRETRAIN_BATCH_SIZE = 256
#: Demonstration episodes use their own seeds, apart from training and evaluation.
DEMONSTRATION_SEED_OFFSET = 20_000
MAX_ACTION_NOISE = 2.0


class Transition(NamedTuple):
    """One expert step: what SB3's replay buffer stores, and the action the expert meant
    before its noise was added (the behaviour-cloning label)."""

    observation: dict
    next_observation: dict
    action: np.ndarray
    reward: float
    done: bool
    info: dict
    intended: np.ndarray


def check_demonstrations(env_id: str, algo: str, spec) -> dict | None:
    """The ``demonstrations`` entry with defaults filled in, or None; raises ConfigError
    naming what is wrong and what is allowed."""
    if spec is None:
        return None
    if not isinstance(spec, Mapping):
        raise ConfigError(
            f"demonstrations must be a mapping with keys expert, {', '.join(DEFAULTS)}; "
            f"got {spec!r}"
        )
    if algo != "sac":
        raise ConfigError(f"demonstrations fill a replay buffer: use them with sac, not {algo}")
    experts = task_for(env_id).experts
    if not experts:
        with_experts = [name for name, task in TASKS.items() if task.experts]
        raise ConfigError(
            f"no expert for {env_id}; demonstrations exist for {', '.join(with_experts)} tasks"
        )
    for key in spec:
        require_known("demonstrations key", key, ("expert", *DEFAULTS))
    resolved = {**DEFAULTS, **spec}
    if "expert" not in spec:
        raise ConfigError(f"demonstrations need an expert, one of {', '.join(experts)}")
    require_known("expert", resolved["expert"], tuple(experts))
    int_at_least("demonstrations.episodes", resolved["episodes"])
    int_at_least("demonstrations.pretrain_steps", resolved["pretrain_steps"], minimum=0)
    for key in ("action_noise", "gripper_noise"):
        resolved[key] = number_in(f"demonstrations.{key}", resolved[key], 0.0, MAX_ACTION_NOISE)
    return resolved


#: A run shorter than its demonstrations gets one expert episode per this many training steps
#: (at least one) and at most as many behaviour-cloning steps as it trains, so that a quick
#: run is quick.
STEPS_PER_DEMONSTRATION = 1_000


def demonstration_sizes(config: dict) -> tuple[int, int]:
    """The expert episodes and behaviour-cloning steps a run takes: its ``demonstrations``
    entry's, cut for runs shorter than them (see STEPS_PER_DEMONSTRATION)."""
    spec, steps = config["demonstrations"], config["n_timesteps"]
    episodes = min(spec["episodes"], max(1, steps // STEPS_PER_DEMONSTRATION))
    return episodes, min(spec["pretrain_steps"], steps)


def seed_replay_buffer(model, config: dict) -> dict:
    """Adds ``config["demonstrations"]`` episodes of the expert to ``model.replay_buffer``
    and to its normaliser's statistics; returns what was added."""
    buffer, normalizer = model.replay_buffer, model.get_vec_normalize_env()
    if buffer.optimize_memory_usage:
        raise ConfigError(
            "demonstrations need optimize_memory_usage: false (that buffer reads each next "
            "observation from the following row)"
        )
    episodes, pretrain_steps = demonstration_sizes(config)
    transitions, successes = record_demonstrations(config, episodes)
    # A buffer row holds one transition per training env; rows are sampled as independent
    # transitions (each stores its own next observation), so demonstrations fill them in
    # order, and a remainder short of a whole row is left out.
    width = buffer.n_envs
    if len(transitions) // width > buffer.buffer_size:
        raise ConfigError(
            f"demonstrations: {episodes} episodes gave "
            f"{len(transitions)} transitions, {len(transitions) // width} buffer rows at "
            f"n_envs={width}, more than buffer_size={buffer.buffer_size}: the ring buffer "
            "would overwrite its own demonstrations before the first update; give fewer "
            "episodes or a larger buffer_size"
        )
    for start in range(0, len(transitions) - width + 1, width):
        row = Transition(*zip(*transitions[start : start + width], strict=True))
        buffer.add(
            _stacked(row.observation),
            _stacked(row.next_observation),
            np.array(row.action),
            np.array(row.reward),
            np.array(row.done),
            list(row.info),
        )
    added = len(transitions) // width * width
    if normalizer is not None:
        for key, statistics in normalizer.obs_rms.items():
            statistics.update(np.array([t.observation[key] for t in transitions[:added]]))
    if pretrain_steps:
        pretrain(model, transitions, pretrain_steps, seed=config["seed"])
    return {
        "expert": config["demonstrations"]["expert"],
        "episodes": episodes,
        "pretrain_steps": pretrain_steps,
        "transitions": added,
        "successes": successes,
    }


def record_demonstrations(config: dict, episodes: int) -> tuple[list[Transition], int]:
    """``episodes`` of the expert in the training env, step by step, and how many
    succeeded."""
    spec = config["demonstrations"]
    env = make_env(config["env_id"], config["env_kwargs"])
    expert = task_for(config["env_id"]).baselines[spec["expert"]](env)
    action_size = env.action_space.shape[0]  # the gripper is the last dimension
    largest = np.array([spec["action_noise"]] * (action_size - 1) + [spec["gripper_noise"]])
    sweep = np.linspace(0.0, 1.0, episodes)[:, None] * largest
    first_seed = config["seed"] + DEMONSTRATION_SEED_OFFSET
    rng = np.random.default_rng(first_seed)
    transitions, successes = [], 0
    try:
        for episode, noise_std in enumerate(sweep):
            observation, _ = env.reset(seed=first_seed + episode)
            expert.reset()
            done, info = False, {}
            while not done:
                intended, _ = expert.predict(observation)
                noise = rng.normal(0.0, 1.0, size=intended.shape) * noise_std
                action = np.clip(intended + noise, -1.0, 1.0).astype(np.float32)
                following, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                timeout = {"TimeLimit.truncated": truncated and not terminated}
                transitions.append(
                    Transition(observation, following, action, reward, done, timeout, intended)
                )
                observation = following
            successes += bool(info.get("is_success", False))
    finally:
        env.close()
    return transitions, successes


def pretrain(model, transitions: list[Transition], steps: int, seed: int) -> None:
    """Behaviour cloning of the expert's intended actions (also in the states its noise led
    to, so the actor learns its corrections), interleaved with SAC's own updates on the
    buffer so the critic learns the demonstrations' values before the actor follows it.

    The loss is the squared error of the actor's deterministic action, the tanh of its mean.
    """
    normalizer = model.get_vec_normalize_env()
    observations = _stacked([t.observation for t in transitions])
    if normalizer is not None:
        observations = normalizer.normalize_obs(observations)
    observations = {
        key: torch.as_tensor(value, device=model.device) for key, value in observations.items()
    }
    intended = torch.as_tensor(np.array([t.intended for t in transitions]), device=model.device)
    rng = np.random.default_rng(seed)
    # SAC.train logs through the logger learn() sets up; until then a silent one.
    model.set_logger(Logger(folder=None, output_formats=[]))
    for _ in range(steps):
        model.train(gradient_steps=1, batch_size=model.batch_size)
        batch = torch.as_tensor(rng.integers(len(intended), size=PRETRAIN_BATCH_SIZE))
        predicted = model.actor({key: value[batch] for key, value in observations.items()}, True)
        loss = torch.nn.functional.mse_loss(predicted, intended[batch])
        model.actor.optimizer.zero_grad()
        loss.backward()
        model.actor.optimizer.step()
    model._custom_logger = False  # learn() then sets up its own (TensorBoard) logger


def _stacked(observations) -> dict:
    return {key: np.stack([o[key] for o in observations]) for key in observations[0]}
