"""MuJoCo's errors for kernels that call MuJoCo's C functions at their addresses.

A MuJoCo error (``mju_error``: a full stack, say) goes to the log handler, and MuJoCo's
default handler ends the process. The Python bindings install, around each of their calls, a
thread-local handler that jumps back out of the call, and raise the message as
``mujoco.FatalError``. A kernel does the same with :func:`error_trap`'s handler: installed
with ``set_handler`` around its calls, it copies an error's subject and function into
``message`` and ``function`` and ``longjmp``\\ s to the ``setjmp`` the kernel made on
``jump_buffer``; other messages (warnings) go on to the global handler, as from the
bindings' calls.

The buffers are one per process: :attr:`ErrorTrap.lock` gives them to one thread's kernel at
a time. A kernel does not run where a MuJoCo hook (:data:`HOOKS`) is set, since user code
would then run inside it. The handler is a few LLVM instructions built in each process (a
few milliseconds), not a cached kernel: it holds this process's buffer addresses. Where the
pieces are missing (no C library ``_setjmp``, a MuJoCo without the thread-local handler
setter), :func:`error_trap` is None and callers keep the bindings' calls.
"""

from __future__ import annotations

import ctypes
import functools
import threading
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

#: ``mjtLogLevel``'s error level; where ``mjLogMessage`` holds its subject (after two ints),
#: how long that is, and where its ``func`` pointer follows the subject and ``body``.
_LOG_ERROR, _SUBJECT_OFFSET, _SUBJECT_SIZE, _FUNCTION_OFFSET = 3, 8, 1024, 1040
#: MuJoCo's hooks that a user (the Python bindings' ``set_mjcb_*`` and ``set_mju_user_*``)
#: can point at code of their own, which a kernel must not run: a Python callback could run
#: the kernel again, and its exceptions need the bindings' handling.
HOOKS = (
    "mjcb_passive", "mjcb_control", "mjcb_contactfilter", "mjcb_sensor", "mjcb_time",
    "mjcb_act_dyn", "mjcb_act_gain", "mjcb_act_bias", "mju_user_warning", "mju_user_malloc",
    "mju_user_free",
)  # fmt: skip
#: Bytes kept for a jump buffer (glibc's ``jmp_buf`` is 200 on x86-64, 312 on aarch64).
_JUMP_BUFFER_BYTES = 1024
_HANDLER_NAME = "liuxing_mujoco_error_trap"


class ErrorTrap(NamedTuple):
    """This process's handler and its buffers (see the module)."""

    #: Address of MuJoCo's ``_mjPRIVATE_setTlsLogHandler``.
    set_handler: int
    #: Address of the handler.
    handler: int
    #: The ``setjmp`` buffer (its address is in the handler).
    jump_buffer: np.ndarray
    #: An error's subject, NUL-terminated.
    message: np.ndarray
    #: An error's ``func`` (the address of a static string, or 0).
    function: np.ndarray
    #: Per MuJoCo hook (:data:`HOOKS`): its address, and the value it holds when no user
    #: code is set (NULL, or the bindings' own C function: MuJoCo's timer, say).
    hooks: np.ndarray
    #: Held by the thread whose kernel uses the buffers (one at a time: the others call
    #: MuJoCo through the bindings meanwhile).
    lock: threading.Lock
    #: The compiled handler's owner (kept alive with the trap).
    engine: object

    def error(self) -> mujoco.FatalError:
        """The trapped error, with the text the bindings give it."""
        text = self.message.tobytes().split(b"\0", 1)[0].decode("utf-8", "replace")
        function = int(self.function[0])
        if function:
            text = f"{ctypes.string_at(function).decode('utf-8', 'replace')}: {text}"
        return mujoco.FatalError(text)


@functools.cache
def mujoco_library() -> ctypes.CDLL | None:
    """The MuJoCo library the bindings loaded (None where it is not found)."""
    for path in sorted(Path(mujoco.__file__).parent.glob("*mujoco*.so*")):
        if path.name.startswith("libmujoco"):
            try:
                return ctypes.CDLL(str(path))
            except OSError:
                return None
    return None


def function_address(name: str) -> int | None:
    """The address of MuJoCo's C function ``name`` (None where it is not found)."""
    library = mujoco_library()
    function = getattr(library, name, None) if library is not None else None
    return None if function is None else ctypes.cast(function, ctypes.c_void_p).value


