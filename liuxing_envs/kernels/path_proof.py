"""Which waypoints of a joint path are free of the arm's contacts by a margin: a conservative
distance bound that lets :meth:`~liuxing_envs.sim.arm_collisions.ArmCollisions.check_path`
skip MuJoCo's kinematics and collision detection at waypoints where no contact can exist.

The bound never decides that a waypoint collides: a waypoint it cannot prove free goes to
``mj_kinematics`` + ``mj_collision`` as before, so the path check's result (the first
colliding waypoint, its contacts) is MuJoCo's own. What it proves, per waypoint: every geom
pair that ``mj_collision`` would test and that involves the arm is apart by at least
``margin`` (1 mm, ten times the contact tolerance that counts a collision), so MuJoCo can
report no penetrating contact there. Everything is derived from the model and data arrays:
the table of pairs again whenever a geom is switched on or off (``geom_contype``), the rest
at each call:

- **The pairs** (:func:`candidate_pairs`): MuJoCo's filters, each applied only where MuJoCo
  surely applies it (a pair it might test is kept): the same weld body, the parent filter
  (``mjDSBL_FILTERPARENT``), ``<exclude>`` (``exclude_signature``, body ids), the
  ``contype``/``conaffinity`` bitmask (not with a contact-filter callback, which replaces
  it), plus every explicit ``<pair>``; pairs without an arm geom do not count.
- **The poses**: forward kinematics of the bodies that the arm's joints move (hinge and slide
  joints, MuJoCo's formulas, ``qpos0`` included), from the data's poses of the others, which
  no waypoint changes: the caller poses the data at the path's start first.
- **The shapes**, each enclosed in a convex volume with an exact support function: spheres,
  capsules and boxes as they are, cylinders as disks swept along their axis, ellipsoids in
  their largest sphere, meshes in their oriented ``geom_aabb`` (MuJoCo collides a mesh's
  convex hull, inside it). Planes, height fields and SDFs are not bounded: a pair with one
  makes every waypoint unproven.
- **The distance bound**: for any unit direction n, the gap between the two volumes'
  projections on n is at most their distance. MuJoCo's own bounding-sphere test
  (``geom_rbound``) comes first; then a box's face normals, the centre line and directions
  from a few alternating projections between the volumes' cores (box or segment).
- **Pairs that no waypoint changes**: pairs of geoms neither of which moves are tested once;
  so is a moving geom turning about its own axis of symmetry on the only moving joint above
  it, next to a fixed geom (the arm's shoulder cylinder on its base): the set it occupies is
  the same at every waypoint, and such a pair only needs to penetrate by no more than
  ``touch`` (1e-6 m, a hundredth of the contact tolerance) along the axis, for flush parts
  that touch. A fixed pair not proven leaves every waypoint unproven.

Floating-point rounding in the bound is some 1e-15 m against the 1 mm margin.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options

# MuJoCo's mjtGeom and mjtJoint values (the kernels do not read module globals of objects).
_SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH = 2, 3, 4, 5, 6, 7
_SLIDE, _HINGE = 2, 3
#: Pair kinds in :func:`candidate_pairs`' table.
MOVING, FIXED, TURNING = 0, 1, 2
#: The geom types with a bound.
_BOUNDED_TYPES = (_SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH)
#: Alternating projections per pair after the box axes and the centre line.
_PROJECTIONS = 6


@njit(**jit_options())
def _quat_to_mat(q, out):
    """Row-major 3x3 rotation of the unit quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    out[0] = w * w + x * x - y * y - z * z
    out[1] = 2 * (x * y - w * z)
    out[2] = 2 * (x * z + w * y)
    out[3] = 2 * (x * y + w * z)
    out[4] = w * w - x * x + y * y - z * z
    out[5] = 2 * (y * z - w * x)
    out[6] = 2 * (x * z - w * y)
    out[7] = 2 * (y * z + w * x)
    out[8] = w * w - x * x - y * y + z * z


