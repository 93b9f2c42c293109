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
prints them as the bindings' calls do. The jump buffer is one per process, so this kernel
holds the GIL (no ``nogil``): no two threads are inside it at once.
"""

from __future__ import annotations

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from liuxing_envs.kernels import jit_options

#: Entries of the ``layout`` argument (int64): function and buffer addresses, then ids.
MJ_STEP, SET_HANDLER, HANDLER, JUMP_BUFFER, MODEL, DATA = range(6)
LEFT_TOUCH, RIGHT_TOUCH, TREE, NOSLIP_WHEN_TOUCHING = range(6, 10)
LAYOUT_SIZE = 10
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
#: a MuJoCo error in the sample's physics (its message is in the error handler's buffer).
FAILED = 4

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


@njit(**{**jit_options(), "nogil": False})
def sleeping_samples(layout, samples, start, noslip, sensordata, tree_asleep, peaks, limits):
    """Run the force samples from ``start``: per sample, its ``samples[k]`` physics steps,
    then the pad forces into ``peaks`` (float64: left, right, impact; updated in place).

    Returns ``(status, k)``: one of the module's status codes and the sample it stopped at
    (``len(samples)`` when DONE). ``noslip``: the model's current noslip iterations."""
    model, data = layout[MODEL], layout[DATA]
    left_touch, right_touch = layout[LEFT_TOUCH], layout[RIGHT_TOUCH]
    previous = _swap_handler(layout[SET_HANDLER], layout[HANDLER])
    # When this returns a second time (the error handler's jump), only values set before it
    # are read: a local changed after setjmp is indeterminate after the jump.
    if _set_jump(layout[JUMP_BUFFER]) != 0:
        _swap_handler(layout[SET_HANDLER], previous)
        return FAILED, start
    sample = start
    while sample < samples.shape[0]:
        left, right = sensordata[left_touch], sensordata[right_touch]
        # As ``max(left, right) > 0.0`` on Python floats (a NaN on the left stays).
        touching = (right if right > left else left) > 0.0
        wanted = layout[NOSLIP_WHEN_TOUCHING] if touching else 0
        if wanted != noslip:
            _swap_handler(layout[SET_HANDLER], previous)
            return NOSLIP, sample
        for _ in range(samples[sample]):
            _call_model_data(layout[MJ_STEP], model, data)
        left, right = sensordata[left_touch], sensordata[right_touch]
        if tree_asleep[layout[TREE]] < 0:
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
    return DONE, sample
