"""What every liuxing_envs env shares: its keyword interface checked by name (from its
:class:`~liuxing_envs.settings.Settings` where it has them) and its settings readable by their
flat names, its ``closed`` state (a closed env refuses ``step()`` until ``reset()`` reopens it,
see :func:`liuxing_envs.validation.refuse_if_closed`), the step's checks and error notes, the
overview camera's renderer, copies that leave out what can be rebuilt, and the warning of a
deprecated id."""

from __future__ import annotations

import functools
import inspect
import operator
import warnings
from typing import ClassVar

import gymnasium as gym

from liuxing_envs.forking import check_opengl_not_forked
from liuxing_envs.opengl import new_renderer
from liuxing_envs.settings import Settings
from liuxing_envs.validation import closest, note_step_error, refuse_if_closed

#: (height, width) of ``render()``'s frames.
RENDER_SIZE = (480, 640)


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

    #: The settings of the id the class is registered as; a docstring's ``{arguments}`` is
    #: their table.
    default_settings: ClassVar[Settings | None] = None
    #: A deprecated version's (old id, new id, what the new one changes): making it warns.
    deprecation: ClassVar[tuple[str, str, str] | None] = None
    #: Whether a setting given under a mode that leaves it unused is refused by name (False
    #: only for the deprecated v0 ids, which always took such settings and ignored them).
    refuses_inapplicable: ClassVar[bool] = True

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        own = cls.__dict__
        if cls.settings_type is not None and "{arguments}" in (own.get("__doc__") or ""):
            # The spec's argument table, made from the settings' knobs with this id's defaults.
            table = cls.settings_type.markdown_table(cls.default_settings)
            cls.__doc__ = cls.__doc__.replace("{arguments}", table.replace("\n", "\n    "))
        if "__init__" not in own and "default_settings" not in own:
            return
        # A version that only changes the defaults inherits the checked __init__: its own
        # wrapper shows and checks its own defaults.
        init = own.get("__init__") or getattr(cls.__init__, "__wrapped__", cls.__init__)

        @functools.wraps(init)
        def checked_init(self, *args, **settings):
            accepted = cls.keyword_names()
            for name in settings:
                if name not in accepted:
                    raise TypeError(
                        f"{cls.__name__} has no keyword argument {name!r}"
                        f"{closest(name, accepted)}; allowed: {', '.join(accepted)}"
                    )
            if type(self) is cls and cls.deprecation is not None:
                warn_deprecated(*cls.deprecation)
            init(self, *args, **settings)

        if cls.settings_type is not None:
            checked_init.__signature__ = cls._keyword_signature(init)
        cls.__init__ = checked_init

    @classmethod
    def _keyword_signature(cls, init) -> inspect.Signature:
        """``init``'s signature with its ``**settings`` spelt out: every setting a keyword-only
        argument with the class's default (``default_settings``), so that ``help()``, IDEs and
        ``inspect`` show the keyword interface :meth:`keyword_names` lists."""
        own = inspect.signature(init).parameters.values()
        defaults = getattr(cls, "default_settings", None) or cls.settings_type()
        settings = [
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=value)
            for name, value in defaults.flat().items()
        ]
        positional = [p for p in own if p.kind is not inspect.Parameter.KEYWORD_ONLY]
        keywords = [p for p in own if p.kind is inspect.Parameter.KEYWORD_ONLY]
        return inspect.Signature(
            [p for p in positional if p.kind is not inspect.Parameter.VAR_KEYWORD]
            + settings
            + keywords
        )

    @classmethod
    def settings_from(cls, given: dict) -> Settings:
        """The settings of the keywords ``given`` over this class's defaults, checked (an
        inapplicable setting refused as :attr:`refuses_inapplicable` says)."""
        return cls.settings_type.from_flat(
            given, defaults=cls.default_settings, refuse_inapplicable=cls.refuses_inapplicable
        )

    @classmethod
    def keyword_names(cls) -> tuple[str, ...]:
        """The settings ``__init__`` takes (``gym.make(id, **settings)``), in order."""
        if cls.settings_type is not None:
            return cls.settings_type.flat_names() + cls.settings_type.extra_keywords
        parameters = inspect.signature(cls.__init__).parameters.values()
        return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)

    #: The setting that sets how many steps an episode runs at most.
    episode_length_setting: ClassVar[str] = ""

    @property
    def episode_length(self) -> int:
        """The value of :attr:`episode_length_setting`: the v1 envs end every episode there
        themselves. A deprecated v0 id's registered time limit ends them instead where it is
        shorter (``ViewPlanning-v0``'s 4 steps) and, for ``InstrumentGrasp-v0``, whose env never
        truncates, always (200 steps)."""
        return self.settings.flat()[self.episode_length_setting]

    def __getattr__(self, name: str):
        """Every setting by its flat name (``env.view_budget``, ``env.max_grip_force``)."""
        settings = self.__dict__.get("settings")
        found = None if settings is None else settings.knobs().get(name)
        if found is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(getattr(settings, found[0]), name)

    def __setattr__(self, name: str, value) -> None:
        """Refuse a setting assigned by its flat name once the env has its settings: the parts
        were built from them, so ``env.view_budget = 8`` would read 8 and change nothing."""
        settings = self.__dict__.get("settings")
        if settings is not None and name in settings.knobs():
            spec = self.__dict__.get("spec")
            maker = f"gym.make({spec.id!r}, " if spec is not None else f"{type(self).__name__}("
            raise AttributeError(
                f"{name} is a setting of {type(self).__name__}, fixed when the env is made "
                f"(its parts are built from it); make a new env with it: "
                f"{maker}{name}={value!r}, ...)"
            )
        super().__setattr__(name, value)

    # ------------------------------------------------------------------ stepping
    #: Whether ``step()`` may run: set by a successful ``reset()``, cleared at an episode's end.
    _episode_ready = False
    #: The last ``reset()``'s seed, named in the notes of an error raised in ``step()``.
    _reset_seed: int | None = None

    def step(self, action):
        refuse_if_closed(self)
        step = self._steps_taken() + 1
        # A try block, not a context manager: this wraps every step of every env, and a
        # context manager costs microseconds to enter and leave.
        try:
            if not self._episode_ready:
                raise RuntimeError("call reset() before step(), and again after an episode ends")
            return self._step(action)
        except Exception as error:
            note_step_error(self, error, step, self._reset_seed)
            raise

    def _steps_taken(self) -> int:
        """Steps of the episode taken so far."""
        raise NotImplementedError

    def _step(self, action):
        """``step()`` once the env is open and its episode ready."""
        raise NotImplementedError

    def prepare_objects(self) -> None:
        """Build now, for every object the env can draw, what the object's first episode
        would otherwise build (nothing, unless the env says otherwise): for measurements that
        must not see it being built."""

    # ------------------------------------------------------------------ rendering, closing
    #: The overview camera's renderer (``render_mode="rgb_array"``), made on first use.
    _renderer = None

    def _overview_renderer(self, model):
        """The overview camera's renderer for ``model``, made on first use (never before a
        fork: a renderer made in the parent hangs in the child)."""
        check_opengl_not_forked()
        if self._renderer is None:
            self._renderer = new_renderer(model, *RENDER_SIZE)
        return self._renderer

    def _close_renderer(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def close(self) -> None:
        """Marks the env closed: :meth:`step` is refused until ``reset()`` reopens it, and
        frees the renderer (each env's own ``close()`` frees its cameras); a reset makes them
        again when needed."""
        self.closed = True
        self._close_renderer()

    # ------------------------------------------------------------------ copies
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for name in ("_renderer", *self.rebuilt_on_copy):
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self.rebuilt_on_copy:
            self.rebuild_after_copy()

    def rebuild_after_copy(self) -> None:
        """Make again the attributes named in :attr:`rebuilt_on_copy` (after unpickling)."""
        raise NotImplementedError(f"{type(self).__name__} names rebuilt_on_copy: rebuild them")


def delegate(path: str, doc: str | None = None) -> property:
    """A read-only property that reads ``path`` (``"scene.model"``) off the env: a part's
    attribute under the name code outside has always read it by."""
    return property(operator.attrgetter(path), doc=doc or f"``self.{path}``.")


def warn_deprecated(old_id: str, new_id: str, what_changed: str) -> None:
    """The warning a deprecated id gives when made: kept for one release so that old run
    folders still evaluate."""
    warnings.warn(
        f"{old_id} is deprecated and will be removed in the next release; use {new_id} "
        f"({what_changed}; see CHANGELOG.md)",
        DeprecationWarning,
        stacklevel=3,
    )
