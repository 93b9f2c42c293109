"""What every liuxing_envs env shares: its keyword interface checked by name, and its
``closed`` state (a closed env refuses ``step()`` until ``reset()`` reopens it, see
:func:`liuxing_envs.validation.refuse_if_closed`)."""

from __future__ import annotations

import functools
import inspect

import gymnasium as gym

from liuxing_envs.validation import closest


class LiuxingEnv(gym.Env):
    """Base of the suite's envs. Every setting is a keyword-only argument of ``__init__``;
    a name that is none of them is refused with the closest one and the full list (Python's
    own TypeError names neither), before anything is built."""

    closed = False

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if "__init__" not in cls.__dict__:
            return
        init = cls.__init__

        @functools.wraps(init)
        def checked_init(self, *args, **settings):
            accepted = cls.keyword_names()
            for name in settings:
                if name not in accepted:
                    raise TypeError(
                        f"{cls.__name__} has no keyword argument {name!r}"
                        f"{closest(name, accepted)}; allowed: {', '.join(accepted)}"
                    )
            init(self, *args, **settings)

        cls.__init__ = checked_init

    @classmethod
    def keyword_names(cls) -> tuple[str, ...]:
        """The settings ``__init__`` takes (``gym.make(id, **settings)``), in order."""
        parameters = inspect.signature(cls.__init__).parameters.values()
        return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)

    def close(self) -> None:
        """Marks the env closed: :meth:`step` is refused until ``reset()`` reopens it (each
        env's own ``close()`` frees its renderers, which a reset makes again when needed)."""
        self.closed = True
