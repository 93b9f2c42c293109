"""Each compiled kernel reads only what its own file defines, so that its disk cache is never
stale: numba keys a cached function on the file that defines it, and freezes what the function
reads from module globals (constants, other jitted functions) into the cached machine code.
A kernel that called another module's jitted function, or read a constant computed from
another module, would keep the old code or value after that module changed."""

from __future__ import annotations

import ast
import dis
import importlib
import inspect
import pkgutil
import types

import pytest

numba = pytest.importorskip("numba")

import liuxing_envs.kernels  # noqa: E402

KERNEL_MODULES = sorted(
    info.name
    for info in pkgutil.iter_modules(liuxing_envs.kernels.__path__, "liuxing_envs.kernels.")
    if not info.name.endswith("__main__")
)


def _project_names(tree: ast.Module) -> set[str]:
    """Module-level names bound to another project module or to something from one, and the
    module-level names computed from those (transitively)."""
    foreign: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("liuxing_envs"):
            foreign |= {alias.asname or alias.name for alias in node.names}
        elif isinstance(node, ast.Import):
            foreign |= {
                (alias.asname or alias.name).split(".")[0]
                for alias in node.names
                if alias.name.startswith("liuxing_envs")
            }
    changed = True
    while changed:
        changed = False
        for node in tree.body:
            if not isinstance(node, (ast.Assign, ast.AnnAssign)) or node.value is None:
                continue
            used = {n.id for n in ast.walk(node.value) if isinstance(n, ast.Name)}
            if not used & foreign:
                continue
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                for name in ast.walk(target):
                    if isinstance(name, ast.Name) and name.id not in foreign:
                        foreign.add(name.id)
                        changed = True
    return foreign


def _globals_read(code: types.CodeType) -> set[str]:
    names = {i.argval for i in dis.get_instructions(code) if i.opname == "LOAD_GLOBAL"}
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _globals_read(constant)
    return names


def foreign_reads(module: types.ModuleType) -> list[str]:
    """What the module's jitted functions read that another module defines or decides."""
    project_names = _project_names(ast.parse(inspect.getsource(module)))
    found = []
    for name, value in vars(module).items():
        if not isinstance(value, numba.core.dispatcher.Dispatcher):
            continue
        if value.py_func.__module__ != module.__name__:
            continue  # imported, not defined here: checked in its own module
        for read in sorted(_globals_read(value.py_func.__code__)):
            target = value.py_func.__globals__.get(read)
            other_kernel = (
                isinstance(target, numba.core.dispatcher.Dispatcher)
                and target.py_func.__module__ != module.__name__
            )
            if read in project_names or other_kernel:
                found.append(f"{module.__name__}.{name} reads {read}")
    return sorted(found)


@pytest.mark.parametrize("module_name", KERNEL_MODULES)
def test_each_kernel_reads_only_what_its_own_file_defines(module_name):
    module = importlib.import_module(module_name)
    jitted = [v for v in vars(module).values() if isinstance(v, numba.core.dispatcher.Dispatcher)]
    assert jitted, f"{module_name} defines no jitted function"
    assert foreign_reads(module) == []


def test_the_check_finds_a_kernel_that_calls_another_modules_kernel_or_reads_its_constant(
    tmp_path, monkeypatch
):
    source = """
import numba
from liuxing_envs.kernels import frustum
from liuxing_envs.kernels.fusion import back_project
from liuxing_envs.sim import ur_ik

SHOULDER = ur_ik._SHOULDER_HEIGHT
OWN = 2.0

@numba.njit
def calls_another_module(x):
    return back_project(x, x, x)

@numba.njit
def reads_a_constant_from_another_module(x):
    return x * SHOULDER + OWN

@numba.njit
def reaches_into_another_module(x):
    return frustum.may_reach(x)

@numba.njit
def self_contained(x):
    return x * OWN
"""
    (tmp_path / "kernel_probe.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("kernel_probe")
    assert foreign_reads(module) == [
        "kernel_probe.calls_another_module reads back_project",
        "kernel_probe.reaches_into_another_module reads frustum",
        "kernel_probe.reads_a_constant_from_another_module reads SHOULDER",
    ]