@njit(**jit_options())
def moving_bodies(arm_qadr, body_parentid, body_jntnum, body_jntadr, jnt_qposadr, nq):
    """Per body: whether one of the arm's joints (qpos addresses ``arm_qadr``) moves it."""
    nbody = body_parentid.shape[0]
    is_arm_q = np.zeros(nq, np.bool_)
    for a in arm_qadr:
        is_arm_q[a] = True
    moving = np.zeros(nbody, np.bool_)
    for b in range(1, nbody):  # parents precede children
        moving[b] = moving[body_parentid[b]]
        for j in range(body_jntadr[b], body_jntadr[b] + body_jntnum[b]):
            if is_arm_q[jnt_qposadr[j]]:
                moving[b] = True
    return moving


@njit(**jit_options())
def _off_axis(vec, axis):
    """The length of ``vec``'s part across the unit ``axis``."""
    cx = vec[1] * axis[2] - vec[2] * axis[1]
    cy = vec[2] * axis[0] - vec[0] * axis[2]
    cz = vec[0] * axis[1] - vec[1] * axis[0]
    return math.sqrt(cx * cx + cy * cy + cz * cz)


@njit(**jit_options())
def _turns_about_own_axis(
    g,
    moving,
    body_parentid,
    body_jntnum,
    body_jntadr,
    jnt_type,
    jnt_pos,
    jnt_axis,
    geom_bodyid,
    geom_type,
    geom_pos,
    geom_quat,
):
    """Whether geom ``g`` is a sphere, capsule or cylinder centred on the axis of the only
    joint that moves it, a hinge of its own body, its axis of symmetry along that axis: then
    every angle of the hinge leaves the space it occupies unchanged."""
    b = geom_bodyid[g]
    if body_jntnum[b] != 1 or moving[body_parentid[b]]:
        return False
    j = body_jntadr[b]
    kind = geom_type[g]
    if jnt_type[j] != _HINGE or not (kind == _SPHERE or kind == _CAPSULE or kind == _CYLINDER):
        return False
    axis = jnt_axis[j]
    if _off_axis(geom_pos[g] - jnt_pos[j], axis) > 1e-12:
        return False
    if kind == _SPHERE:
        return True
    rot = np.empty(9)
    _quat_to_mat(geom_quat[g], rot)
    symmetry = np.array([rot[2], rot[5], rot[8]])  # the geom's z axis in its body's frame
    return _off_axis(symmetry, axis) <= 1e-12


@njit(**jit_options())
def candidate_pairs(
    moving,
    is_arm_geom,
    use_bitmask,
    filter_parent,
    body_parentid,
    body_weldid,
    body_jntnum,
    body_jntadr,
    jnt_type,
    jnt_pos,
    jnt_axis,
    geom_bodyid,
    geom_type,
    geom_pos,
    geom_quat,
    geom_contype,
    geom_conaffinity,
    exclude_signature,
    pair_geom1,
    pair_geom2,
):
    """The geom pairs ``mj_collision`` may test that involve the arm, as rows (g1, g2, kind)
    with g1 < g2: ``MOVING`` where a joint of the arm moves either geom, ``TURNING`` for a
    moving geom that only turns about its own axis next to a fixed one, ``FIXED`` where
    neither moves."""
    ngeom = geom_bodyid.shape[0]
    keep = np.zeros((ngeom, ngeom), np.bool_)
    for g1 in range(ngeom):
        for g2 in range(g1 + 1, ngeom):
            if not (is_arm_geom[g1] or is_arm_geom[g2]):
                continue
            b1, b2 = geom_bodyid[g1], geom_bodyid[g2]
            w1, w2 = body_weldid[b1], body_weldid[b2]
            if w1 == w2:
                continue
            if filter_parent and w1 != 0 and w2 != 0:
                if w1 == body_weldid[body_parentid[w2]] or w2 == body_weldid[body_parentid[w1]]:
                    continue
            signature = (np.int64(min(b1, b2)) << 16) + max(b1, b2)
            excluded = False
            for s in exclude_signature:
                if s == signature:
                    excluded = True
            if excluded:
                continue
            if use_bitmask and not (
                (geom_contype[g1] & geom_conaffinity[g2])
                or (geom_contype[g2] & geom_conaffinity[g1])
            ):
                continue
            keep[g1, g2] = True
    for p in range(pair_geom1.shape[0]):  # explicit pairs bypass every filter
        g1, g2 = pair_geom1[p], pair_geom2[p]
        if is_arm_geom[g1] or is_arm_geom[g2]:
            keep[min(g1, g2), max(g1, g2)] = True
    out = np.empty((ngeom * ngeom, 3), np.int64)
    count = 0
    for g1 in range(ngeom):
        for g2 in range(g1 + 1, ngeom):
            if not keep[g1, g2]:
                continue
            m1, m2 = moving[geom_bodyid[g1]], moving[geom_bodyid[g2]]
            kind = MOVING
            if not (m1 or m2):
                kind = FIXED
            elif m1 != m2 and _turns_about_own_axis(
                g1 if m1 else g2,
                moving,
                body_parentid,
                body_jntnum,
                body_jntadr,
                jnt_type,
                jnt_pos,
                jnt_axis,
                geom_bodyid,
                geom_type,
                geom_pos,
                geom_quat,
            ):
                kind = TURNING
            out[count, 0], out[count, 1], out[count, 2] = g1, g2, kind
            count += 1
    return out[:count].copy()


