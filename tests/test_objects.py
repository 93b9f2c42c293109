"""The object library, users' mesh files, surface samples and observability."""

import itertools

import mujoco
import numpy as np
import open3d as o3d
import pytest

from liuxing_envs import forking
from liuxing_envs.sim.camera import CameraIntrinsics
from liuxing_envs.sim.objects import (
    DEFAULT_OBSERVATION_ELEVATIONS_DEG,
    DEFAULT_OBSERVATION_RADII,
    OBJECT_NAMES,
    OBJECT_SETS,
    PROCEDURAL_SET_SIZE,
    PROCEDURAL_SIZE_RANGE,
    ObjectMesh,
    _make_procedural,
    default_observation_viewpoints,
    get_object,
    is_object_name,
    load_mesh_file,
    observable_mask,
    observable_samples,
    observation_viewpoints,
    surface_samples,
)
from tests.forked_child import outcome_in_forked_child

MULTI_PART = (
    "mug", "table", "chair", "stacked_blocks", "t_pipe", "step_pyramid", "ring_stand", "stool",
)  # fmt: skip


def _legacy(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array(vertices)), o3d.utility.Vector3iVector(np.array(faces))
    )
    mesh.remove_unreferenced_vertices()
    return mesh


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _box_mesh(size=(0.1, 0.06, 0.04), name: str = "test_box") -> ObjectMesh:
    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate((-size[0] / 2, -size[1] / 2, 0.0))
    return ObjectMesh(name, np.asarray(box.vertices), np.asarray(box.triangles))


# --- the library -----------------------------------------------------------------------------


def test_library_has_the_required_families():
    required = "box cylinder cone torus l_bracket u_bracket mug bowl table chair stacked_blocks"
    required += " arch bunny obelisk vase t_pipe step_pyramid"
    assert set(required.split()) <= set(OBJECT_NAMES)
    assert len(OBJECT_NAMES) >= 16 and len(set(OBJECT_NAMES)) == len(OBJECT_NAMES)


def _assert_union_of_closed_outward_parts(mesh: ObjectMesh) -> None:
    name = mesh.name
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape[1] == 3
    assert mesh.faces.dtype == np.int32 and mesh.faces.shape[1] == 3
    assert len(mesh.faces) <= 4000
    whole = mesh.to_open3d()
    assert whole.is_edge_manifold(allow_boundary_edges=False)
    assert whole.is_vertex_manifold()
    # Consistent winding: every directed edge exactly once, its reverse exactly once.
    directed = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    assert len(np.unique(directed, axis=0)) == len(directed)
    assert len(np.unique(np.sort(directed, axis=1), axis=0)) * 2 == len(directed)
    # No degenerate triangles and no coincident vertices (those would weld parts together).
    assert mesh.face_areas.min() > 1e-7 * mesh.diagonal**2
    assert len(np.unique(mesh.vertices.round(9), axis=0)) == len(mesh.vertices)
    # Parts may overlap each other, but each is watertight on its own (open3d's test also
    # rejects self-intersections) and encloses a positive volume (outward normals).
    for part in np.unique(mesh.part_ids):
        faces = mesh.faces[mesh.part_ids == part]
        assert _legacy(mesh.vertices, faces).is_watertight(), f"{name} part {part}"
        assert _signed_volume(mesh.vertices, faces) > 0, f"{name} part {part}"


def _assert_resting_centred(mesh: ObjectMesh) -> None:
    assert mesh.vertices[:, 2].min() == 0.0
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose((low + high)[:2] / 2, 0.0, atol=1e-12)
    np.testing.assert_allclose(mesh.extents, high - low)
    assert mesh.diagonal == pytest.approx(np.linalg.norm(high - low))
    assert mesh.area == pytest.approx(mesh.to_open3d().get_surface_area())


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_every_object_is_a_union_of_closed_outward_parts(name):
    mesh = get_object(name)
    assert mesh.name == name
    _assert_union_of_closed_outward_parts(mesh)
    assert (mesh.part_ids.max() > 0) == (name in MULTI_PART)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_every_object_rests_on_the_table_centred_at_tabletop_size(name):
    mesh = get_object(name)
    assert 0.08 <= mesh.extents.max() <= 0.20
    _assert_resting_centred(mesh)


