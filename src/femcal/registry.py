"""One registry of names for surrogates, calibrators, physical effects and FE solvers.

Every kind of pluggable piece of femcal lives in a :class:`Registry` and is used with the
same verbs::

    SOLVERS = Registry("FE solver", group="femcal.solvers", builtins=("femcal.fe.*",))

    @SOLVERS.register("calculix")         # a decorator with a name ...
    class CalculixDisc: ...

    SOLVERS.register("other", OtherDisc)  # ... or a call
    SOLVERS.get("calculix")               # the registered object (class or function)
    SOLVERS.create("calculix", **kw)      # get(name)(**kw): an instance
    SOLVERS.names()                       # sorted names; "calculix" in SOLVERS

A name is registered once: registering another object under a taken name raises
:class:`~femcal.errors.ConfigError` naming both, unless ``replace=True`` says it is meant.
Registering the very same object again is not a duplicate (a module imported twice, a file
loaded again), nor is a new definition from the same module under the same qualified name (a
module reloaded with :func:`importlib.reload`): that one replaces the old.

The registry fills itself on first use (``get``, ``create``, ``names``, ``in``), never on
import, so a command that does not use it pays nothing and cannot fail because of it:

* **built-in modules** (``builtins``): imported, their decorators register; a name ending in
  ``.*`` imports every module of that package (a new file there registers itself);
* **installed plugins**: every entry point of the group (``group``), in the distribution's
  ``pyproject.toml``::

      [project.entry-points."femcal.solvers"]
      my_solver = "my_package.solver"            # a module: its decorators register
      other = "my_package.solver:OtherSolver"    # an object: registered under "other"

  A plugin that fails to load is reported as a ConfigError naming the entry point, its
  distribution, the error and the fix, on every use of that registry until it is fixed or
  uninstalled; whatever it registered before failing is removed, and the other plugins load.

femcal's five registries, each with thin module functions of the same verbs:

==========================================  ======================  =========================
registry                                    entry-point group       module functions
==========================================  ======================  =========================
``femcal.surrogates.surrogate_registry``    ``femcal.surrogates``   ``register_surrogate``,
                                                                    ``get_surrogate``,
                                                                    ``make_surrogate``,
                                                                    ``available_surrogates``
``femcal.surrogates.baseline_registry``     ``femcal.baselines``    ``register_baseline``,
                                                                    ``get_baseline``,
                                                                    ``make_baseline``,
                                                                    ``available_baselines``
``femcal.calibration.calibrator_registry``  ``femcal.calibrators``  ``register_calibrator``,
                                                                    ``get_calibrator``,
                                                                    ``available_calibrators``
``femcal.effects.effect_registry``          ``femcal.effects``      ``register_effect``,
                                                                    ``get_effect``,
                                                                    ``available_effects``
``femcal.fe.solver_registry``               ``femcal.solvers``      ``register_solver``,
                                                                    ``make_solver``,
                                                                    ``available_solvers``
==========================================  ======================  =========================

``make_*`` builds an instance (``create``), ``get_*`` returns what was registered, except the
older ``femcal.fe.get_solver``, kept as an alias of ``make_solver``.
"""

from __future__ import annotations

import difflib
import importlib
import pkgutil
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from importlib import metadata
from types import ModuleType
from typing import Any, Generic, TypeVar, overload

from femcal.errors import ConfigError

T = TypeVar("T")


@dataclass(frozen=True)
class RegistryState:
    """What :meth:`Registry.snapshot` saved (opaque; give it back to :meth:`Registry.restore`)."""

    entries: dict[str, Any]
    plugins: frozenset[str]
    loaded: bool
    builtins_loaded: bool


