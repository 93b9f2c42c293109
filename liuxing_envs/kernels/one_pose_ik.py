"""The closed-form IK of one flange pose, ordered nearest first: ``ur_ik.solutions_of_one``
followed by ``ArmIK.nearest_first_of_few`` (a controller's target, once per control step),
with the same results bit for bit; and the whole ``ee_delta`` set-point around it.

The reference runs on Python floats with the ``math`` module, which calls the C library's
``sin``, ``cos``, ``acos``, ``asin``, ``atan2`` and ``sqrt``; numba's scalar ``math`` calls
the same functions, and its ``+ - * /`` round as Python's do (no ``fastmath``: nothing is
reassociated or fused into multiply-adds). The one numpy call of the reference,
``np.hypot`` of two scalars, is the C library's ``hypot`` too, which ``math.hypot`` in numba
calls (Python's own ``math.hypot`` is not). So every operation below is spelled in the
reference's order and grouping; its comparisons, ``min``/``max`` (which keep their first
argument on a tie or a NaN) and whole-turn rounding (``round`` of a float, half to even, as
``np.rint``) likewise.

The set-point (``EndEffectorDeltaController.set_point``) first makes the tool pose an action
asks for: numpy's ``np.minimum`` and ``np.maximum`` keep their first argument on a tie (the
workspace bounds are never zero, so a tie is of two equal numbers), and ``%`` of two floats
follows Python's sign rule in numba as in numpy. The flange pose is two 4x4 products that
numpy hands to BLAS, whose order of sums no plain loop reproduces: :func:`ee_delta_set_point`
calls that same BLAS function at its address (:func:`liuxing_envs.kernels.numpy_dgemm`), and
where it is not found the caller makes the products with numpy between
:func:`tool_target_pose` and :func:`one_pose_nearest`. ``tests/test_grasp_kernels.py`` holds
each equal to its reference.

A solution's row among a pose's eight is ``4 * shoulder + 2 * wrist + elbow``, as in
``ur_ik``; the kernel returns the kept solutions nearest first (a stable sort of their
squared joint-space distances, as ``list.sort``).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from liuxing_envs.kernels import jit_options
from liuxing_envs.sim import ur_ik

#: The constants of ``solutions_of_one``'s arithmetic, as its Python expressions compute them
#: (the kernel takes them as an argument: numba would freeze module globals into its cache).
CONSTANTS = np.array(
    [
        ur_ik._D1F,
        ur_ik._D4F,
        ur_ik._D5F,
        ur_ik._D6F,
        ur_ik._A3F,
        ur_ik._A2F**2,
        ur_ik._A3F**2,
        2 * ur_ik._A2F * ur_ik._A3F,
        ur_ik.COS_SLACK,
        ur_ik._SINGULAR,
        float(ur_ik._TWO_PI),
        math.pi,
        math.pi / 2,
    ],
    dtype=np.float64,
)
_D1, _D4, _D5, _D6, _A3, _A2SQ, _A3SQ, _DEN, _SLACK, _SINGULAR, _TWO_PI, _PI, _HALF_PI = range(13)


@njit(**jit_options())
def _min(a, b):
    """Python's ``min(a, b)`` of two floats: ``a`` unless ``b < a``."""
    return b if b < a else a


@njit(**jit_options())
def _max(a, b):
    """Python's ``max(a, b)`` of two floats: ``a`` unless ``b > a``."""
    return b if b > a else a


@njit(**jit_options())
def _wrapped(angle, consts):
    """``solutions_of_one``'s wrap to (-pi, pi] by whole turns, where it is outside."""
    pi = consts[_PI]
    if -pi <= angle <= pi:
        return angle
    two_pi = consts[_TWO_PI]
    return angle - two_pi * np.rint(angle / two_pi)