def test_objects_are_distinct_shapes_even_up_to_scale():
    # Scale-free signature: the two smaller bounding-box sides relative to the largest, and
    # log(volume / (area * diagonal)). Every pair must differ clearly in at least one.
    signature = {}
    for name in OBJECT_NAMES:
        mesh = get_object(name)
        sides = np.sort(mesh.extents) / mesh.extents.max()
        signature[name] = np.r_[sides[:2], np.log(mesh.volume / (mesh.area * mesh.diagonal))]
    for a, b in itertools.combinations(OBJECT_NAMES, 2):
        assert np.abs(signature[a] - signature[b]).max() > 0.1, (a, b)


def test_the_blob_is_the_same_every_time():
    # Built fresh (bypassing the cache) it must reproduce the cached object exactly.
    from liuxing_envs.sim.objects import _BUILDERS

    assert _BUILDERS["bunny"]() == get_object("bunny")


def test_library_compiles_as_mujoco_mesh_geoms():
    spec = mujoco.MjSpec()
    for name in OBJECT_NAMES:
        mesh = get_object(name)
        spec.add_mesh(name=name, uservert=mesh.vertices.ravel(), userface=mesh.faces.ravel())
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name)
    model = spec.compile()
    assert model.nmesh == len(OBJECT_NAMES)
    assert np.all(model.mesh_facenum == [len(get_object(n).faces) for n in OBJECT_NAMES])


def test_split_is_fixed_disjoint_and_covers_the_library():
    train, held_out = set(OBJECT_SETS["train"]), set(OBJECT_SETS["held_out"])
    validation = set(OBJECT_SETS["validation"])
    assert not train & held_out and not train & validation and not validation & held_out
    assert train | validation | held_out == set(OBJECT_NAMES) == set(OBJECT_SETS["all"])
    assert len(train) >= 10 and len(held_out) >= 5 and len(validation) >= 3
    # Held out: families with no member in train.
    assert {"torus", "chair", "arch"} <= held_out


def test_get_object_caches_and_rejects_unknown_names():
    assert get_object("mug") is get_object("mug")
    with pytest.raises(ValueError, match="unknown object 'teapot'.*box.*mug"):
        get_object("teapot")


# --- procedural shapes -----------------------------------------------------------------------


@pytest.mark.parametrize("name", OBJECT_SETS["procedural"])
def test_every_procedural_shape_is_a_tabletop_union_of_closed_parts(name):
    mesh = get_object(name)
    assert mesh.name == name
    _assert_union_of_closed_outward_parts(mesh)
    _assert_resting_centred(mesh)
    low, high = PROCEDURAL_SIZE_RANGE
    assert low - 1e-12 <= mesh.extents.max() <= high + 1e-12


def test_procedural_shapes_are_seeded_distinct_and_apart_from_the_library():
    names = OBJECT_SETS["procedural"]
    assert len(names) == PROCEDURAL_SET_SIZE == len(set(names))
    assert not set(names) & set(OBJECT_SETS["all"])  # "all" is the library's families
    # Built fresh (bypassing the cache), a shape is the same on every build.
    assert _make_procedural(7) == get_object("procedural_7")
    # Any index names a shape, beyond the set too; the set is many shapes, not a few.
    assert get_object("procedural_5000").name == "procedural_5000"
    digests = {get_object(name).digest for name in names}
    assert len(digests) == len(names)
    part_counts = {int(get_object(name).part_ids.max()) + 1 for name in names}
    assert {1, 2, 3} <= part_counts
    # Shapes, not rescalings: their scale-free proportions spread widely.
    ratios = np.array([np.sort(get_object(n).extents) / get_object(n).extents.max() for n in names])
    assert ratios[:, 0].std() > 0.1 and ratios[:, 1].std() > 0.1


# Beyond the set too: a sample of indices, with the four whose tiny cups once came out
# inside out or with slivers (now built solid).
@pytest.mark.parametrize("index", sorted({70, 586, 908, 937, *range(101, 4000, 97)}))
def test_procedural_shapes_beyond_the_set_are_valid_too(index):
    mesh = get_object(f"procedural_{index}")
    _assert_union_of_closed_outward_parts(mesh)
    _assert_resting_centred(mesh)


@pytest.mark.parametrize(
    "bad",
    [
        *("procedural_", "procedural_01", "procedural_-1", "procedural_x", "procedural_1.5"),
        *("procedural_1000000", "procedural_\u0663", "procedural_ 1"),
    ],
)
def test_malformed_procedural_names_are_refused(bad):
    assert not is_object_name(bad)
    with pytest.raises(ValueError, match=f"unknown object '{bad}'.*procedural_<n>"):
        get_object(bad)


