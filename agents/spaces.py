"""Comparing and describing Gymnasium spaces: does a saved policy fit an environment?"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from gymnasium import spaces

#: What a saved SB3 model records of the env it was trained in.
MODEL_SPACES = ("observation_space", "action_space")


def same_space(expected: spaces.Space, actual: spaces.Space) -> bool:
    """Same keys, shapes and dtypes (bounds may differ: a policy only sees the arrays)."""
    if isinstance(expected, spaces.Dict) and isinstance(actual, spaces.Dict):
        return set(expected.spaces) == set(actual.spaces) and all(
            same_space(expected[key], actual[key]) for key in expected.spaces
        )
    if isinstance(expected, spaces.Box) and isinstance(actual, spaces.Box):
        return expected.shape == actual.shape and expected.dtype == actual.dtype
    return expected == actual


def describe_space(space: spaces.Space) -> str:
    """A short description for error messages: keys, shapes and dtypes, no bounds."""
    if isinstance(space, spaces.Dict):
        return "{" + ", ".join(f"{k}: {describe_space(v)}" for k, v in space.spaces.items()) + "}"
    if isinstance(space, spaces.Box):
        return f"Box{space.shape} {space.dtype}"
    return repr(space)


def mismatched_spaces(env, saved: Mapping) -> Iterator[tuple[str, spaces.Space, object]]:
    """``(name, env's space, saved space)`` for each of :data:`MODEL_SPACES` where ``env``'s
    differs from ``saved`` (a saved model's data, which may lack one: None)."""
    for name in MODEL_SPACES:
        if not same_space(getattr(env, name), saved.get(name)):
            yield name, getattr(env, name), saved.get(name)
