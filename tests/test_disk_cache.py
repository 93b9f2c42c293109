"""The disk cache of precomputed ground truth: bit-for-bit results, misses on any change,
damaged entries never used but replaced, and a cache that is off or unwritable costing only
time."""

import os
import warnings

import numpy as np
import pytest

from liuxing_envs import disk_cache
from liuxing_envs.sim import objects
from liuxing_envs.sim.objects import observable_samples


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache folder, a cold in-memory cache, and a count of the ray casts."""
    folder = tmp_path / "cache"
    monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, str(folder))
    objects.clear_memory_caches()
    casts = []
    real = objects.observable_mask

    def counted(*args, **kwargs):
        casts.append(args[0].name)
        return real(*args, **kwargs)

    monkeypatch.setattr(objects, "observable_mask", counted)
    yield folder, casts
    objects.clear_memory_caches()


def entries(folder):
    return sorted(folder.glob("observable-*.entry"))


def stored_array(entry):
    return disk_cache.decode_entry(entry.read_bytes())


def cold(*args, **kwargs):
    """observable_samples as a new process would compute it: nothing in memory."""
    objects.clear_memory_caches()
    return observable_samples(*args, **kwargs)


def test_a_new_process_reads_the_stored_result_bit_for_bit(cache):
    folder, casts = cache
    first = cold("mug", 1.0, 1024)
    assert casts == ["mug"] and len(entries(folder)) == 1
    again = cold("mug", 1.0, 1024)
    assert casts == ["mug"]  # read, not cast again
    np.testing.assert_array_equal(again.observable, first.observable)
    np.testing.assert_array_equal(again.points, first.points)
    assert again.observable.dtype == bool and not again.observable.flags.writeable
    assert 0.3 < again.observable.mean() < 1.0  # a real mask, not all or nothing


def test_any_change_of_what_it_is_computed_from_misses(cache):
    folder, casts = cache
    variants = [
        ("mug", 1.0, 1024, {}),
        ("mug", 1.2, 1024, {}),  # scale
        ("mug", 1.0, 2048, {}),  # sample count
        ("mug", 1.0, 1024, {"seed": 1}),
        ("mug", 1.0, 1024, {"radii": (0.32, 0.45)}),  # the views around it
        ("mug", 1.0, 1024, {"elevations_deg": (30.0, 90.0)}),
        ("mug", 1.0, 1024, {"table": False}),
        ("bowl", 1.0, 1024, {}),  # another mesh
    ]
    cast = [cold(name, scale, count, **kw).observable for name, scale, count, kw in variants]
    assert len(casts) == len(variants) and len(entries(folder)) == len(variants)
    read = [cold(name, scale, count, **kw).observable for name, scale, count, kw in variants]
    assert len(casts) == len(variants)  # every one read back, none cast again
    for first, again in zip(cast, read, strict=True):  # and no entry read for another's
        np.testing.assert_array_equal(first, again)
    assert not np.array_equal(cast[0], cast[3]) and not np.array_equal(cast[0], cast[7])


def flipped(data: bytes, start: int, stop: int | None = None) -> bytes:
    """``data`` with every bit of ``data[start:stop]`` inverted."""
    middle = bytes(255 - byte for byte in data[start:stop])
    return data[:start] + middle + (data[stop:] if stop is not None else b"")


def npy_body(entry_bytes: bytes) -> int:
    """Where an entry's array data starts: after the cache header and the .npy header, so
    damage there leaves every header intact."""
    payload = len(disk_cache.ENTRY_MAGIC) + 32
    return payload + entry_bytes[payload:].index(b"\n") + 1


def test_a_damaged_entry_is_never_used_but_computed_again_replaced_and_named(cache):
    """Only shape and dtype were checked: an entry whose array bytes were inverted, or
    overwritten with 7s, with its headers intact, was used as it was (other coverages, no
    warning), and a zeroed one made every env fail with "no sample is observable"."""
    folder, casts = cache
    first = cold("mug", 1.0, 1024)
    (entry,) = entries(folder)
    stored = entry.read_bytes()
    body, magic = npy_body(stored), len(disk_cache.ENTRY_MAGIC)
    damages = {
        "array bits inverted": flipped(stored, body),
        "array overwritten with 7s": stored[:body] + b"\x07" * (len(stored) - body),
        "array zeroed": stored[:body] + bytes(len(stored) - body),
        "one byte of the checksum": flipped(stored, magic, magic + 1),
        "not an entry": b"not an array",
        "cut short": stored[: len(stored) // 2],
        "an entry of another shape": disk_cache.encode_entry(np.zeros(3, dtype=bool)),
        "an entry of another dtype": disk_cache.encode_entry(np.zeros(1024, dtype=np.uint8)),
    }
    for what, damage in damages.items():
        entry.write_bytes(damage)
        casts.clear()
        with pytest.warns(RuntimeWarning, match="damaged cache entry") as warned:
            again = cold("mug", 1.0, 1024)
        assert len(warned) == 1 and str(entry) in str(warned[0].message), what
        assert casts == ["mug"], what
        np.testing.assert_array_equal(again.observable, first.observable, err_msg=what)
        assert entry.read_bytes() == stored, what  # replaced with the true entry
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            cold("mug", 1.0, 1024)  # read back: no warning, no cast
        assert casts == ["mug"], what


def test_a_damaged_entry_never_changes_what_an_env_measures(cache):
    """Through gym.make: the coverages of seeded episodes with a damaged cache are those of
    a fresh one."""
    import gymnasium as gym

    import liuxing_envs  # noqa: F401

    folder, _ = cache
    kwargs = {"objects": ["mug"], "scales": (1.0,), "coverage_samples": 1024}

    def coverages():
        objects.clear_memory_caches()
        env = gym.make("ViewPlanning-v1", **kwargs)
        try:
            return [env.reset(seed=seed)[1]["coverage"] for seed in range(3)]
        finally:
            env.close()

    fresh = coverages()
    (entry,) = entries(folder)
    stored = entry.read_bytes()
    entry.write_bytes(flipped(stored, npy_body(stored)))
    with pytest.warns(RuntimeWarning, match="damaged cache entry"):
        assert coverages() == fresh
    assert entry.read_bytes() == stored


@pytest.mark.parametrize("umask", [0o002, 0o022, 0o077])
def test_entries_are_created_with_the_users_umask(cache, umask):
    """Entries were written with mode 0600 whatever the umask: a cache folder shared by a
    group was unreadable to the others."""
    folder, _ = cache
    previous = os.umask(umask)
    try:
        cold("mug", 1.0, 1024)
    finally:
        os.umask(previous)
    (entry,) = entries(folder)
    assert entry.stat().st_mode & 0o777 == 0o666 & ~umask


def test_the_cache_can_be_turned_off(cache, monkeypatch):
    folder, casts = cache
    monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, "off")
    first = cold("mug", 1.0, 1024)
    second = cold("mug", 1.0, 1024)
    assert casts == ["mug", "mug"] and not folder.exists()
    np.testing.assert_array_equal(first.observable, second.observable)


def test_an_unwritable_folder_warns_once_and_costs_only_time(cache, monkeypatch, tmp_path):
    folder, casts = cache
    blocker = tmp_path / "a_file"
    blocker.write_text("a file where the cache folder's parent should be")
    monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, str(blocker / "cache"))
    monkeypatch.setattr(disk_cache, "_warned_unwritable", False)
    with pytest.warns(RuntimeWarning, match="cannot write the cache folder"):
        first = cold("mug", 1.0, 1024)
    with warnings.catch_warnings(record=True) as later:
        warnings.simplefilter("always")
        cold("bowl", 1.0, 1024)
    assert not later  # once per process
    assert casts == ["mug", "bowl"]
    monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, str(folder))
    np.testing.assert_array_equal(cold("mug", 1.0, 1024).observable, first.observable)


def test_cache_keys_tell_arrays_apart_by_dtype_and_shape():
    data = np.arange(6, dtype=np.int32)
    keys = {
        disk_cache.cache_key(data),
        disk_cache.cache_key(data.reshape(2, 3)),
        disk_cache.cache_key(data.view(np.float32)),
        disk_cache.cache_key(data, True),
        disk_cache.cache_key(data, 1),
    }
    assert len(keys) == 5
    assert disk_cache.cache_key(data.copy()) == disk_cache.cache_key(data)


def test_the_cache_lives_in_the_user_cache_folder_unless_told(monkeypatch, tmp_path):
    monkeypatch.delenv(disk_cache.CACHE_ENV_VAR)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert disk_cache.cache_dir() == tmp_path / "liuxing_envs"
    monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, str(tmp_path / "elsewhere"))
    assert disk_cache.cache_dir() == tmp_path / "elsewhere"
    for off in ("off", "OFF", "0", ""):
        monkeypatch.setenv(disk_cache.CACHE_ENV_VAR, off)
        assert disk_cache.cache_dir() is None