def test_procedural_shapes_compile_and_are_mostly_observable():
    spec = mujoco.MjSpec()
    names = OBJECT_SETS["procedural"]
    for name in names:
        mesh = get_object(name)
        spec.add_mesh(name=name, uservert=mesh.vertices.ravel(), userface=mesh.faces.ravel())
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name)
    assert spec.compile().nmesh == len(names)
    for name in names[:8]:
        points, normals, observable = observable_samples(name, 1.2, 512)
        assert 0.5 < observable.mean() < 1.0, name
        resting = (points[:, 2] < 1e-9) & (normals[:, 2] < -0.99)
        assert not observable[resting].any(), name


def test_object_mesh_is_immutable_and_compares_by_content():
    mesh = get_object("cone")
    with pytest.raises(ValueError):
        mesh.vertices[0, 0] = 1.0
    copy = ObjectMesh("cone", np.array(mesh.vertices), np.array(mesh.faces))
    assert copy == mesh and hash(copy) == hash(mesh) and copy is not mesh
    assert ObjectMesh("other", mesh.vertices, mesh.faces) != mesh
    bigger = mesh.scaled(1.5)
    np.testing.assert_allclose(bigger.extents, 1.5 * mesh.extents)
    assert bigger.vertices[:, 2].min() == 0.0
    with pytest.raises(ValueError, match="scale"):
        mesh.scaled(0.0)
    with pytest.raises(ValueError, match="faces"):
        ObjectMesh("bad", mesh.vertices, np.array([[0, 1, len(mesh.vertices)]]))


# --- users' mesh files -----------------------------------------------------------------------


@pytest.mark.parametrize("extension", [".obj", ".stl", ".ply"])
def test_user_meshes_load_scaled_centred_and_resting_on_the_table(tmp_path, extension):
    box = o3d.geometry.TriangleMesh.create_box(2.0, 1.0, 0.5)  # a "millimetre" CAD export
    box.translate((5.0, -3.0, 7.0))
    box.compute_triangle_normals()  # STL needs them
    path = tmp_path / f"widget{extension}"
    assert o3d.io.write_triangle_mesh(str(path), box)
    mesh = load_mesh_file(path, size=0.12)
    assert mesh.name == "widget"
    np.testing.assert_allclose(mesh.extents, [0.12, 0.06, 0.03], atol=1e-7)
    assert mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(
        mesh.vertices[:, :2].min(0) + mesh.vertices[:, :2].max(0), 0.0, atol=1e-9
    )
    # STL stores three vertices per triangle; the duplicates are merged again.
    assert (len(mesh.vertices), len(mesh.faces)) == (8, 12)
    assert mesh.volume == pytest.approx(0.12 * 0.06 * 0.03, rel=1e-5)


#: A cube as Blender exports it: quads, texture and normal indices, a group and smoothing.
QUAD_CUBE_OBJ = """# Blender 4.2
o Cube
v 1 1 -1
v 1 -1 -1
v 1 1 1
v 1 -1 1
v -1 1 -1
v -1 -1 -1
v -1 1 1
v -1 -1 1
vn 0 1 0
vt 0.5 0.5
s 0
f 1/1/1 5/1/1 7/1/1 3/1/1
f 4/1/1 3/1/1 7/1/1 8/1/1
f 8/1/1 7/1/1 5/1/1 6/1/1
f 6/1/1 2/1/1 4/1/1 8/1/1
f 2/1/1 1/1/1 3/1/1 4/1/1
f -3//1 -4//1 -8//1 -7//1
"""


def test_user_obj_polygons_are_triangulated_not_dropped(tmp_path):
    path = tmp_path / "cube.obj"
    path.write_text(QUAD_CUBE_OBJ)
    mesh = load_mesh_file(path, size=0.1)
    assert (len(mesh.vertices), len(mesh.faces)) == (8, 12)
    assert mesh.volume == pytest.approx(0.1**3, rel=1e-9)  # closed and wound outward
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(ValueError, match="bad.obj.*vertex it does not define"):
        load_mesh_file(bad)
    bad.write_text("v 0 0 0\nv 1 0 zero\n")
    with pytest.raises(ValueError, match="bad.obj, line 2"):
        load_mesh_file(bad)


