"""The objects an env is given: a named set, or a list of library names, procedural shapes
and users' mesh files, each with a name of its own."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from liuxing_envs.sim.objects import (
    OBJECT_SETS,
    PROCEDURAL_PREFIX,
    ObjectMesh,
    get_object,
    is_object_name,
    load_mesh_file,
)

USER_MESH_SIZE = 0.15  # m, largest bounding-box side of users' meshes


def load_objects(object_set: str, objects: Sequence[str] | None) -> list[ObjectMesh]:
    """The meshes of ``object_set``, or of ``objects`` when given (library names, procedural
    names or mesh files, scaled to USER_MESH_SIZE), renamed apart where names clash."""
    if objects is None:
        return [get_object(name) for name in OBJECT_SETS[object_set]]
    expected = (
        "objects must be a non-empty list of library names, procedural_<n> names or mesh file paths"
    )
    if isinstance(objects, str | os.PathLike):
        raise ValueError(f"{expected}, got the single {objects!r} (wrap it in a list)")
    try:
        items = list(objects)
    except TypeError:
        raise ValueError(f"{expected}, got {objects!r}") from None
    if not items or not all(isinstance(item, str | os.PathLike) for item in items):
        raise ValueError(f"{expected}, got {objects!r}")
    meshes = []
    for item in items:
        if is_object_name(str(item)):
            meshes.append(get_object(str(item)))
            continue
        try:
            meshes.append(load_mesh_file(item, size=USER_MESH_SIZE))
        except (OSError, ValueError) as error:
            raise type(error)(
                f"objects: {str(item)!r} is not a library object "
                f"({', '.join(OBJECT_SETS['all'])}) or a procedural shape "
                f"({PROCEDURAL_PREFIX}<n>), and as a mesh file: {error}"
            ) from error
    return named_apart(items, meshes)


def named_apart(items: list, meshes: list[ObjectMesh]) -> list[ObjectMesh]:
    """``meshes`` (loaded from ``items``) renamed where their names clash: a mesh file is then
    named by as much of its path as tells it apart, its file name and then its folders
    (``box.stl`` and ``box.ply``; ``chair1/models/model_normalized.obj``, as in ShapeNet).
    An item listed twice, which no path tells apart, is refused."""
    paths = [None if is_object_name(str(item)) else Path(item).resolve() for item in items]
    levels = [0] * len(items)

    def name(index: int) -> str:
        path, level = paths[index], levels[index]
        if path is None or level == 0:
            return meshes[index].name
        return "/".join(path.parts[-level:])

    while True:
        names = [name(index) for index in range(len(items))]
        clashing = [index for index, n in enumerate(names) if names.count(n) > 1]
        if not clashing:
            break
        longer = [
            i for i in clashing if paths[i] is not None and levels[i] < len(paths[i].parts) - 1
        ]
        if not longer:
            twice = [str(items[i]) for i in clashing if names[i] == names[clashing[0]]]
            raise ValueError(f"objects lists the same object more than once: {twice}")
        for index in longer:
            levels[index] += 1
    return [
        mesh if mesh.name == new else replace(mesh, name=new)
        for mesh, new in zip(meshes, names, strict=True)
    ]