# A bounding volume is a row of 17 numbers: centre (3), axes as the columns of a row-major
# 3x3 (9), half extents along them (3), a radius, and 1.0 where the radius is a disk's about
# the third axis (a cylinder: the disk swept along that axis) or 0.0 where it is a ball's
# (the box swept by a ball). The helpers take the table of volumes and row numbers: no array
# views in the loops (each would count references).
_VOLUME = 17


@njit(**jit_options())
def _volume(g, geom_type, geom_size, geom_aabb, gpos, gmat, vols):
    """Row ``g`` of ``vols``: the bounding volume of geom ``g`` posed at ``gpos[g]``,
    ``gmat[g]``."""
    kind = geom_type[g]
    for i in range(3):
        vols[g, i] = gpos[g, i]
    for i in range(9):
        vols[g, 3 + i] = gmat[g, i]
    vols[g, 12] = vols[g, 13] = vols[g, 14] = vols[g, 15] = vols[g, 16] = 0.0
    if kind == _SPHERE:
        vols[g, 15] = geom_size[g, 0]
    elif kind == _CAPSULE:
        vols[g, 14], vols[g, 15] = geom_size[g, 1], geom_size[g, 0]
    elif kind == _ELLIPSOID:
        vols[g, 15] = max(geom_size[g, 0], max(geom_size[g, 1], geom_size[g, 2]))
    elif kind == _CYLINDER:
        vols[g, 14], vols[g, 15], vols[g, 16] = geom_size[g, 1], geom_size[g, 0], 1.0
    elif kind == _BOX:
        for i in range(3):
            vols[g, 12 + i] = geom_size[g, i]
    else:  # a mesh: its oriented bounding box
        for i in range(3):
            vols[g, i] += (
                gmat[g, 3 * i] * geom_aabb[g, 0]
                + gmat[g, 3 * i + 1] * geom_aabb[g, 1]
                + gmat[g, 3 * i + 2] * geom_aabb[g, 2]
            )
            vols[g, 12 + i] = geom_aabb[g, 3 + i]


@njit(**jit_options())
def _support(vols, v, nx, ny, nz):
    """Half the width of volume ``v`` along the unit direction (nx, ny, nz)."""
    along2 = vols[v, 5] * nx + vols[v, 8] * ny + vols[v, 11] * nz
    width = vols[v, 14] * abs(along2)
    if vols[v, 16] > 0.0:  # a disk about the third axis
        return width + vols[v, 15] * math.sqrt(max(0.0, 1.0 - along2 * along2))
    along0 = vols[v, 3] * nx + vols[v, 6] * ny + vols[v, 9] * nz
    along1 = vols[v, 4] * nx + vols[v, 7] * ny + vols[v, 10] * nz
    return width + vols[v, 12] * abs(along0) + vols[v, 13] * abs(along1) + vols[v, 15]


@njit(**jit_options())
def _unit_gap(vols, a, b, nx, ny, nz):
    """A lower bound on the distance between volumes ``a`` and ``b``: the gap between
    their projections on the unit direction (nx, ny, nz)."""
    centres = (
        (vols[b, 0] - vols[a, 0]) * nx
        + (vols[b, 1] - vols[a, 1]) * ny
        + (vols[b, 2] - vols[a, 2]) * nz
    )
    return abs(centres) - _support(vols, a, nx, ny, nz) - _support(vols, b, nx, ny, nz)