def test_user_mesh_cleanup_drops_degenerate_triangles_and_fixes_inward_winding(tmp_path):
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    vertices = np.vstack([np.asarray(box.vertices), [[0.5, 0.0, 0.0]]])  # midpoint of 0 and 1
    inward = np.asarray(box.triangles)[:, ::-1]
    faces = np.vstack([inward, [[0, 0, 1], [0, 1, 8]]])  # a repeated index; a zero-area sliver
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces)
    )
    path = tmp_path / "cube.ply"
    assert o3d.io.write_triangle_mesh(str(path), legacy)
    mesh = load_mesh_file(str(path))
    assert len(mesh.faces) == 12 and len(mesh.vertices) == 8
    assert mesh.volume > 0
    assert mesh.extents.max() == pytest.approx(0.15)
    # A sliver reaching far out is dropped, and the size is the solid's, not the sliver's.
    far = np.vstack([vertices, [[5.0, 0.0, 0.0], [10.0, 0.0, 0.0]]])
    slivered = np.vstack([inward, [[0, 9, 10]]])
    _write_ply(tmp_path / "slivered.ply", far, slivered)
    mesh = load_mesh_file(str(tmp_path / "slivered.ply"))
    assert len(mesh.faces) == 12 and mesh.extents.max() == pytest.approx(0.15)


def _write_ply(path, vertices, faces) -> None:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)),
    )
    assert o3d.io.write_triangle_mesh(str(path), mesh)


def test_user_meshes_are_wound_outward_part_by_part_and_triangle_by_triangle(tmp_path):
    """Ground truth on an inward-wound part counts as unobservable, so every part of a file
    must come out wound outward whatever the file mixed: one part inward, every other
    triangle reversed, each triangle also present reversed (a double-sided export)."""
    ball = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=12)
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate((1.5, -0.5, -0.5))
    ball_v, ball_f = np.asarray(ball.vertices), np.asarray(ball.triangles)
    box_v, box_f = np.asarray(box.vertices), np.asarray(box.triangles) + len(ball_v)
    vertices = np.vstack([ball_v, box_v])
    _write_ply(tmp_path / "ok.ply", vertices, np.vstack([ball_f, box_f]))
    outward = load_mesh_file(tmp_path / "ok.ply")
    mixed = ball_f.copy()
    mixed[::2] = mixed[::2, ::-1]
    cases = {
        "handle_inward": np.vstack([ball_f, box_f[:, ::-1]]),
        "mixed": np.vstack([mixed, box_f]),
        "double_sided": np.vstack([ball_f, box_f, ball_f[:, ::-1], box_f[:, ::-1]]),
    }
    for name, faces in cases.items():
        _write_ply(tmp_path / f"{name}.ply", vertices, faces)
        mesh = load_mesh_file(tmp_path / f"{name}.ply")
        assert len(mesh.faces) == len(outward.faces), name
        assert mesh.volume == pytest.approx(outward.volume, rel=1e-9), name
        assert sorted(map(tuple, np.sort(mesh.faces, axis=1))) == sorted(
            map(tuple, np.sort(outward.faces, axis=1))
        )
        seen = observable_samples(mesh, 1.0, 2048).observable.mean()
        assert seen == pytest.approx(observable_samples(outward, 1.0, 2048).observable.mean())


def test_an_open_user_mesh_is_oriented_the_same_wherever_the_file_puts_it(tmp_path):
    dome = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=12)
    vertices, faces = np.asarray(dome.vertices), np.asarray(dome.triangles)
    upper = faces[(vertices[faces][:, :, 2] >= -1e-9).all(axis=1)]  # the open upper half
    meshes = []
    for offset in (0.0, -50.0, 300.0):
        _write_ply(tmp_path / f"dome{offset}.ply", vertices + [0, 0, offset], upper[:, ::-1])
        meshes.append(load_mesh_file(tmp_path / f"dome{offset}.ply"))
    for mesh in meshes[1:]:
        np.testing.assert_array_equal(mesh.faces, meshes[0].faces)
    assert observable_samples(meshes[0], 1.0, 2048).observable.mean() > 0.9  # seen from above


def test_obj_face_indices_count_from_one_and_a_bom_is_skipped(tmp_path):
    tetrahedron = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    path = tmp_path / "bom.obj"
    path.write_text(tetrahedron, encoding="utf-8-sig")
    assert len(load_mesh_file(path).vertices) == 4
    path = tmp_path / "zero.obj"
    path.write_text(tetrahedron.replace("f 2 3 4", "f 0 3 4") + "v 9 9 9\n")
    with pytest.raises(ValueError, match=r"zero.obj, line 8: .*vertex 0 \(OBJ counts"):
        load_mesh_file(path)