@njit(**jit_options())
def _solutions(pose, consts, solutions, rows):
    """``solutions_of_one(pose)``: its solutions in row order into ``solutions`` (8, 6) and
    their rows into ``rows`` (8,); their count."""
    count = 0
    for i in range(4):
        for j in range(4):
            if not math.isfinite(pose[i, j]):
                return 0
    x0, y0, z0, px = pose[0, 0], pose[0, 1], pose[0, 2], pose[0, 3]
    x1, y1, z1, py = pose[1, 0], pose[1, 1], pose[1, 2], pose[1, 3]
    x2, y2, z2, pz = pose[2, 0], pose[2, 1], pose[2, 2], pose[2, 3]
    d1, d4, d5, d6 = consts[_D1], consts[_D4], consts[_D5], consts[_D6]
    a3, slack, singular = consts[_A3], consts[_SLACK], consts[_SINGULAR]
    x05, y05 = px - d6 * z0, py - d6 * z1
    radius = math.hypot(x05, y05)
    if not radius > 0.0 or not d4 / radius <= 1.0:
        return 0
    phi1, phi2 = math.atan2(y05, x05), math.acos(d4 / radius)
    for shoulder_index in range(2):
        shoulder = 1.0 if shoulder_index == 0 else -1.0
        theta1 = phi1 + shoulder * phi2 + consts[_HALF_PI]
        s1, c1 = math.sin(theta1), math.cos(theta1)
        cos5 = (px * s1 - py * c1 - d4) / d6
        if abs(cos5) > 1.0 + slack:
            continue
        base5 = math.acos(_min(_max(cos5, -1.0), 1.0))
        c5 = math.cos(base5)
        x_on_z1, y_on_z1 = x0 * s1 - x1 * c1, y0 * s1 - y1 * c1
        for wrist_index in range(2):
            wrist = 1.0 if wrist_index == 0 else -1.0
            theta5 = base5 * wrist
            s5 = math.sin(theta5)
            if abs(s5) < singular:
                continue
            theta6 = math.atan2(-y_on_z1 / s5, x_on_z1 / s5)
            s6, c6 = math.sin(theta6), math.cos(theta6)
            u0 = s6 * d5 - c6 * s5 * d4
            u1 = c6 * d5 + s6 * s5 * d4
            u2 = -d6 - c5 * d4
            v0, v1, v2 = c6 * c5, -s6 * c5, -s5
            b0 = u0 * x0 + u1 * y0 + u2 * z0 + px
            b1 = u0 * x1 + u1 * y1 + u2 * z1 + py
            b2 = u0 * x2 + u1 * y2 + u2 * z2 + (pz - d1)
            column_x = c1 * (v0 * x0 + v1 * y0 + v2 * z0) + s1 * (v0 * x1 + v1 * y1 + v2 * z1)
            column_y = v0 * x2 + v1 * y2 + v2 * z2
            reach = b0 * b0 + b1 * b1 + b2 * b2
            cos3 = (reach - consts[_A2SQ] - consts[_A3SQ]) / consts[_DEN]
            if not -1.0 - slack <= cos3 <= 1.0 + slack:
                continue
            cos3 = _min(_max(cos3, -1.0), 1.0)
            base3, shoulder_to_wrist = math.acos(cos3), math.sqrt(reach)
            offset = math.atan2(b2, -(c1 * b0 + s1 * b1))
            column = math.atan2(column_y, column_x)
            for elbow_index in range(2):
                row = 4 * shoulder_index + 2 * wrist_index + elbow_index
                elbow = 1.0 if elbow_index == 0 else -1.0
                theta3 = base3 * elbow
                sin2 = a3 * math.sin(theta3) / shoulder_to_wrist
                if not -1.0 <= sin2 <= 1.0:
                    continue
                theta2 = math.asin(sin2) - offset
                theta4 = column - theta2 - theta3
                solutions[count, 0] = _wrapped(theta1, consts)
                solutions[count, 1] = _wrapped(theta2, consts)
                solutions[count, 2] = _wrapped(theta3, consts)
                solutions[count, 3] = _wrapped(theta4, consts)
                solutions[count, 4] = _wrapped(theta5, consts)
                solutions[count, 5] = _wrapped(theta6, consts)
                rows[count] = row
                count += 1
    return count