class Registry(Generic[T]):
    """Objects of one kind by name, with built-in modules and entry-point plugins.

    Parameters
    ----------
    kind : str
        What is registered, as a noun: ``"surrogate"``, ``"effect"`` (messages).
    group : str or None
        The entry-point group installed plugins declare in (``"femcal.surrogates"``); None:
        no plugins.
    builtins : sequence of str
        Modules imported on first use (their decorators register); ``"package.*"`` imports
        every module of the package.
    what : str, optional
        The noun as the user meets it in settings, for "unknown name" (default ``kind``):
        ``"calibration method"``.
    fix : str
        How to get a name that is missing, appended to "unknown name" messages.
    name_of : callable, optional
        The name an object carries itself (an effect's ``name``): then ``register(obj)`` needs
        no name, and a plugin entry point naming such an object registers it under that name
        rather than the entry point's.
    accepts : callable, optional
        Whether a plugin entry point's object is one of this kind (default: callable).
    expects : str
        That kind of object in words, for a plugin naming something else (``"an Effect
        subclass"``).
    on_register : callable, optional
        ``on_register(name, obj)`` before an object is registered: raises ConfigError to refuse
        it (validation) or annotates it.
    rename : str
        How to resolve a duplicate name, in the message (default "Give yours another name").
    """

    def __init__(
        self,
        kind: str,
        *,
        group: str | None,
        builtins: Sequence[str] = (),
        what: str | None = None,
        fix: str = "",
        name_of: Callable[[T], str] | None = None,
        accepts: Callable[[object], bool] = callable,
        expects: str = "a class or function",
        on_register: Callable[[str, T], None] | None = None,
        rename: str = "Give yours another name",
    ) -> None:
        self.kind = kind
        self.group = group
        self.builtins = tuple(builtins)
        self.what = what or kind
        self.fix = fix
        self._name_of = name_of
        self._accepts = accepts
        self._expects = expects
        self._on_register = on_register
        self._rename = rename
        self._entries: dict[str, T] = {}
        self._plugins: set[str] = set()  # entry points loaded ("name = value")
        self._loaded = False  # builtins and every plugin
        self._builtins_loaded = False
        self._busy = False  # loading now (a module being imported may use the registry)
        self._lock = threading.RLock()

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, group={self.group!r}, {len(self._entries)} registered)"

    # ------------------------------------------------------------------ register
    @overload
    def register(self, name: str, obj: T, /, *, replace: bool = ...) -> T: ...

    @overload
    def register(self, name: str | None = ..., /, *, replace: bool = ...) -> Callable[[T], T]: ...

    @overload
    def register(self, obj: T, /, *, replace: bool = ...) -> T: ...

    def register(self, name_or_obj: Any = None, obj: Any = None, /, *, replace: bool = False):
        """Register an object under a name; a decorator or a call.

        ``register("name", obj)`` registers and returns ``obj``; ``@register("name")``
        decorates. With ``name_of`` (objects that carry their name), ``@register`` and
        ``register(obj)`` use that name.

        Raises
        ------
        ConfigError
            The name is taken by another object (unless ``replace=True``), is not a non-empty
            string, or ``on_register`` refuses the object.
        """
        if obj is not None:
            return self._add(name_or_obj, obj, replace=replace)
        if name_or_obj is None or isinstance(name_or_obj, str):
            name = name_or_obj

            def decorate(target: T) -> T:
                return self._add(name, target, replace=replace)

            return decorate
        return self._add(None, name_or_obj, replace=replace)

    def _add(self, name: str | None, obj: T, *, replace: bool) -> T:
        if name is None:
            if self._name_of is None:
                raise ConfigError(
                    f"Registering {_describe(obj)} as a {self.kind} needs a name; got none. "
                    f'Write @register("my_{self.kind.split()[-1]}") or register(name, obj).'
                )
            name = self._name_of(obj)
        with self._lock:
            if self._on_register is not None:
                self._on_register(name, obj)
            if not isinstance(name, str) or not name.strip():
                raise ConfigError(
                    f"A {self.kind} needs a non-empty name (a string); got {name!r} for "
                    f"{_describe(obj)}. Give it a name."
                )
            old = self._entries.get(name)
            if old is not None and not replace and not _same_definition(old, obj):
                raise ConfigError(
                    f"{_article(self.kind).capitalize()} {self.kind} named '{name}' is already "
                    f"registered ({_describe(old)}); got another, {_describe(obj)}. "
                    f"{self._rename}, or pass replace=True to replace it on purpose."
                )
            self._entries[name] = obj
        return obj

    def unregister(self, name: str) -> T:
        """Remove ``name`` and return what was registered (ConfigError if nothing was)."""
        with self._lock:
            if name not in self._entries:
                raise ConfigError(
                    f"Cannot unregister the {self.kind} '{name}': it is not registered "
                    f"(registered: {', '.join(sorted(self._entries)) or 'none'})."
                )
            return self._entries.pop(name)

    # ------------------------------------------------------------------ look up
    def get(self, name: str) -> T:
        """The object registered under ``name``.

        Raises
        ------
        ConfigError
            No such name (the message lists the names and how to add one), or a plugin of
            the group failed to load.
        """
        self.load()
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            raise ConfigError(self._unknown_message(name)) from None

    def create(self, name: str, /, *args: Any, **kwargs: Any) -> Any:
        """``get(name)(*args, **kwargs)``: an instance of a registered class (or a call)."""
        return self.get(name)(*args, **kwargs)  # type: ignore[operator]

    def names(self) -> list[str]:
        """The registered names, sorted (built-in, plugins, registered in this process)."""
        self.load()
        return sorted(self._entries)

    def items(self, *, load: bool = True) -> list[tuple[str, T]]:
        """``(name, object)`` pairs, in registration order.

        ``load=False``: those registered so far, without importing the built-in modules or
        loading the plugins (see :meth:`import_builtin`).
        """
        if load:
            self.load()
        return list(self._entries.items())

    def __contains__(self, name: object) -> bool:
        self.load()
        try:
            return name in self._entries
        except TypeError:  # an unhashable value is no name
            return False

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def _unknown_message(self, name: object) -> str:
        names = sorted(self._entries)
        close = difflib.get_close_matches(name, names, n=1) if isinstance(name, str) else []
        shown = f"'{name}'" if isinstance(name, str) else f"{name!r} (a {type(name).__name__})"
        choices = ", ".join(names) if names else "none (nothing is registered)"
        guess = f" Did you mean '{close[0]}'?" if close else ""
        fix = f" {self.fix}" if self.fix else ""
        return f"Unknown {self.what} {shown}; choose one of {choices}.{guess}{fix}"

    # ------------------------------------------------------------------ loading
    def import_builtin(self, module: str) -> bool:
        """Import one built-in module (its decorators register), not the others or plugins.

        For a look-up that knows where its object is defined (a saved model names its class
        as ``"module:QualName"``): only that module's imports are paid.

        Returns
        -------
        bool
            Whether ``module`` is one of the built-in modules named in ``builtins`` (a
            ``"package.*"`` entry does not name its modules); False imports nothing.
        """
        if module not in self.builtins or module.endswith(".*"):
            return False
        importlib.import_module(module)
        return True

    def load(self) -> None:
        """Import the built-in modules and load the plugins, once (idempotent).

        Called by every look-up; call it yourself to surface a broken plugin early.
        """
        if self._loaded:
            return
        with self._lock:
            if self._loaded or self._busy:
                return
            self._busy = True
            try:
                self._load_builtins()
                self._load_plugins()
                self._loaded = True
            finally:
                self._busy = False

    def rescan_plugins(self) -> None:
        """Look for new entry points at the next use (after installing a plugin in-process).

        Plugins already loaded stay registered and are not loaded again.
        """
        with self._lock:
            self._loaded = False

    def _load_plugins(self) -> None:
        if self.group is None:
            return
        failures = []
        for ep in metadata.entry_points(group=self.group):
            key = f"{ep.name} = {ep.value}"
            if key in self._plugins:
                continue
            problem = self._load_plugin(ep)
            if problem:
                failures.append(problem)
            else:
                self._plugins.add(key)
        if len(failures) == 1:
            raise ConfigError(failures[0])
        if failures:
            listed = " ".join(f"({i}) {msg}" for i, msg in enumerate(failures, 1))
            raise ConfigError(f"{len(failures)} femcal {self.kind} plugins failed: {listed}")

    def _load_plugin(self, ep: metadata.EntryPoint) -> str | None:
        """Load one entry point; the message of what went wrong, or None."""
        dist = getattr(ep, "dist", None)
        where = f"'{ep.name} = {ep.value}' (entry point group {self.group}"
        where += f", distribution {dist.name} {dist.version})" if dist is not None else ")"
        remove = f"pip uninstall {dist.name}" if dist is not None else "uninstall it"
        saved = dict(self._entries)
        try:
            obj = ep.load()
            if not isinstance(obj, ModuleType):
                if not self._accepts(obj):
                    self._restore_entries(saved)
                    return (
                        f"The femcal {self.kind} plugin {where} names {obj!r}, a "
                        f"{type(obj).__name__}; an entry point of this group names a module "
                        f"('my_package.module') or {self._expects} ('my_package.module:Name'). "
                        f"Fix the plugin, or remove it ({remove})."
                    )
                if not any(old is obj for old in self._entries.values()):
                    self._add(self._name_of(obj) if self._name_of else ep.name, obj, replace=False)
        except Exception as exc:
            self._restore_entries(saved)
            return (
                f"The femcal {self.kind} plugin {where} failed to load: "
                f"{type(exc).__name__}: {exc}. Fix the plugin, or remove it ({remove})."
            )
        return None

    def _restore_entries(self, saved: dict[str, T]) -> None:
        self._entries.clear()
        self._entries.update(saved)

    # ------------------------------------------------------------------ tests
    def _load_builtins(self) -> None:
        with self._lock:
            if not self._builtins_loaded:
                for module in self.builtins:
                    _import(module)
                self._builtins_loaded = True

    def snapshot(self) -> RegistryState:
        """The registry's contents and loading state, for :meth:`restore` (tests).

        The built-in modules are imported first: a module registers its entries once, when it
        is first imported, so a state saved before that would drop them on restore.
        """
        self._load_builtins()
        with self._lock:
            return RegistryState(
                dict(self._entries),
                frozenset(self._plugins),
                self._loaded,
                self._builtins_loaded,
            )

    def restore(self, state: RegistryState) -> None:
        """Put back what :meth:`snapshot` saved."""
        with self._lock:
            self._restore_entries(state.entries)
            self._plugins = set(state.plugins)
            self._loaded = state.loaded
            self._builtins_loaded = state.builtins_loaded


def _import(module: str) -> None:
    """Import a module, or every module of a package for ``"package.*"``."""
    if not module.endswith(".*"):
        importlib.import_module(module)
        return
    package = importlib.import_module(module[:-2])
    for info in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{package.__name__}.{info.name}")


def _same_definition(old: object, new: object) -> bool:
    """The same object, or its new definition after a reload (same module and qualname)."""
    if old is new:
        return True
    key = (getattr(old, "__module__", None), getattr(old, "__qualname__", None))
    new_key = (getattr(new, "__module__", None), getattr(new, "__qualname__", None))
    return None not in key and key == new_key and "<locals>" not in key[1]


def _describe(obj: object) -> str:
    """``module.QualName`` of a class or function, else its repr."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    return f"{module}.{qualname}" if module and qualname else repr(obj)


def _article(noun: str) -> str:
    """``"an"`` before a vowel sound (``effect``, ``FE solver``), else ``"a"``."""
    word = noun.split()[0]
    acronym = word.isupper() and word[0] in "AEFHILMNORSX"
    return "an" if acronym or (not word.isupper() and word[0].lower() in "aeiou") else "a"