@njit(**jit_options())
def _gap(vols, a, b, nx, ny, nz):
    """:func:`_unit_gap` along the direction (nx, ny, nz) of any length (a null direction
    bounds nothing)."""
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if not norm > 0.0:
        return -np.inf
    return _unit_gap(vols, a, b, nx / norm, ny / norm, nz / norm)


@njit(**jit_options())
def _core_point(vols, v, px, py, pz):
    """The point of volume ``v``'s core (its box or segment, without the radius) nearest
    (px, py, pz)."""
    dx, dy, dz = px - vols[v, 0], py - vols[v, 1], pz - vols[v, 2]
    x, y, z = vols[v, 0], vols[v, 1], vols[v, 2]
    for k in range(3):
        ax, ay, az = vols[v, 3 + k], vols[v, 6 + k], vols[v, 9 + k]
        half = vols[v, 12 + k]
        local = min(max(ax * dx + ay * dy + az * dz, -half), half)
        x += ax * local
        y += ay * local
        z += az * local
    return x, y, z


@njit(**jit_options())
def _faces_apart(vols, v, a, b, threshold):
    """Whether a face normal of volume ``v`` (``a`` or ``b``), if a box, proves ``a`` and
    ``b`` at least ``threshold`` apart; the normal of its thinnest side first."""
    if not (vols[v, 12] > 0.0 and vols[v, 13] > 0.0 and vols[v, 14] > 0.0):
        return False
    first = 0
    if vols[v, 13] < vols[v, 12 + first]:
        first = 1
    if vols[v, 14] < vols[v, 12 + first]:
        first = 2
    for step in range(3):
        k = (first + step) % 3
        if _unit_gap(vols, a, b, vols[v, 3 + k], vols[v, 6 + k], vols[v, 9 + k]) >= threshold:
            return True
    return False


@njit(**jit_options())
def _apart(vols, a, b, threshold):
    """Whether some direction proves volumes ``a`` and ``b`` at least ``threshold`` apart:
    a box's face normals (the thinnest first: a table top's), the centre line, then the line
    between the nearest points of their cores as alternating projections approach them."""
    if _faces_apart(vols, a, a, b, threshold) or _faces_apart(vols, b, a, b, threshold):
        return True
    ax, ay, az = vols[a, 0], vols[a, 1], vols[a, 2]
    bx, by, bz = vols[b, 0], vols[b, 1], vols[b, 2]
    if _gap(vols, a, b, bx - ax, by - ay, bz - az) >= threshold:
        return True
    for _ in range(_PROJECTIONS):
        bx, by, bz = _core_point(vols, b, ax, ay, az)
        ax, ay, az = _core_point(vols, a, bx, by, bz)
        if _gap(vols, a, b, bx - ax, by - ay, bz - az) >= threshold:
            return True
    return False


@njit(**jit_options())
def _spheres_apart(g1, g2, geom_rbound, gpos, margin):
    """MuJoCo's bounding-sphere test, by ``margin``."""
    r1, r2 = geom_rbound[g1], geom_rbound[g2]
    if not (r1 > 0.0 and r2 > 0.0):
        return False
    dx = gpos[g1, 0] - gpos[g2, 0]
    dy = gpos[g1, 1] - gpos[g2, 1]
    dz = gpos[g1, 2] - gpos[g2, 2]
    reach = r1 + r2 + margin
    return dx * dx + dy * dy + dz * dz >= reach * reach


@njit(**jit_options())
def _quat_mul_into(out, o, a, ia, b, ib):
    """``out[o] = a[ia] * b[ib]`` (quaternions, w first)."""
    aw, ax, ay, az = a[ia, 0], a[ia, 1], a[ia, 2], a[ia, 3]
    bw, bx, by, bz = b[ib, 0], b[ib, 1], b[ib, 2], b[ib, 3]
    out[o, 0] = aw * bw - ax * bx - ay * by - az * bz
    out[o, 1] = aw * bx + ax * bw + ay * bz - az * by
    out[o, 2] = aw * by - ax * bz + ay * bw + az * bx
    out[o, 3] = aw * bz + ax * by - ay * bx + az * bw


