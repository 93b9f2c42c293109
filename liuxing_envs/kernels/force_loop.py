"""The force monitor's loop in one call: a control step's physics steps (MuJoCo's ``mj_step``,
called at its address) and the pad-force samples between them, for as long as the
instrument sleeps on the tray; its caller takes over, in ``ForceMonitor``'s own Python, at
the first sample that needs more (the instrument awake, a change of the noslip setting, a
protective stop), so the step's physics and figures are the reference's bit for bit.

A MuJoCo error inside ``mj_step`` (a full arena or stack, say) does not end the process, as
it would if MuJoCo's default handler met it: the kernel installs, around its calls, the
thread-local log handler of :mod:`liuxing_envs.sim.mujoco_errors` (what the Python
bindings do around theirs), which copies an error's message and jumps back to the
``setjmp`` here; the kernel then returns :data:`FAILED` and its caller raises the message as
``mujoco.FatalError``, as the bindings do. Warnings pass on to the global handler, which
prints them as the bindings' calls do. The handler's buffers are one per process: the caller
holds the handler's lock around the call (another thread meanwhile steps through the
bindings), and the kernel does nothing where a MuJoCo hook holds user code, which would
run inside it (a Python callback could run the kernel again, or raise where only the
bindings know how to pass the exception on).
"""

from __future__ import annotations

import math

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from liuxing_envs.kernels import jit_options

#: Entries of the ``layout`` argument (int64): function and buffer addresses; the addresses
#: of ``mjData``'s arrays that the kernel reads (``sensordata``, ``tree_asleep``, ``qpos``,
#: ``qvel``, and the first warning's ``number``, whose entries lie WARNING_STRIDE bytes
#: apart); ids and sizes.
MJ_STEP, SET_HANDLER, HANDLER, JUMP_BUFFER, MODEL, DATA = range(6)
SENSORDATA, TREE_ASLEEP, QPOS, QVEL, WARNING_NUMBERS, WARNING_STRIDE = range(6, 12)
LEFT_TOUCH, RIGHT_TOUCH, TREE, NOSLIP_WHEN_TOUCHING, NQ, NV = range(12, 18)
#: Where MuJoCo's hooks (function pointers users may set) are listed, and how many: pairs of
#: int64, each hook's address and the value it holds when no user code is set.
HOOKS, HOOK_COUNT = 18, 19
#: ``layout[DIVERGENCE_WARNINGS:]``: the warnings that count a divergence (MuJoCo's bad
#: qpos, qvel and qacc).
DIVERGENCE_WARNINGS = 20
LAYOUT_SIZE = 23
#: Entries of the ``divergence`` argument (int64, written): the divergence warnings counted
#: when the kernel started, and, when it returns DONE, its verdict on the step:
COUNT_AT_START, VERDICT = range(2)
#: not diverged, diverged, or undecided (a finite value over HUGE in ``qpos`` or ``qvel``,
#: whose sum may or may not overflow in numpy's order: the caller sums them).
STABLE, DIVERGED, UNDECIDED = range(3)
#: Below this size n finite values sum to a finite value in any order (n < 1e8).
HUGE = 1e300
#: Entries of the ``limits`` argument (float64): the hard limits of a pad and of an impact.
HARD_LIMIT, HARD_IMPACT_LIMIT = range(2)

#: What the kernel returns first, with the sample it stopped at: every sample is done;
DONE = 0
#: the sample's noslip setting must change before it steps (nothing of it is done);
NOSLIP = 1
#: the sample has stepped and the instrument is awake: its impact, peaks and limit check are
#: the caller's;
AWAKE = 2
#: the sample's peaks (updated) passed a hard limit: the protective stop is the caller's;
STOPPED = 3
#: a MuJoCo error in the physics (its message is in the error handler's buffer; the sample
#: returned is ``start``);
FAILED = 4
#: a MuJoCo hook is set (user code would run inside the kernel): nothing is done.
HOOKED = 5

_BYTE_POINTER = ir.IntType(8).as_pointer()


@intrinsic
def _set_jump(typingctx, buffer_address):
    """C's ``setjmp`` on the buffer at ``buffer_address``: 0, then again non-zero when a
    ``longjmp`` returns to it (declared ``returns_twice``, so LLVM keeps that path sound)."""

    def codegen(context, builder, signature, args):
        function_type = ir.FunctionType(ir.IntType(32), [_BYTE_POINTER])
        set_jump = cgutils.get_or_insert_function(builder.module, function_type, "_setjmp")
        set_jump.attributes.add("returns_twice")
        return builder.call(set_jump, [builder.inttoptr(args[0], _BYTE_POINTER)])

    return types.int32(types.int64), codegen


@intrinsic
def _swap_handler(typingctx, setter_address, handler_address):
    """``mjfLogHandler setter(mjfLogHandler)`` at ``setter_address``: installs a handler and
    returns the one it replaces."""

    def codegen(context, builder, signature, args):
        function_type = ir.FunctionType(_BYTE_POINTER, [_BYTE_POINTER])
        setter = builder.inttoptr(args[0], function_type.as_pointer())
        previous = builder.call(setter, [builder.inttoptr(args[1], _BYTE_POINTER)])
        return builder.ptrtoint(previous, ir.IntType(64))

    return types.int64(types.int64, types.int64), codegen


