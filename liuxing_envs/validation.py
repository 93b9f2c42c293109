"""Checks shared by the environments and the perception functions: keyword arguments (each
failure names the argument, the value it got and what is allowed), actions and reset options,
and the context added to an error raised in an env's ``step``."""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Iterable, Mapping, Set

import numpy as np


def require_choice(name: str, value, allowed) -> None:
    # An array compares element by element: one element would pass as that element (and be
    # kept as an array), more would raise numpy's ambiguous-truth error, which names nothing.
    # A switch takes a bool, not what equals one (1, 1.0, 1+0j, numpy's True_): each would be
    # recorded in a run's config as given, and numpy's does not even write to YAML.
    if (
        isinstance(value, np.ndarray)
        or value not in allowed
        or (
            not isinstance(value, bool)
            and any(isinstance(choice, bool) and choice == value for choice in allowed)
        )
    ):
        raise ValueError(f"{name}={value!r} is not allowed; choose one of {list(allowed)}")


def require_int(name: str, value, low: int, high: int) -> None:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not low <= value <= high
    ):
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


def require_number(name: str, value, low: float, high: float) -> None:
    if not is_number(value) or not (math.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} must be a number in [{low}, {high}], got {value!r}")


def require_range(name: str, value, low: float, high: float) -> tuple[float, float]:
    message = f"{name} must be a pair of numbers (min, max), got {value!r}"
    # Each would unpack: "09" as the pair (0, 9), a dict as its keys, a set in any order.
    if isinstance(value, str | bytes | Mapping | Set):
        raise ValueError(message)
    try:
        first, second = value
    except (TypeError, ValueError):
        raise ValueError(message) from None
    if not (is_number(first) and is_number(second)):
        raise ValueError(message)
    first, second = float(first), float(second)
    if not (low <= first <= second <= high):
        raise ValueError(f"{name} must satisfy {low} <= min <= max <= {high}, got {value!r}")
    return first, second


def require_numbers(name: str, value, low: float, high: float) -> tuple[float, ...]:
    """A non-empty sequence of finite numbers in [low, high], as floats."""
    message = f"{name} must be a non-empty list of numbers in [{low}, {high}], got {value!r}"
    try:
        # A string, a dict (its keys) or a set (in any order) is no list of numbers.
        items = list(value) if not isinstance(value, str | bytes | Mapping | Set) else []
    except TypeError:
        raise ValueError(message) from None
    if not items or not all(is_number(v) for v in items):
        raise ValueError(message)
    numbers = tuple(float(v) for v in items)
    if not all(math.isfinite(v) and low <= v <= high for v in numbers):
        raise ValueError(message)
    return numbers


def is_number(value) -> bool:
    """A real number, not a bool (np.number would take complex ones too)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def checked_reset_options(options, checks: Mapping[str, Callable]) -> dict:
    """``reset(options=...)`` checked before the env changes anything: unknown keys and bad
    values raise ValueError naming them. ``checks`` maps each allowed key to a function
    ``(key, value) -> value`` that raises on a bad value."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ValueError(f"reset options must be a dict, got {options!r}")
    unknown = sorted(set(options) - set(checks), key=str)
    if unknown:
        raise ValueError(f"unknown reset option(s) {unknown}; allowed: {', '.join(checks)}")
    return {key: checks[key](key, value) for key, value in options.items()}


def option_in(allowed) -> Callable:
    """A check that returns the allowed choice equal to the value: numpy compares a float32
    with a Python float in float32, so ``np.float32(0.9)`` matches 0.9 and becomes 0.9. A bool
    matches only a bool (True equals 1 and 1.0)."""

    def check(key, value):
        if not isinstance(value, np.ndarray):
            flag = isinstance(value, bool | np.bool_)
            for choice in allowed:
                if flag == isinstance(choice, bool) and value == choice:
                    return choice
        raise ValueError(f"reset option {key}={value!r} is not one of {tuple(allowed)}")

    return check


def finite_vector(value, size: int) -> np.ndarray | None:
    """``value`` as ``size`` finite floats, or None if it is not that."""
    try:
        vector = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None
    return vector if vector.shape == (size,) and np.isfinite(vector).all() else None


def option_xy(key, value) -> np.ndarray:
    xy = finite_vector(value, 2)
    if xy is None:
        raise ValueError(f"reset option {key} must be two finite numbers (x, y), got {value!r}")
    return xy


def option_angle(key, value) -> float:
    if not is_number(value) or not math.isfinite(value):
        raise ValueError(f"reset option {key} must be a finite angle (rad), got {value!r}")
    return float(value)


def as_action(action, shape: tuple[int, ...]) -> np.ndarray:
    """A continuous action as float64, or ValueError naming what is wrong with it."""
    if type(action) is np.ndarray and action.dtype.kind == "f":  # a policy's: the usual
        array = action.astype(np.float64, copy=False)
    else:
        array = _real_array(action, shape)
    if array.shape != shape:
        raise ValueError(f"action must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"action must be finite, got {array.tolist()}")
    return array


def _real_array(action, shape: tuple[int, ...]) -> np.ndarray:
    """``action`` as a float64 array if it holds real numbers only, or ValueError."""
    array = None
    try:
        # numpy would read strings ("0.5") as numbers and drop complex numbers' imaginary part.
        if _real_numbers(np.asarray(action)):
            array = np.asarray(action, dtype=np.float64)
    except (TypeError, ValueError):
        pass
    if array is None:
        raise ValueError(f"action must be {shape} real numbers, got {action!r}")
    return array


def _real_numbers(array: np.ndarray) -> bool:
    if array.dtype.kind == "O":  # a list mixing types: each element as it is
        return all(is_number(v) or isinstance(v, bool | np.bool_) for v in array.flat)
    return array.dtype.kind in "biuf"


def as_index(action, n: int) -> int:
    """A discrete action as an int in [0, n), or ValueError. Integral floats pass (some
    vectorised code hands them over); strings, booleans and arrays do not."""
    message = f"discrete action must be an integer in [0, {n - 1}], got {action!r}"
    if isinstance(action, str | bytes | bool | np.bool_) or np.ndim(action) != 0:
        raise ValueError(message)
    try:
        value = float(action)
    except (TypeError, ValueError):
        raise ValueError(message) from None
    if not (math.isfinite(value) and value.is_integer() and 0 <= value < n):
        raise ValueError(message)
    return int(value)


def closest(name, allowed: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest allowed name, or ``""`` if none is close."""
    if not isinstance(name, str):  # a YAML key or value of another kind: 5, [1]
        return ""
    match = difflib.get_close_matches(name, list(allowed), n=1, cutoff=0.5)
    return f" (did you mean {match[0]!r}?)" if match else ""


def refuse_if_closed(env) -> None:
    """RuntimeError for a step of an env whose close() has run since its last reset(): a
    closed env that went on stepping (its renderers made anew) hid a use-after-close bug."""
    if env.closed:
        env_id = env.spec.id if env.spec is not None else type(env).__name__
        raise RuntimeError(f"{env_id}: step() after close(); reset() it first, or make a new env")


def note_step_error(env, error: Exception, step: int, seed: int | None) -> None:
    """Add to ``error``, raised inside ``env.step()``, which env, which step of the episode,
    and the reset seed that replays it. Python prints notes with the traceback, also from a
    vector env's worker process, where the env would otherwise be anonymous."""
    env_id = env.spec.id if env.spec is not None else type(env).__name__
    error.add_note(f"in {env_id}, step {step} of the episode reset with seed={seed}")
