"""Each compiled kernel reads only what its own file defines, so that its disk cache is never
stale: numba keys a cached function on the file that defines it, and freezes what the function
reads from module globals (constants, other jitted functions) into the cached machine code.
A kernel that called another module's jitted function, or read a constant computed from
another module, would keep the old code or value after that module changed."""

from __future__ import annotations

import ast
import dis
import importlib
import importlib.util
import inspect
import pkgutil
import sys
import types

import pytest

numba = pytest.importorskip("numba")

from numba.core.ccallback import CFunc  # noqa: E402
from numba.np.ufunc.dufunc import DUFunc  # noqa: E402

import liuxing_envs.kernels  # noqa: E402

PROJECT = "liuxing_envs"
KERNEL_MODULES = sorted(
    info.name
    for info in pkgutil.iter_modules(liuxing_envs.kernels.__path__, "liuxing_envs.kernels.")
    if not info.name.endswith("__main__")
)


def _import_time_statements(tree: ast.Module):
    """The statements that run when the module is imported: its own and those inside its
    ``if``, ``try``, ``with`` and loop blocks (not those of function or class bodies)."""
    stack = list(tree.body)
    while stack:
        node = stack.pop()
        yield node
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.excepthandler):
                stack.extend(child.body)
            elif isinstance(child, ast.stmt):
                stack.append(child)


def _imported_module(node: ast.ImportFrom, package: str) -> str:
    if node.level:
        return importlib.util.resolve_name("." * node.level + (node.module or ""), package)
    return node.module or ""


def _names_in(node: ast.AST) -> set[str]:
    return {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}


def _project_names(module: types.ModuleType) -> set[str]:
    """Module-level names bound to another project module or to something from one, and the
    names whose values are computed from those, or by functions that read them."""
    tree = ast.parse(inspect.getsource(module))
    statements = list(_import_time_statements(tree))
    foreign: set[str] = set()
    for node in statements:
        if isinstance(node, ast.ImportFrom):
            imported = _imported_module(node, module.__package__)
            if imported.startswith(PROJECT) and imported != module.__name__:
                foreign |= {alias.asname or alias.name for alias in node.names}
        elif isinstance(node, ast.Import):
            foreign |= {
                alias.asname or alias.name.split(".")[0]
                for alias in node.names
                if alias.name.startswith(PROJECT)
            }
    changed = True
    while changed:
        changed = False
        for node in statements:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                # Its body's reads (its decorators run once, at import, on this module's
                # side: ``jit_options()`` decides no value the function computes).
                bound = [node.name]
                read = set().union(*(_names_in(statement) for statement in node.body))
            elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)) and node.value:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                bound = [n for target in targets for n in _names_in(target)]
                read = _names_in(node.value)
            else:
                continue
            if read & foreign and not set(bound) <= foreign:
                foreign |= set(bound)
                changed = True
    return foreign


def _globals_read(code: types.CodeType) -> set[str]:
    names = {i.argval for i in dis.get_instructions(code) if i.opname == "LOAD_GLOBAL"}
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _globals_read(constant)
    return names


def _from_elsewhere(value, module: types.ModuleType) -> bool:
    """A project module other than ``module``, or a jitted function defined in one."""
    if isinstance(value, types.ModuleType):
        return value.__name__.startswith(PROJECT) and value is not module
    if isinstance(value, numba.core.dispatcher.Dispatcher):
        return value.py_func.__module__ != module.__name__
    return False


def foreign_reads(module: types.ModuleType) -> list[str]:
    """What the module's jitted functions read that another module defines or decides."""
    project_names = _project_names(module)
    found = []
    for name, value in vars(module).items():
        if not isinstance(value, numba.core.dispatcher.Dispatcher):
            continue
        function = value.py_func
        if function.__module__ != module.__name__:
            continue  # imported, not defined here: checked in its own module
        for read in _globals_read(function.__code__):
            if read in project_names or _from_elsewhere(function.__globals__.get(read), module):
                found.append(f"{module.__name__}.{name} reads {read}")
        cells = zip(function.__code__.co_freevars, function.__closure__ or (), strict=True)
        for free, cell in cells:
            if _from_elsewhere(cell.cell_contents, module):
                found.append(f"{module.__name__}.{name} reads {free}")
    return sorted(found)


@pytest.mark.parametrize("module_name", KERNEL_MODULES)
def test_each_kernel_reads_only_what_its_own_file_defines(module_name):
    module = importlib.import_module(module_name)
    jitted = [v for v in vars(module).values() if isinstance(v, numba.core.dispatcher.Dispatcher)]
    assert jitted, f"{module_name} defines no jitted function"
    # The check reads @njit functions; other compiled kinds would pass it unexamined.
    others = (CFunc, DUFunc)
    assert not [name for name, v in vars(module).items() if isinstance(v, others)]
    assert foreign_reads(module) == []


PROBE = """
import numba
from liuxing_envs.kernels import frustum
from liuxing_envs.kernels.fusion import back_project
from liuxing_envs.sim import ur_ik
from . import coverage
from .depth import ray_quad
try:
    from .fusion import depth_bytes
except ImportError:
    depth_bytes = None

SHOULDER = ur_ik._SHOULDER_HEIGHT
OWN = 2.0
SCALED = 1.0
SCALED *= ur_ik._A2F


def _table():
    return ur_ik._A3F * OWN


TABLE = _table()


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
def calls_by_a_relative_import(x):
    return ray_quad(x, x, x) + coverage.cover(x) + depth_bytes(x)


@numba.njit
def reads_computed_constants(x):
    return x * SCALED + TABLE


def _factory(module):
    @numba.njit
    def reads_a_captured_module(x):
        return module.may_reach(x)

    return reads_a_captured_module


captured = _factory(frustum)


@numba.njit
def self_contained(x):
    return x * OWN
"""


def test_the_check_finds_every_way_a_kernel_reads_another_module(tmp_path, monkeypatch):
    path = tmp_path / "kernel_probe.py"
    path.write_text(PROBE)
    name = "liuxing_envs.kernels.kernel_probe"  # so that its relative imports are the package's
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)
    spec.loader.exec_module(module)
    prefix = name + "."
    assert [entry.removeprefix(prefix) for entry in foreign_reads(module)] == [
        "calls_another_module reads back_project",
        "calls_by_a_relative_import reads coverage",
        "calls_by_a_relative_import reads depth_bytes",
        "calls_by_a_relative_import reads ray_quad",
        "captured reads module",
        "reaches_into_another_module reads frustum",
        "reads_a_constant_from_another_module reads SHOULDER",
        "reads_computed_constants reads SCALED",
        "reads_computed_constants reads TABLE",
    ]