@intrinsic
def _call_model_data(typingctx, function_address, model_address, data_address):
    """``void function(const mjModel*, mjData*)`` at ``function_address`` (``mj_step``)."""

    def codegen(context, builder, signature, args):
        function_type = ir.FunctionType(ir.VoidType(), [_BYTE_POINTER, _BYTE_POINTER])
        function = builder.inttoptr(args[0], function_type.as_pointer())
        model, data = (builder.inttoptr(arg, _BYTE_POINTER) for arg in args[1:])
        builder.call(function, [model, data])
        return context.get_dummy_value()

    return types.void(types.int64, types.int64, types.int64), codegen


@intrinsic
def _load_float(typingctx, address):
    """The float64 at ``address``."""

    def codegen(context, builder, signature, args):
        pointer = builder.inttoptr(args[0], ir.DoubleType().as_pointer())
        return builder.load(pointer)

    return types.float64(types.int64), codegen


@intrinsic
def _load_int(typingctx, address):
    """The int32 at ``address``."""

    def codegen(context, builder, signature, args):
        pointer = builder.inttoptr(args[0], ir.IntType(32).as_pointer())
        return builder.load(pointer)

    return types.int32(types.int64), codegen


@intrinsic
def _load_address(typingctx, address):
    """The int64 (a pointer) at ``address``."""

    def codegen(context, builder, signature, args):
        return builder.load(builder.inttoptr(args[0], ir.IntType(64).as_pointer()))

    return types.int64(types.int64), codegen


@njit(**jit_options())
def _hooked(layout):
    """Whether any of MuJoCo's hooks holds user code."""
    for k in range(layout[HOOK_COUNT]):
        entry = layout[HOOKS] + 16 * k
        if _load_address(_load_address(entry)) != _load_address(entry + 8):
            return True
    return False


@njit(**jit_options())
def _divergences(layout):
    """How many times MuJoCo has counted a divergence warning (as ``divergence_count``)."""
    count = 0
    for k in range(DIVERGENCE_WARNINGS, LAYOUT_SIZE):
        count += _load_int(layout[WARNING_NUMBERS] + layout[WARNING_STRIDE] * layout[k])
    return count


@njit(**jit_options())
def _verdict(layout, count_at_start):
    """STABLE, DIVERGED or UNDECIDED (see the constants), as ``diverged_since`` would say."""
    if _divergences(layout) > count_at_start:
        return DIVERGED
    undecided = False
    for base, size in ((layout[QPOS], layout[NQ]), (layout[QVEL], layout[NV])):
        for i in range(size):
            value = _load_float(base + 8 * i)
            if not math.isfinite(value):
                return DIVERGED  # numpy's sum is NaN or infinite too
            if abs(value) > HUGE:
                undecided = True
    return UNDECIDED if undecided else STABLE


@njit(**jit_options())
def sleeping_samples(layout, samples, start, noslip, peaks, limits, divergence):
    """Run the force samples from ``start``: per sample, its ``samples[k]`` physics steps,
    then the pad forces into ``peaks`` (float64: left, right, impact; updated in place).

    Returns ``(status, k)``: one of the module's status codes and the sample it stopped at
    (``len(samples)`` when DONE). ``noslip``: the model's current noslip iterations.
    ``divergence`` (int64): see COUNT_AT_START (written when ``start`` is 0) and VERDICT.
    """
    if _hooked(layout):
        return HOOKED, start
    model, data = layout[MODEL], layout[DATA]
    left_touch = layout[SENSORDATA] + 8 * layout[LEFT_TOUCH]
    right_touch = layout[SENSORDATA] + 8 * layout[RIGHT_TOUCH]
    instrument_asleep = layout[TREE_ASLEEP] + 4 * layout[TREE]
    if start == 0:  # later calls of the same step go on from its earlier ones
        divergence[COUNT_AT_START] = _divergences(layout)
    previous = _swap_handler(layout[SET_HANDLER], layout[HANDLER])
    # When this returns a second time (the error handler's jump), only values set before it
    # are read: a local changed after setjmp is indeterminate after the jump.
    if _set_jump(layout[JUMP_BUFFER]) != 0:
        _swap_handler(layout[SET_HANDLER], previous)
        return FAILED, start
    sample = start
    while sample < samples.shape[0]:
        left, right = _load_float(left_touch), _load_float(right_touch)
        # As ``max(left, right) > 0.0`` on Python floats (a NaN on the left stays).
        touching = (right if right > left else left) > 0.0
        wanted = layout[NOSLIP_WHEN_TOUCHING] if touching else 0
        if wanted != noslip:
            _swap_handler(layout[SET_HANDLER], previous)
            return NOSLIP, sample
        for _ in range(samples[sample]):
            _call_model_data(layout[MJ_STEP], model, data)
        left, right = _load_float(left_touch), _load_float(right_touch)
        if _load_int(instrument_asleep) < 0:
            _swap_handler(layout[SET_HANDLER], previous)
            return AWAKE, sample
        # A sleeping instrument feels no impact (0.0, never a new peak).
        if left > peaks[0]:
            peaks[0] = left
        if right > peaks[1]:
            peaks[1] = right
        hard_limit = limits[HARD_LIMIT]
        if peaks[0] > hard_limit or peaks[1] > hard_limit or peaks[2] > limits[HARD_IMPACT_LIMIT]:
            _swap_handler(layout[SET_HANDLER], previous)
            return STOPPED, sample
        sample += 1
    _swap_handler(layout[SET_HANDLER], previous)
    divergence[VERDICT] = _verdict(layout, divergence[COUNT_AT_START])
    return DONE, sample