@njit(**jit_options())
def _quat_to_mat_row(q, i, out, o):
    """``out[o]``: the row-major rotation of the unit quaternion ``q[i]``."""
    w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
    out[o, 0] = w * w + x * x - y * y - z * z
    out[o, 1] = 2 * (x * y - w * z)
    out[o, 2] = 2 * (x * z + w * y)
    out[o, 3] = 2 * (x * y + w * z)
    out[o, 4] = w * w - x * x + y * y - z * z
    out[o, 5] = 2 * (y * z - w * x)
    out[o, 6] = 2 * (x * z - w * y)
    out[o, 7] = 2 * (y * z + w * x)
    out[o, 8] = w * w - x * x - y * y + z * z


@njit(**jit_options())
def _rotate(mat, m, v, i):
    """``mat[m]`` (row-major 3x3) times the vector ``v[i]``."""
    return (
        mat[m, 0] * v[i, 0] + mat[m, 1] * v[i, 1] + mat[m, 2] * v[i, 2],
        mat[m, 3] * v[i, 0] + mat[m, 4] * v[i, 1] + mat[m, 5] * v[i, 2],
        mat[m, 6] * v[i, 0] + mat[m, 7] * v[i, 1] + mat[m, 8] * v[i, 2],
    )


@njit(**jit_options())
def _pose_bodies(
    moving,
    qv,
    qpos0,
    body_parentid,
    body_jntnum,
    body_jntadr,
    body_pos,
    body_quat,
    jnt_type,
    jnt_qposadr,
    jnt_pos,
    jnt_axis,
    bx,
    bq,
    bm,
    tq,
    tm,
):
    """Forward kinematics of the ``moving`` bodies into ``bx``, ``bq``, ``bm`` (the others'
    poses there are read), as ``mj_kinematics`` computes them; ``tq`` (2, 4) and ``tm``
    (1, 9) are scratch."""
    for body in range(1, body_parentid.shape[0]):
        if not moving[body]:
            continue
        parent = body_parentid[body]
        x, y, z = _rotate(bm, parent, body_pos, body)
        bx[body, 0] = bx[parent, 0] + x
        bx[body, 1] = bx[parent, 1] + y
        bx[body, 2] = bx[parent, 2] + z
        _quat_mul_into(bq, body, bq, parent, body_quat, body)
        for j in range(body_jntadr[body], body_jntadr[body] + body_jntnum[body]):
            angle = qv[jnt_qposadr[j]] - qpos0[jnt_qposadr[j]]
            off_centre = jnt_pos[j, 0] != 0.0 or jnt_pos[j, 1] != 0.0 or jnt_pos[j, 2] != 0.0
            if jnt_type[j] == _SLIDE or off_centre:
                _quat_to_mat_row(bq, body, tm, 0)
            if jnt_type[j] == _SLIDE:
                x, y, z = _rotate(tm, 0, jnt_axis, j)
                bx[body, 0] += x * angle
                bx[body, 1] += y * angle
                bx[body, 2] += z * angle
                continue
            if off_centre:  # from the anchor, which the rotation keeps in place
                x, y, z = _rotate(tm, 0, jnt_pos, j)
                bx[body, 0] += x
                bx[body, 1] += y
                bx[body, 2] += z
            s = math.sin(0.5 * angle)
            tq[0, 0] = math.cos(0.5 * angle)
            for i in range(3):
                tq[0, 1 + i] = jnt_axis[j, i] * s
            _quat_mul_into(tq, 1, bq, body, tq, 0)
            for i in range(4):
                bq[body, i] = tq[1, i]
            if off_centre:
                _quat_to_mat_row(bq, body, tm, 0)
                x, y, z = _rotate(tm, 0, jnt_pos, j)
                bx[body, 0] -= x
                bx[body, 1] -= y
                bx[body, 2] -= z
        norm = math.sqrt(bq[body, 0] ** 2 + bq[body, 1] ** 2 + bq[body, 2] ** 2 + bq[body, 3] ** 2)
        for i in range(4):
            bq[body, i] /= norm
        _quat_to_mat_row(bq, body, bm, body)