@njit(**jit_options())
def one_pose_nearest(pose, reference, lower, upper, limit_slack, consts):
    """``nearest_first_of_few(solutions_of_one(pose), reference)`` as a (k, 6) array, nearest
    first: ``lower`` and ``upper`` are the joint limits, ``limit_slack`` how far past them a
    solution may land and be clipped back (``IK_LIMIT_SLACK``); ``consts``:
    :data:`CONSTANTS`."""
    solutions = np.empty((8, 6))
    count = _solutions(pose, consts, solutions, np.empty(8, dtype=np.int64))
    pi, two_pi = consts[_PI], consts[_TWO_PI]
    kept = np.empty((8, 6))
    distances = np.empty(8)
    n_kept = 0
    for s in range(count):
        distance2 = 0.0
        inside = True
        for j in range(6):
            angle = solutions[s, j]
            near = reference[j]
            low, high = lower[j], upper[j]
            slack_low, slack_high = low - limit_slack, high + limit_slack
            gap = near - angle
            if -pi <= gap <= pi:
                shifted = angle + 0.0  # as angle + 2 pi * 0 (a -0.0 becomes 0.0)
            else:
                shifted = angle + two_pi * np.rint(gap / two_pi)
            if slack_low <= shifted <= slack_high:
                angle = shifted
            elif not slack_low <= angle <= slack_high:
                inside = False
                break
            if not low <= angle <= high:
                angle = _min(_max(angle, low), high)
            kept[n_kept, j] = angle
            distance2 += (angle - near) * (angle - near)
        if inside:
            distances[n_kept] = distance2
            n_kept += 1
    # A stable insertion sort on the distances, as list.sort by key: a later solution moves
    # ahead of an earlier one only where its distance is strictly smaller.
    order = np.empty(n_kept, dtype=np.int64)
    for i in range(n_kept):
        position = i
        while position > 0 and distances[i] < distances[order[position - 1]]:
            order[position] = order[position - 1]
            position -= 1
        order[position] = i
    ordered = np.empty((n_kept, 6))
    for i in range(n_kept):
        for j in range(6):
            ordered[i, j] = kept[order[i], j]
    return ordered


@njit(**jit_options())
def solutions_of_one(pose, consts):
    """``ur_ik.solutions_of_one(pose)`` as its rows (n,) and joint angles (n, 6), in row
    order (for tests)."""
    solutions = np.empty((8, 6))
    rows = np.empty(8, dtype=np.int64)
    count = _solutions(pose, consts, solutions, rows)
    return rows[:count].copy(), solutions[:count].copy()


@njit(**jit_options())
def _clipped(value, low, high):
    """``np.minimum(np.maximum(value, low), high)`` of floats (a NaN passes through)."""
    if value != value:
        return value
    raised = value if value >= low else low
    return raised if raised <= high else high


@njit(**jit_options())
def tool_target_pose(
    site_xpos, site_xmat, site, arm_action, max_translation, max_yaw, scale, lower, upper
):
    """The 4x4 pose of site ``site`` (row of ``site_xpos`` and ``site_xmat``) that the
    ``ee_delta`` action ``arm_action`` (4 floats in [-1, 1]) asks for: its translation, times
    ``max_translation`` m, from where the site is, clipped to ``lower`` and ``upper``; its yaw,
    times ``max_yaw`` rad, from the site's x axis about world z, wrapped to [-pi, pi); both
    moves times ``scale`` (from a zero action's target); the tool pointing down."""
    pi = math.pi
    target = np.empty(3)
    for i in range(3):
        target[i] = _clipped(
            site_xpos[site, i] + max_translation * arm_action[i], lower[i], upper[i]
        )
    yaw_change = max_yaw * arm_action[3]
    if scale != 1.0:
        for i in range(3):
            start = _clipped(site_xpos[site, i], lower[i], upper[i])
            target[i] = start + scale * (target[i] - start)
        yaw_change *= scale
    yaw = math.atan2(site_xmat[site, 3], site_xmat[site, 0]) + yaw_change
    yaw = (yaw + pi) % (2 * pi) - pi
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.zeros((4, 4))
    pose[0, 0], pose[0, 1] = c, s
    pose[1, 0], pose[1, 1] = s, -c
    pose[2, 2] = -1.0
    for i in range(3):
        pose[i, 3] = target[i]
    pose[3, 3] = 1.0
    return pose


