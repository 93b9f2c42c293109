"""Assertions that two computations gave the same numbers bit for bit (a kernel and the code
it replaces), through nested infos."""

import numpy as np


def assert_same_bits(got, expected):
    got, expected = np.asarray(got), np.asarray(expected)
    assert got.shape == expected.shape and got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)
    assert got.tobytes() == expected.tobytes()  # the signs of zeros too


def assert_same_values(got, expected, where="info"):
    if isinstance(expected, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(expected), where
        for key in expected:
            assert_same_values(got[key], expected[key], f"{where}[{key!r}]")
    elif isinstance(expected, (list, tuple)):
        assert type(got) is type(expected) and len(got) == len(expected), where
        for index, (a, b) in enumerate(zip(got, expected, strict=True)):
            assert_same_values(a, b, f"{where}[{index}]")
    elif isinstance(expected, (np.ndarray, np.generic, float, int, bool)):
        assert type(got) is type(expected), where
        assert_same_bits(got, expected)
    else:
        assert got == expected, where