@njit(**jit_options())
def proven_free(
    waypoints,
    arm_qadr,
    pairs,
    moving,
    margin,
    touch,
    body_parentid,
    body_jntnum,
    body_jntadr,
    body_pos,
    body_quat,
    jnt_type,
    jnt_qposadr,
    jnt_pos,
    jnt_axis,
    qpos0,
    geom_bodyid,
    geom_type,
    geom_size,
    geom_pos,
    geom_quat,
    geom_aabb,
    geom_rbound,
    qpos,
    xpos,
    xquat,
    xmat,
    geom_xpos,
    geom_xmat,
):
    """Per row of ``waypoints`` (the arm's joints, at qpos addresses ``arm_qadr``): True
    where every pair of ``pairs`` (:func:`candidate_pairs`, all of bounded geom types) is at
    least ``margin`` apart. ``moving`` is :func:`moving_bodies`, all of whose joints are
    hinges or slides. The data (``qpos``, body and geom poses) must be posed, its kinematics
    done, with the arm anywhere: only the poses that the arm's joints do not move are read."""
    n = waypoints.shape[0]
    proven = np.zeros(n, np.bool_)
    ngeom = geom_bodyid.shape[0]
    vols = np.empty((ngeom, _VOLUME))
    moving_geom = np.zeros(ngeom, np.bool_)
    for g in range(ngeom):
        moving_geom[g] = moving[geom_bodyid[g]]
    # The pairs that no waypoint changes, from the data's poses.
    nmoving = 0
    for row in range(pairs.shape[0]):
        g1, g2, kind = pairs[row, 0], pairs[row, 1], pairs[row, 2]
        if kind == MOVING:
            nmoving += 1
            continue
        if kind == FIXED and _spheres_apart(g1, g2, geom_rbound, geom_xpos, margin):
            continue
        _volume(g1, geom_type, geom_size, geom_aabb, geom_xpos, geom_xmat, vols)
        _volume(g2, geom_type, geom_size, geom_aabb, geom_xpos, geom_xmat, vols)
        if kind == FIXED:
            if not _apart(vols, g1, g2, margin):
                return proven
        else:  # TURNING: flush along the turning geom's axis at most
            t = g1 if moving_geom[g1] else g2
            if not (
                _unit_gap(vols, g1, g2, vols[t, 5], vols[t, 8], vols[t, 11]) >= -touch
                or _apart(vols, g1, g2, margin)
            ):
                return proven
    moving_pairs = np.empty((nmoving, 2), np.int64)
    nmoving = 0
    for row in range(pairs.shape[0]):
        if pairs[row, 2] == MOVING:
            moving_pairs[nmoving, 0], moving_pairs[nmoving, 1] = pairs[row, 0], pairs[row, 1]
            nmoving += 1
    # The fixed geoms' volumes once; the moving ones' at each waypoint, where needed.
    bounded_at = np.full(ngeom, -1, np.int64)
    local = np.empty((ngeom, 9))
    for g in range(ngeom):
        if moving_geom[g]:
            _quat_to_mat_row(geom_quat, g, local, g)
        else:
            _volume(g, geom_type, geom_size, geom_aabb, geom_xpos, geom_xmat, vols)
    qv = qpos.copy()
    bx, bq, bm = xpos.copy(), xquat.copy(), xmat.copy()
    gx, gm = geom_xpos.copy(), geom_xmat.copy()
    tq, tm = np.empty((2, 4)), np.empty((1, 9))
    for k in range(n):
        for i in range(arm_qadr.shape[0]):
            qv[arm_qadr[i]] = waypoints[k, i]
        _pose_bodies(
            moving,
            qv,
            qpos0,
            body_parentid,
            body_jntnum,
            body_jntadr,
            body_pos,
            body_quat,
            jnt_type,
            jnt_qposadr,
            jnt_pos,
            jnt_axis,
            bx,
            bq,
            bm,
            tq,
            tm,
        )
        for g in range(ngeom):
            if not moving_geom[g]:
                continue
            body = geom_bodyid[g]
            x, y, z = _rotate(bm, body, geom_pos, g)
            gx[g, 0] = bx[body, 0] + x
            gx[g, 1] = bx[body, 1] + y
            gx[g, 2] = bx[body, 2] + z
            for r in range(3):
                for c in range(3):
                    gm[g, 3 * r + c] = (
                        bm[body, 3 * r] * local[g, c]
                        + bm[body, 3 * r + 1] * local[g, 3 + c]
                        + bm[body, 3 * r + 2] * local[g, 6 + c]
                    )
        free = True
        for row in range(nmoving):
            g1, g2 = moving_pairs[row, 0], moving_pairs[row, 1]
            if _spheres_apart(g1, g2, geom_rbound, gx, margin):
                continue
            if moving_geom[g1] and bounded_at[g1] != k:
                _volume(g1, geom_type, geom_size, geom_aabb, gx, gm, vols)
                bounded_at[g1] = k
            if moving_geom[g2] and bounded_at[g2] != k:
                _volume(g2, geom_type, geom_size, geom_aabb, gx, gm, vols)
                bounded_at[g2] = k
            if not _apart(vols, g1, g2, margin):
                free = False
                break
        proven[k] = free
    return proven