@functools.cache
def error_trap() -> ErrorTrap | None:
    """This process's :class:`ErrorTrap` (built on first use), or None where the pieces are
    missing."""
    set_handler = function_address("_mjPRIVATE_setTlsLogHandler")
    global_handler = function_address("_mjPRIVATE_getGlobalLogHandler")
    if set_handler is None or global_handler is None:
        return None
    try:
        process = ctypes.CDLL(None)  # the symbols the process has loaded, the C library's too
    except (OSError, TypeError):  # no such handle (Windows)
        return None
    if not all(hasattr(process, name) for name in ("_setjmp", "longjmp", "memcpy")):
        return None
    hooks = [mujoco_library_variable(name) for name in HOOKS]
    if None in hooks:
        return None
    # A hook whose bindings' getter answers None holds no user code: its value then is the
    # one to expect. One that holds user code now counts as set until the process ends.
    unset = [
        ctypes.c_void_p.from_address(address).value or 0
        if getattr(mujoco, f"get_{name}", lambda: None)() is None
        else 0
        for name, address in zip(HOOKS, hooks, strict=True)
    ]
    jump_buffer = np.zeros(_JUMP_BUFFER_BYTES, dtype=np.uint8)
    message = np.zeros(_SUBJECT_SIZE, dtype=np.uint8)
    function = np.zeros(1, dtype=np.uint64)
    engine, handler = _compile_handler(
        jump_buffer.ctypes.data, message.ctypes.data, function.ctypes.data, global_handler
    )
    return ErrorTrap(
        set_handler, handler, jump_buffer, message, function,
        np.array([hooks, unset], dtype=np.int64).T.copy(),
        threading.Lock(), engine,
    )  # fmt: skip


def mujoco_library_variable(name: str) -> int | None:
    """The address of MuJoCo's global variable ``name`` (None where it is not found)."""
    library = mujoco_library()
    try:
        return ctypes.addressof(ctypes.c_void_p.in_dll(library, name))
    except (ValueError, TypeError):
        return None


def _compile_handler(
    jump_address: int, message_address: int, function_address_: int, global_handler: int
):
    """``void handler(const mjLogMessage*)``: an error's subject into ``message_address``, its
    ``func`` into ``function_address_``, and ``longjmp(jump_address, 1)``; anything else to
    the global handler."""
    import llvmlite.binding as llvm
    from llvmlite import ir

    byte, int32, int64 = ir.IntType(8), ir.IntType(32), ir.IntType(64)
    pointer = byte.as_pointer()
    module = ir.Module(_HANDLER_NAME)
    handler_type = ir.FunctionType(ir.VoidType(), [pointer])
    handler = ir.Function(module, handler_type, _HANDLER_NAME)
    long_jump = ir.Function(module, ir.FunctionType(ir.VoidType(), [pointer, int32]), "longjmp")
    long_jump.attributes.add("noreturn")
    copy = ir.Function(module, ir.FunctionType(pointer, [pointer, pointer, int64]), "memcpy")
    entry, error, forward = (handler.append_basic_block(name) for name in ("entry", "e", "f"))

    builder = ir.IRBuilder(entry)
    message = handler.args[0]
    level = builder.load(builder.bitcast(message, int32.as_pointer()))
    builder.cbranch(
        builder.icmp_signed("==", level, ir.Constant(int32, _LOG_ERROR)), error, forward
    )

    builder = ir.IRBuilder(error)
    subject = builder.gep(message, [ir.Constant(int64, _SUBJECT_OFFSET)])
    target = builder.inttoptr(ir.Constant(int64, message_address), pointer)
    builder.call(copy, [target, subject, ir.Constant(int64, _SUBJECT_SIZE - 1)])
    function_slot = builder.gep(message, [ir.Constant(int64, _FUNCTION_OFFSET)])
    function = builder.load(builder.bitcast(function_slot, int64.as_pointer()))
    builder.store(
        function, builder.inttoptr(ir.Constant(int64, function_address_), int64.as_pointer())
    )
    builder.call(long_jump, [builder.inttoptr(ir.Constant(int64, jump_address), pointer),
                             ir.Constant(int32, 1)])  # fmt: skip
    builder.unreachable()

    builder = ir.IRBuilder(forward)
    getter_type = ir.FunctionType(handler_type.as_pointer(), [])
    getter = builder.inttoptr(ir.Constant(int64, global_handler), getter_type.as_pointer())
    builder.call(builder.call(getter, []), [message])
    builder.ret_void()

    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    machine = llvm.Target.from_default_triple().create_target_machine()
    compiled = llvm.parse_assembly(str(module))
    compiled.verify()
    engine = llvm.create_mcjit_compiler(compiled, machine)
    engine.finalize_object()
    return engine, engine.get_function_address(_HANDLER_NAME)