def test_user_mesh_errors_are_clear(tmp_path):
    missing = tmp_path / "nowhere.obj"
    with pytest.raises(FileNotFoundError, match="nowhere.obj"):
        load_mesh_file(missing)
    text = tmp_path / "notes.txt"
    text.write_text("not a mesh")
    with pytest.raises(ValueError, match=r"\.txt.*\.obj, \.ply, \.stl"):
        load_mesh_file(text)
    rng = np.random.default_rng(0)
    for extension in (".obj", ".stl", ".ply"):
        garbage = tmp_path / f"garbage{extension}"
        garbage.write_bytes(rng.bytes(2048))
        with pytest.raises(ValueError, match=f"garbage\\{extension}"):
            load_mesh_file(garbage)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    with pytest.raises(ValueError, match="empty.obj"):
        load_mesh_file(empty)
    huge = tmp_path / "huge.obj"  # was an OverflowError naming no file
    huge.write_text("v 0 0 0\nv 1e300 0 0\nv 0 1e300 0\nv 0 0 1e300\nf 1 2 3\nf 1 3 4\n")
    with pytest.raises(ValueError, match="huge.obj spans 1e\\+300 units"):
        load_mesh_file(huge)
    cloud = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(
        str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.random((20, 3))))
    )
    with pytest.raises(ValueError, match="cloud.ply"):
        load_mesh_file(cloud)
    box = tmp_path / "box.obj"
    o3d.io.write_triangle_mesh(str(box), o3d.geometry.TriangleMesh.create_box())
    with pytest.raises(ValueError, match="size"):
        load_mesh_file(box, size=0.0)
    # A tilted square sheet and a lone triangle: MuJoCo could not build their collision hulls.
    square = tmp_path / "sheet.obj"
    square.write_text("v 0 0 0\nv 1 0 0.5\nv 1 1 0.5\nv 0 1 0\nf 1 2 3 4\n")
    triangle = tmp_path / "triangle.obj"
    triangle.write_text("v 0 0 0\nv 1 0 0\nv 0 1 1\nf 1 2 3\n")
    for flat in (square, triangle):
        with pytest.raises(ValueError, match=f"{flat.name} is flat"):
            load_mesh_file(flat)


# --- surface samples -------------------------------------------------------------------------


def test_samples_are_deterministic_per_seed_and_cached():
    points, normals = surface_samples("bunny", 2048, seed=3)
    again = surface_samples(get_object("bunny"), 2048, seed=3)
    assert again[0] is points  # cached: the same read-only arrays
    assert not points.flags.writeable
    bunny = get_object("bunny")
    rebuilt = ObjectMesh("bunny", np.array(bunny.vertices), np.array(bunny.faces))
    fresh = surface_samples(rebuilt, 2048, 3)
    np.testing.assert_array_equal(fresh[0], points)
    other, _ = surface_samples("bunny", 2048, seed=4)
    assert points.shape == other.shape == normals.shape == (2048, 3)
    assert not np.allclose(points, other)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_box_samples_are_uniform_per_face_with_outward_normals():
    size = np.array([0.1, 0.06, 0.04])
    mesh = _box_mesh(tuple(size))
    points, normals = surface_samples(mesh, 20000, seed=1)
    half = np.array([size[0] / 2, size[1] / 2, size[2] / 2])
    centre = np.array([0.0, 0.0, size[2] / 2])
    # Each sample lies on the face its normal says, on the box's surface.
    axis = np.abs(normals).argmax(axis=1)
    sign = np.sign(normals[np.arange(len(normals)), axis])
    offset = points - centre
    np.testing.assert_allclose(offset[np.arange(len(points)), axis], sign * half[axis], atol=1e-9)
    assert np.all(np.abs(offset) <= half + 1e-9)
    face_area = {0: size[1] * size[2], 1: size[0] * size[2], 2: size[0] * size[1]}
    total = 2 * sum(face_area.values())
    for k in range(3):
        for s in (-1.0, 1.0):
            share = np.mean((axis == k) & (sign == s))
            assert share == pytest.approx(face_area[k] / total, rel=0.06), (k, s)


