"""What every liuxing_envs env shares: its keyword interface checked by name (from its
:class:`~liuxing_envs.settings.Settings` where it has them), its ``closed`` state (a closed env
refuses ``step()`` until ``reset()`` reopens it, see
:func:`liuxing_envs.validation.refuse_if_closed`), copies that leave out what can be rebuilt,
and the warning of a deprecated id."""

from __future__ import annotations

import functools
import inspect
import warnings
from typing import ClassVar

import gymnasium as gym

from liuxing_envs.settings import Settings
from liuxing_envs.validation import closest


class LiuxingEnv(gym.Env):
    """Base of the suite's envs. Every setting is a keyword-only argument of ``__init__``;
    a name that is none of them is refused with the closest one and the full list (Python's
    own TypeError names neither), before anything is built."""

    closed = False
    #: The env's typed settings (None: its keywords are ``__init__``'s own keyword-only ones).
    settings_type: ClassVar[type[Settings] | None] = None
    #: Attributes that pickles and deep copies leave out (caches, compiled scenes), made again
    #: from the settings by :meth:`rebuild_after_copy`.
    rebuilt_on_copy: ClassVar[tuple[str, ...]] = ()

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
        if cls.settings_type is not None:
            return cls.settings_type.flat_names() + cls.settings_type.extra_keywords
        parameters = inspect.signature(cls.__init__).parameters.values()
        return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)

    def close(self) -> None:
        """Marks the env closed: :meth:`step` is refused until ``reset()`` reopens it (each
        env's own ``close()`` frees its renderers, which a reset makes again when needed)."""
        self.closed = True

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for name in self.rebuilt_on_copy:
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self.rebuilt_on_copy:
            self.rebuild_after_copy()

    def rebuild_after_copy(self) -> None:
        """Make again the attributes named in :attr:`rebuilt_on_copy` (after unpickling)."""
        raise NotImplementedError(f"{type(self).__name__} names rebuilt_on_copy: rebuild them")


def warn_deprecated(old_id: str, new_id: str, what_changed: str) -> None:
    """The warning a deprecated id gives when made: kept for one release so that old run
    folders still evaluate."""
    warnings.warn(
        f"{old_id} is deprecated and will be removed in the next release; use {new_id} "
        f"({what_changed}; see CHANGELOG.md)",
        DeprecationWarning,
        stacklevel=3,
    )