class PathProof:
    """:func:`proven_free` for one collision scene: a model holding the arm, its data, the
    arm's qpos addresses there and which geoms are the arm's.

    The pair table is made again whenever a geom's ``contype`` or ``conaffinity``, the
    parent filter or MuJoCo's contact-filter callback changes; the model's other arrays are
    read at every call. Where the table holds a geom without a bound (a plane, height field
    or SDF) or the arm moves a body by a ball or free joint, nothing is proven.
    """

    def __init__(self, model, data, qpos_addresses, is_arm_geom) -> None:
        m = self.model = model
        self.data = data
        self.qpos_addresses = np.asarray(qpos_addresses, dtype=np.int64)
        self.is_arm_geom = np.ascontiguousarray(is_arm_geom, dtype=np.bool_)
        self.moving = moving_bodies(
            self.qpos_addresses, m.body_parentid, m.body_jntnum, m.body_jntadr, m.jnt_qposadr, m.nq
        )
        joints = np.concatenate(
            [
                np.arange(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
                for b in np.flatnonzero(self.moving)
            ]
            + [np.zeros(0, dtype=int)]
        )
        self.joints_bounded = bool(np.isin(m.jnt_type[joints], (_HINGE, _SLIDE)).all())
        self._key = None
        self._pairs = None
        self.model_arrays = (
            m.body_parentid,
            m.body_jntnum,
            m.body_jntadr,
            m.body_pos,
            m.body_quat,
            m.jnt_type,
            m.jnt_qposadr,
            m.jnt_pos,
            m.jnt_axis,
            m.qpos0,
            m.geom_bodyid,
            m.geom_type,
            m.geom_size,
            m.geom_pos,
            m.geom_quat,
            m.geom_aabb,
            m.geom_rbound,
        )
        self.data_arrays = (
            data.qpos,
            data.xpos,
            data.xquat,
            data.xmat,
            data.geom_xpos,
            data.geom_xmat,
        )

    def pairs(self, use_bitmask: bool, filter_parent: bool) -> np.ndarray | None:
        """:func:`candidate_pairs` now, or None where one of them has no bound."""
        m = self.model
        key = (m.geom_contype.tobytes(), m.geom_conaffinity.tobytes(), use_bitmask, filter_parent)
        if key != self._key:
            pairs = candidate_pairs(
                self.moving,
                self.is_arm_geom,
                use_bitmask,
                filter_parent,
                m.body_parentid,
                m.body_weldid,
                m.body_jntnum,
                m.body_jntadr,
                m.jnt_type,
                m.jnt_pos,
                m.jnt_axis,
                m.geom_bodyid,
                m.geom_type,
                m.geom_pos,
                m.geom_quat,
                m.geom_contype,
                m.geom_conaffinity,
                m.exclude_signature,
                m.pair_geom1,
                m.pair_geom2,
            )
            bounded = np.isin(m.geom_type[pairs[:, :2]], _BOUNDED_TYPES).all()
            self._pairs = pairs if bounded and self.joints_bounded else None
            self._key = key
        return self._pairs

    def unproven(
        self,
        waypoints: np.ndarray,
        margin: float,
        touch: float,
        use_bitmask: bool,
        filter_parent: bool,
    ) -> list[int]:
        """The indices of the ``waypoints`` (rows of the arm's joints) not proven free, the
        data posed (kinematics done) with the world as along the path."""
        pairs = self.pairs(use_bitmask, filter_parent)
        if pairs is None:
            return list(range(len(waypoints)))
        proven = proven_free(
            waypoints,
            self.qpos_addresses,
            pairs,
            self.moving,
            margin,
            touch,
            *self.model_arrays,
            *self.data_arrays,
        )
        return np.flatnonzero(~proven).tolist()