def test_samples_inside_other_parts_are_rejected():
    # Table: the legs run 8 mm into the top; nothing may be sampled inside the top slab.
    points, _ = surface_samples("table", 8192, seed=0)
    inside_top = (
        (np.abs(points[:, 0]) < 0.08 - 1e-6)
        & (np.abs(points[:, 1]) < 0.05 - 1e-6)
        & (points[:, 2] > 0.088 + 1e-6)
        & (points[:, 2] < 0.1 - 1e-6)
    )
    assert not inside_top.any()
    # Step pyramid: each tier sinks 2 mm into the one below. Uniform samples over the union
    # put up-facing samples in proportion to the exposed up-facing area (the base's
    # footprint), not to the sum of all tier tops.
    points, normals = surface_samples("step_pyramid", 8192, seed=0)
    sides = np.array([0.16, 0.12, 0.08, 0.04])
    exposed = 2 * sides[0] ** 2 + 4 * (sides[0] * 0.025 + sides[1:].sum() * 0.023)
    assert np.mean(normals[:, 2] > 0.5) == pytest.approx(sides[0] ** 2 / exposed, rel=0.05)


# --- observability ---------------------------------------------------------------------------


def test_default_viewpoints_cover_the_upper_hemisphere():
    views = default_observation_viewpoints(0.5)
    assert views.shape == (97, 3)
    np.testing.assert_allclose(np.linalg.norm(views, axis=1), 0.5)
    elevation = np.degrees(np.arcsin(views[:, 2] / 0.5))
    assert elevation.min() == pytest.approx(20.0) and elevation.max() == pytest.approx(90.0)
    assert np.sum(np.isclose(elevation, 90.0)) == 1  # the top view once
    shifted = default_observation_viewpoints(0.3, center=(0.1, 0, 0.05), elevations_deg=(45,))
    assert shifted.shape == (24, 3)
    np.testing.assert_allclose(np.linalg.norm(shifted - [0.1, 0, 0.05], axis=1), 0.3)


def test_box_bottom_is_never_observable_and_top_always_is():
    mesh = _box_mesh()
    points, normals = surface_samples(mesh, 4096, seed=0)
    visible = observable_mask(mesh, points, normals, default_observation_viewpoints())
    assert visible.dtype == bool and visible.shape == (4096,)
    bottom, top = normals[:, 2] < -0.5, normals[:, 2] > 0.5
    assert not visible[bottom].any()
    assert visible[top].all() and visible[~bottom].all()
    # Seen from below with no table, the bottom shows; the table hides it again.
    below = np.array([[0.0, 0.0, -0.4], [0.3, 0.1, -0.2]])
    assert observable_mask(mesh, points, normals, below, table=False)[bottom].all()
    assert not observable_mask(mesh, points, normals, below, table=True).any()


@pytest.mark.parametrize(
    ("name", "scale", "group"),
    [("mug", 0.8, 8), ("chair", 1.2, 3), ("procedural_5", 1.0, 8), ("torus", 1.1, 1)],
)
def test_views_cast_a_few_at_a_time_see_what_all_at_once_see(name, scale, group):
    """Casting each group of views only towards the samples earlier groups left unseen gives
    the mask of one cast of every (view, sample) pair, sample for sample."""
    mesh = get_object(name).scaled(scale)
    points, normals = surface_samples(get_object(name), 4096, seed=3)
    points = points * scale
    views = observation_viewpoints(
        DEFAULT_OBSERVATION_RADII,
        center=mesh.middle,
        elevations_deg=DEFAULT_OBSERVATION_ELEVATIONS_DEG,
    )
    at_once = observable_mask(mesh, points, normals, views, views_per_cast=None)
    assert 0.5 < at_once.mean() < 1.0  # some samples hidden, so the groups' skipping matters
    np.testing.assert_array_equal(
        observable_mask(mesh, points, normals, views, views_per_cast=group), at_once
    )
    with pytest.raises(ValueError, match="views_per_cast must be a positive integer or None"):
        observable_mask(mesh, points, normals, views, views_per_cast=0)


def _observable_mask_in_a_forked_child(mesh, points, normals, results) -> None:
    try:
        observable_mask(mesh, points, normals, default_observation_viewpoints())
        results.put("returned")
    except Exception as error:  # reported at once, rather than as the parent's timeout
        results.put(repr(error))