@intrinsic
def _dgemm(typingctx, address, a, b, product):
    """``product = a @ b`` of C-contiguous 4x4 float64 matrices by the ``cblas_dgemm`` at
    ``address``, called with the arguments numpy's ``matmul`` passes. The arrays themselves
    are the arguments (not their data pointers), so they live through the call."""
    for array in (a, b, product):
        if not (isinstance(array, types.Array) and array.dtype == types.float64):
            return None
        if array.ndim != 2 or array.layout != "C":
            return None
    signature = types.void(address, a, b, product)

    def codegen(context, builder, signature, args):
        int32, int64, double = ir.IntType(32), ir.IntType(64), ir.DoubleType()
        pointer = ir.IntType(8).as_pointer()
        function_type = ir.FunctionType(
            ir.VoidType(),
            [int32, int32, int32, int64, int64, int64, double, pointer, int64]
            + [pointer, int64, double, pointer, int64],
        )
        function = builder.inttoptr(args[0], function_type.as_pointer())
        row_major, no_trans = ir.Constant(int32, 101), ir.Constant(int32, 111)
        four, one, zero = ir.Constant(int64, 4), ir.Constant(double, 1.0), ir.Constant(double, 0.0)
        a_data, b_data, product_data = (
            builder.bitcast(context.make_array(kind)(context, builder, value).data, pointer)
            for kind, value in zip(signature.args[1:], args[1:], strict=True)
        )
        builder.call(
            function,
            [row_major, no_trans, no_trans, four, four, four, one, a_data, four]
            + [b_data, four, zero, product_data, four],
        )
        return context.get_dummy_value()

    return signature, codegen


@njit(**jit_options())
def ee_delta_set_point(
    site_xpos, site_xmat, site, arm_action, max_translation, max_yaw, scale, workspace_lower,
    workspace_upper, base_inverse, flange_in_site, dgemm, reference, lower, upper, limit_slack,
    consts, max_jump,
):  # fmt: skip
    """``EndEffectorDeltaController.set_point`` in one call: the pose of
    :func:`tool_target_pose`, the flange's pose in the arm base
    (``base_inverse @ pose @ flange_in_site``, both C-contiguous, by the ``cblas_dgemm`` at
    ``dgemm``), then the first of :func:`one_pose_nearest` if no joint moves more than
    ``max_jump`` from ``reference``: its 6 joint angles, or an empty array where it is refused
    or there is none."""
    pose = tool_target_pose(
        site_xpos, site_xmat, site, arm_action, max_translation, max_yaw, scale,
        workspace_lower, workspace_upper,
    )  # fmt: skip
    first, flange = np.empty((4, 4)), np.empty((4, 4))
    _dgemm(dgemm, base_inverse, pose, first)
    _dgemm(dgemm, first, flange_in_site, flange)
    ordered = one_pose_nearest(flange, reference, lower, upper, limit_slack, consts)
    if ordered.shape[0] == 0:
        return np.empty(0)
    for j in range(6):
        jump = abs(ordered[0, j] - reference[j])
        if not jump <= max_jump:  # as np.abs(...).max() <= max_jump: a NaN refuses too
            return np.empty(0)
    return ordered[0].copy()