def test_a_forked_child_refuses_the_observable_surface_instead_of_hanging(monkeypatch):
    """The observable-surface precomputation (an object not yet cached, in a worker forked
    after open3d was imported) waited forever in open3d's ray casting; it now raises,
    naming spawn. The parent still computes it."""
    # As when OMP_NUM_THREADS was not 1 at import (with it at 1 nothing would hang).
    monkeypatch.setattr(forking, "_single_openmp_thread", False)
    import open3d  # noqa: F401 (the package imports it only when first used)

    mesh = _box_mesh()
    points, normals = surface_samples(mesh, 256, seed=0)
    outcome = outcome_in_forked_child(_observable_mask_in_a_forked_child, mesh, points, normals)
    assert "observable_mask() uses open3d" in outcome
    assert "vector_kwargs={'context': 'spawn'}" in outcome
    assert observable_mask(mesh, points, normals, default_observation_viewpoints()).any()


def test_points_inside_a_closed_box_are_never_observable():
    mesh = _box_mesh()
    rng = np.random.default_rng(0)
    points = rng.uniform([-0.049, -0.029, 0.001], [0.049, 0.029, 0.039], size=(2000, 3))
    normals = rng.normal(size=(2000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert not observable_mask(mesh, points, normals, default_observation_viewpoints()).any()


def test_bowl_inside_is_seen_from_above_but_hidden_from_a_low_side_view():
    mesh = get_object("bowl")
    points, normals = surface_samples(mesh, 4096, seed=0)
    radial = np.hypot(points[:, 0], points[:, 1])
    inner_floor = (radial < 0.02) & (normals[:, 2] > 0.9) & (points[:, 2] > 0.001)
    outer_foot = (normals[:, 2] < -0.9) & (points[:, 2] < 1e-9)
    assert inner_floor.sum() > 20 and outer_foot.sum() > 5
    top = observable_mask(mesh, points, normals, [[0.0, 0.0, 0.4]])
    assert top[inner_floor].all()
    assert not top[outer_foot].any()
    low_side = np.array([[0.4 * np.cos(np.radians(10)), 0.0, 0.4 * np.sin(np.radians(10))]])
    assert not observable_mask(mesh, points, normals, low_side)[inner_floor].any()


def test_observable_samples_are_cached_and_scale_consistently():
    first = observable_samples("mug", 1.0, 4096)
    assert observable_samples("mug", 1.0, 4096) is first
    points, normals, observable = first
    assert points.shape == normals.shape == (4096, 3) and observable.shape == (4096,)
    assert not (points.flags.writeable or observable.flags.writeable)
    assert 0.6 < observable.mean() < 1.0
    bigger = observable_samples(get_object("mug"), 1.2, 4096)
    np.testing.assert_allclose(bigger.points, 1.2 * points)
    np.testing.assert_array_equal(bigger.normals, normals)
    # A box: everything but its bottom (area share 0.06*0.1 / 0.0248) is observable.
    box = observable_samples(_box_mesh(), 0.9, 4096)
    assert box.observable.mean() == pytest.approx(1 - 0.006 / 0.0248, abs=0.03)
    with pytest.raises(ValueError, match="observation radius 0.05 m must exceed"):
        observable_samples("obelisk", 1.0, 1024, radii=(0.05, 0.4))
    with pytest.raises(ValueError, match="non-empty"):
        observable_samples("obelisk", 1.0, 1024, elevations_deg=())
    with pytest.raises(ValueError, match="scale"):
        observable_samples("mug", -1.0)


def test_every_object_has_observable_samples_at_the_largest_scale():
    # The default observation spheres clear every object at scale 1.2, and most of each
    # object's surface is observable while the part resting on the table is not.
    for name in OBJECT_NAMES:
        points, normals, observable = observable_samples(name, 1.2, 512)
        assert 0.5 < observable.mean() < 1.0, name
        resting = (points[:, 2] < 1e-9) & (normals[:, 2] < -0.99)
        assert not observable[resting].any(), name


def test_observability_is_judged_from_the_view_space_around_the_objects_middle():
    """What only a view outside ViewPlanning-v0's view space sees does not count: the
    underside of a table's top shows from a view near the table plane, but from no view at
    20-90 deg around the table's middle, at any of its scales; a narrower view space (the
    env's own elevation range) sees less of a T-pipe lying on its side."""
    table = get_object("table")
    height = table.extents[2]
    for scale in (0.8, 1.0, 1.2):
        points, normals, observable = observable_samples(table, scale, 2048)
        underside = (normals[:, 2] < -0.99) & (points[:, 2] > 0.5 * scale * height)
        assert underside.sum() > 50
        assert not observable[underside].any()
        low_view = [[0.45, 0.0, 0.3 * scale * height]]  # under the top, beside the table
        assert observable_mask(table.scaled(scale), points, normals, low_view)[underside].any()
    wide = observable_samples("t_pipe", 1.0, 2048).observable
    high = observable_samples("t_pipe", 1.0, 2048, elevations_deg=(60.0, 75.0, 90.0)).observable
    assert not (high & ~wide).any() and high.mean() < wide.mean() - 0.05


def test_a_mesh_in_many_pieces_is_sampled_with_a_warning():
    # 70 disjoint cubes: a fragmented scan rather than an assembly; no per-part rejection.
    cube = _box_mesh((0.01, 0.01, 0.01))
    offsets = np.repeat(0.02 * np.arange(70), len(cube.vertices))[:, None] * [1.0, 0.0, 0.0]
    vertices = np.tile(cube.vertices, (70, 1)) + offsets
    faces = (cube.faces[None] + len(cube.vertices) * np.arange(70)[:, None, None]).reshape(-1, 3)
    mesh = ObjectMesh("shards", vertices, faces)
    with pytest.warns(UserWarning, match="70 separate parts"):
        points, _ = surface_samples(mesh, 1000, 0)
    assert points.shape == (1000, 3)
    # Every cube is sampled, about in proportion to its area (1000 / 70 each), and every
    # sample lies on a cube's surface.
    corners = np.asarray(mesh.vertices).reshape(70, -1, 3)
    low, high = corners.min(axis=1), corners.max(axis=1)
    cube = np.clip(np.searchsorted(low[:, 0], points[:, 0], side="right") - 1, 0, 69)
    assert np.all((points >= low[cube] - 1e-9) & (points <= high[cube] + 1e-9))
    on_a_face = np.isclose(points, low[cube], atol=1e-9) | np.isclose(points, high[cube], atol=1e-9)
    assert on_a_face.any(axis=1).all()
    per_cube = np.bincount(cube, minlength=70)
    assert per_cube.min() >= 3 and per_cube.max() <= 30


def _seen_in_image(name, scale, count, half_angle, min_depth):
    """Per sample: whether some default observation view sees it (observable_mask) with it
    inside the view's image cone of ``half_angle`` and beyond ``min_depth``, the camera aimed
    at the object's middle as the env aims at its estimate of it."""
    mesh = get_object(name).scaled(scale)
    points, normals, _ = observable_samples(name, scale, count)
    middle = mesh.middle
    seen = np.zeros(len(points), dtype=bool)
    eyes = observation_viewpoints(
        DEFAULT_OBSERVATION_RADII,
        center=middle,
        elevations_deg=DEFAULT_OBSERVATION_ELEVATIONS_DEG,
    )
    for eye in eyes:
        offset = points - eye
        depth = offset @ ((middle - eye) / np.linalg.norm(middle - eye))
        in_image = (depth >= min_depth) & (
            depth >= np.cos(half_angle) * np.linalg.norm(offset, axis=1)
        )
        ids = np.flatnonzero(in_image & ~seen)
        if ids.size:
            seen[ids[observable_mask(mesh, points[ids], normals[ids], [eye])]] = True
    return seen


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_the_cameras_image_and_near_limit_hide_no_observable_sample(name):
    """Observability ignores the camera's field of view and near limit; for the library at
    the env's scales that loses nothing: every observable sample is inside the image (the
    cone inscribed in its square) and beyond the near limit of some view that sees it."""
    camera = CameraIntrinsics()
    for scale in (0.8, 1.2):
        observable = observable_samples(name, scale, 1024).observable
        seen = _seen_in_image(name, scale, 1024, np.radians(camera.fovy_deg) / 2, camera.min_depth)
        assert observable.sum() > 300
        assert not (observable & ~seen).any(), (name, scale)


def test_a_narrower_image_or_a_farther_near_limit_would_hide_observable_samples():
    """The check above can fail, through either limit: a 10 deg image misses much of a chair,
    and so does the real image with a near limit of 0.5 m."""
    camera = CameraIntrinsics()
    observable = observable_samples("chair", 1.2, 1024).observable
    narrow = _seen_in_image("chair", 1.2, 1024, np.radians(5.0), camera.min_depth)
    assert (observable & ~narrow).mean() > 0.1
    far = _seen_in_image("chair", 1.2, 1024, np.radians(camera.fovy_deg) / 2, 0.5)
    assert (observable & ~far).mean() > 0.1
