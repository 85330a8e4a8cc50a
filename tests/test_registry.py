"""The one Registry[T]: register, look up, duplicates, built-in modules and entry-point plugins.

Plugins are real: a dist-info folder with an ``entry_points.txt`` on a temporary ``sys.path``
entry, found by :func:`importlib.metadata.entry_points` as an installed package would be.
"""

from __future__ import annotations

import importlib
import sys
from functools import partial

import dists
import pytest
from dists import write

from femcal.errors import ConfigError, FemcalError
from femcal.registry import Registry

GROUP = "femcal.tests"


@pytest.fixture
def site(tmp_path, monkeypatch):
    """A folder on sys.path; modules imported from it are forgotten after the test."""
    folder = tmp_path / "site"
    folder.mkdir()
    monkeypatch.syspath_prepend(str(folder))  # also invalidates importlib's caches
    before = set(sys.modules)
    yield folder
    for name in set(sys.modules) - before:
        if name.startswith("regtest_"):
            del sys.modules[name]


@pytest.fixture
def hub(site):
    """A registry of the test group, which modules written by a test register into
    (``from regtest_hub import REG``)."""
    write(site / "regtest_hub.py", "REG = None\n")
    module = importlib.import_module("regtest_hub")
    module.REG = widgets(accepts=lambda obj: isinstance(obj, type), expects="a widget class")
    return module.REG


#: An installed distribution: a dist-info with entry points (of GROUP), and its modules.
install = partial(dists.install, group=GROUP)


def widgets(**kwargs) -> Registry:
    return Registry("widget", group=GROUP, fix="Register yours with @WIDGETS.register.", **kwargs)


class Gear:
    name = "gear"

    def __init__(self, teeth: int = 12) -> None:
        self.teeth = teeth


class Cog:
    name = "cog"


# ---------------------------------------------------------------- register and look up
def test_register_as_decorator_and_as_call_then_get_create_and_names():
    reg = widgets()

    @reg.register("gear")
    class Local(Gear):
        pass

    assert reg.register("cog", Cog) is Cog  # a call returns the object
    assert reg.get("gear") is Local and reg.get("cog") is Cog
    assert reg.names() == ["cog", "gear"] == list(reg)
    assert "gear" in reg and "nope" not in reg and ["gear"] not in reg and len(reg) == 2
    assert reg.create("gear", teeth=30).teeth == 30
    assert reg.items() == [("gear", Local), ("cog", Cog)]  # in registration order


def test_objects_that_carry_their_name_register_bare():
    reg = widgets(name_of=lambda obj: obj.name)
    reg.register(Gear)

    @reg.register
    class Sprocket:
        name = "sprocket"

    assert reg.names() == ["gear", "sprocket"]


def test_a_name_is_needed_when_objects_do_not_carry_one():
    reg = widgets()
    with pytest.raises(ConfigError, match=r"Registering .*Gear as a widget needs a name; got"):
        reg.register(Gear)
    with pytest.raises(ConfigError, match=r"needs a non-empty name \(a string\); got ''"):
        reg.register("", Gear)


def test_a_duplicate_name_is_refused_with_both_objects_and_the_fix():
    reg = widgets()
    reg.register("gear", Gear)
    with pytest.raises(
        ConfigError,
        match=rf"A widget named 'gear' is already registered \({__name__}\.Gear\); got "
        rf"another, {__name__}\.Cog\. Give yours another name, or pass replace=True",
    ) as info:
        reg.register("gear", Cog)
    assert isinstance(info.value, FemcalError) and isinstance(info.value, ValueError)
    assert reg.get("gear") is Gear  # the first stays
    reg.register("gear", Cog, replace=True)  # on purpose
    assert reg.get("gear") is Cog


def test_the_same_object_again_is_not_a_duplicate():
    reg = widgets()
    reg.register("gear", Gear)
    reg.register("gear", Gear)
    reg.register("also_gear", Gear)  # an alias is fine
    assert reg.names() == ["also_gear", "gear"]


def test_a_reloaded_module_replaces_its_own_definitions(site, hub):
    write(
        site / "regtest_reload.py",
        """
        from regtest_hub import REG

        @REG.register("thing")
        class Thing:
            pass
        """,
    )
    first = importlib.import_module("regtest_reload").Thing
    second = importlib.reload(sys.modules["regtest_reload"]).Thing
    assert first is not second and hub.get("thing") is second


def test_classes_made_by_a_function_are_distinct_definitions():
    reg = widgets()

    def make():
        class Local:
            pass

        return Local

    reg.register("local", make())
    with pytest.raises(ConfigError, match="already registered"):
        reg.register("local", make())


def test_an_unknown_name_names_the_choices_a_close_match_and_the_fix():
    reg = widgets(what="widget kind")
    reg.register("gear", Gear)
    reg.register("cog", Cog)
    with pytest.raises(
        ConfigError,
        match=r"^Unknown widget kind 'gaer'; choose one of cog, gear\. Did you mean 'gear'\? "
        r"Register yours with @WIDGETS\.register\.$",
    ):
        reg.get("gaer")
    with pytest.raises(ConfigError, match=r"Unknown widget kind \['gear'\] \(a list\)"):
        reg.get(["gear"])
    with pytest.raises(ConfigError, match=r"choose one of none \(nothing is registered\)"):
        widgets().get("gear")


def test_unregister():
    reg = widgets()
    reg.register("gear", Gear)
    assert reg.unregister("gear") is Gear and reg.names() == []
    with pytest.raises(ConfigError, match=r"Cannot unregister the widget 'gear': it is not"):
        reg.unregister("gear")


def test_on_register_validates_before_anything_is_stored():
    def only_gears(name, obj):
        if not issubclass(obj, Gear):
            raise ConfigError(f"{name}: not a gear")

    reg = widgets(on_register=only_gears)
    with pytest.raises(ConfigError, match="cog: not a gear"):
        reg.register("cog", Cog)
    assert reg.names() == []


def test_snapshot_and_restore():
    reg = widgets()
    reg.register("gear", Gear)
    state = reg.snapshot()
    reg.register("cog", Cog)
    reg.restore(state)
    assert reg.names() == ["gear"]


# ---------------------------------------------------------------- built-in modules
def test_builtin_modules_are_imported_on_first_use_only(site, hub):
    write(site / "regtest_pkg" / "__init__.py", "")
    for name in ("alpha", "beta"):
        write(
            site / "regtest_pkg" / f"{name}.py",
            f"""
            from regtest_hub import REG

            @REG.register("{name}")
            def {name}():
                return "{name}"
            """,
        )
    reg = widgets(builtins=("regtest_pkg.*",))
    assert "regtest_pkg" not in sys.modules  # nothing on creation
    assert reg.names() == []  # alpha and beta register into hub, on reg's first use
    assert "regtest_pkg.alpha" in sys.modules and "regtest_pkg.beta" in sys.modules
    assert hub.names() == ["alpha", "beta"] and hub.create("beta") == "beta"


def test_a_restore_keeps_what_the_builtin_modules_registered(site):
    """A module registers once, when first imported: a state saved before the registry's
    first use must not drop its entries on restore (a test fixture's snapshot and restore
    around a look-up that imported them)."""
    write(site / "regtest_hub.py", "REG = None\n")
    hub_module = importlib.import_module("regtest_hub")
    hub_module.REG = reg = widgets(builtins=("regtest_builtin",))
    write(
        site / "regtest_builtin.py",
        """
        from regtest_hub import REG

        @REG.register("alpha")
        def alpha():
            return "alpha"
        """,
    )
    state = reg.snapshot()
    assert reg.create("alpha") == "alpha"
    reg.restore(state)
    assert reg.names() == ["alpha"]


def test_one_builtin_module_is_imported_alone_for_a_look_up_that_knows_it(site, hub):
    for name in ("alpha", "beta"):
        write(
            site / f"regtest_{name}.py",
            f"""
            from regtest_hub import REG

            @REG.register("{name}")
            class {name.title()}:
                pass
            """,
        )
    hub.builtins = ("regtest_alpha", "regtest_beta")
    assert hub.import_builtin("regtest_beta") is True
    assert "regtest_beta" in sys.modules and "regtest_alpha" not in sys.modules
    assert [name for name, _ in hub.items(load=False)] == ["beta"]
    # Not a built-in module (or a package's wildcard): nothing is imported.
    write(site / "regtest_gamma.py", "raise RuntimeError('imported')\n")
    assert hub.import_builtin("regtest_gamma") is False
    assert widgets(builtins=("regtest_pkg.*",)).import_builtin("regtest_pkg.alpha") is False
    assert "regtest_gamma" not in sys.modules and "regtest_alpha" not in sys.modules
    assert [name for name, _ in hub.items()] == ["beta", "alpha"]  # then the whole registry


# ---------------------------------------------------------------- entry-point plugins
MODULE_PLUGIN = """
from regtest_hub import REG

@REG.register("from_module")
class FromModule:
    pass
"""


@pytest.fixture
def plugged(hub):
    return hub


def test_a_plugin_module_registers_on_first_use(site, plugged):
    install(site, "mod = regtest_mod\n", {"regtest_mod": MODULE_PLUGIN})
    plugged.register("gear", Gear)  # registering loads nothing
    assert "regtest_mod" not in sys.modules
    assert plugged.names() == ["from_module", "gear"]
    assert plugged.get("from_module").__module__ == "regtest_mod"


def test_a_plugin_object_registers_under_the_entry_point_name(site, plugged):
    install(
        site, "sprocket = regtest_obj:Sprocket\n", {"regtest_obj": "class Sprocket:\n    pass\n"}
    )
    assert plugged.get("sprocket").__qualname__ == "Sprocket"


def test_a_plugin_object_that_carries_its_name_registers_under_it(site):
    install(
        site,
        "whatever = regtest_named:Named\n",
        {"regtest_named": "class Named:\n    name = 'own'\n"},
    )
    reg = widgets(name_of=lambda obj: obj.name)
    assert reg.names() == ["own"]


def test_an_entry_point_naming_a_registered_class_does_not_register_it_twice(site, plugged):
    install(site, "alias = regtest_mod:FromModule\n", {"regtest_mod": MODULE_PLUGIN})
    assert plugged.names() == ["from_module"]


def test_a_broken_plugin_names_the_entry_point_its_error_and_the_fix(site, plugged):
    install(
        site,
        """
        good = regtest_mod
        broken = regtest_broken
        """,
        {
            "regtest_mod": MODULE_PLUGIN,
            "regtest_broken": MODULE_PLUGIN.replace("from_module", "half_done")
            + "\nraise RuntimeError('needs calibration')\n",
        },
    )
    plugged.register("gear", Gear)
    message = (
        r"^The femcal widget plugin 'broken = regtest_broken' \(entry point group femcal\.tests, "
        r"distribution regtest-demo 0\.1\) failed to load: RuntimeError: needs calibration\. "
        r"Fix the plugin, or remove it \(pip uninstall regtest-demo\)\.$"
    )
    with pytest.raises(ConfigError, match=message):
        plugged.names()
    with pytest.raises(ConfigError, match=message):  # on every use, until fixed
        plugged.get("gear")
    # What the broken module registered before failing is gone; the good plugin loaded.
    assert set(plugged.snapshot().entries) == {"gear", "from_module"}
    # Fixed (here: uninstalled), the registry works again without a restart.
    (site / "regtest_demo-0.1.dist-info" / "entry_points.txt").write_text(
        f"[{GROUP}]\ngood = regtest_mod\n"
    )
    importlib.invalidate_caches()
    assert plugged.names() == ["from_module", "gear"]


def test_every_broken_plugin_is_listed(site, plugged):
    install(site, "one = regtest_missing_one\ntwo = regtest_missing_two\n", {})
    with pytest.raises(
        ConfigError,
        match=r"^2 femcal widget plugins failed: \(1\) The femcal widget plugin 'one = "
        r"regtest_missing_one' .*ModuleNotFoundError.* \(2\) The femcal widget plugin 'two = ",
    ):
        plugged.names()


def test_a_plugin_naming_something_else(site, plugged):
    install(site, "thing = regtest_fn:make\n", {"regtest_fn": "def make():\n    return None\n"})
    with pytest.raises(
        ConfigError,
        match=r"plugin 'thing = regtest_fn:make' .* names <function make .*>, a function; an "
        r"entry point of this group names a module \('my_package\.module'\) or a widget class",
    ):
        plugged.names()


def test_a_plugin_clashing_with_a_registered_name_is_reported(site, plugged):
    install(site, "gear = regtest_obj:Sprocket\n", {"regtest_obj": "class Sprocket:\n    pass\n"})
    plugged.register("gear", Gear)
    with pytest.raises(
        ConfigError,
        match=r"plugin 'gear = regtest_obj:Sprocket' .*failed to load: ConfigError: A widget "
        rf"named 'gear' is already registered \({__name__}\.Gear\)",
    ):
        plugged.names()
    assert plugged.snapshot().entries == {"gear": Gear}


def test_a_plugin_installed_later_is_found_after_a_rescan(site, plugged):
    assert plugged.names() == []
    install(site, "mod = regtest_mod\n", {"regtest_mod": MODULE_PLUGIN})
    assert plugged.names() == []  # scanned once per process ...
    plugged.rescan_plugins()
    assert plugged.names() == ["from_module"]  # ... unless asked to look again


def test_a_registry_without_a_group_loads_no_plugin(site):
    install(site, "mod = regtest_mod\n", {"regtest_mod": MODULE_PLUGIN})
    assert Registry("widget", group=None).names() == []


# ---------------------------------------------------------------- femcal's four registries
def _registries():
    from femcal.calibration import calibrator_registry
    from femcal.effects import effect_registry
    from femcal.fe import solver_registry
    from femcal.surrogates import surrogate_registry

    return {
        "femcal.surrogates": (surrogate_registry, "nn"),
        "femcal.calibrators": (calibrator_registry, "pgd"),
        "femcal.effects": (effect_registry, "facet_contact"),
        "femcal.solvers": (solver_registry, "calculix"),
    }


@pytest.mark.parametrize("group", ["femcal.surrogates", "femcal.calibrators", "femcal.effects"])
def test_femcals_registries_share_the_verbs_and_refuse_duplicates(group):
    registry, builtin = _registries()[group]
    assert isinstance(registry, Registry) and registry.group == group
    assert builtin in registry.names() and registry.get(builtin) is not None
    state = registry.snapshot()
    try:
        with pytest.raises(ConfigError, match=f"named '{builtin}' is already registered"):
            if group == "femcal.effects":
                from femcal.effects import Effect, register_effect

                register_effect(
                    type(
                        "Impostor",
                        (Effect,),
                        {"name": builtin, "kind": "series", "load_cases": ("Flexion",)},
                    )
                )
            else:
                registry.register(builtin, type("Impostor", (), {}))
    finally:
        registry.restore(state)
    assert registry.get(builtin).__name__ != "Impostor"


def test_the_solver_registry_and_its_module_functions():
    from femcal.fe import available_solvers, get_solver, make_solver, solver_registry
    from femcal.fe.calculix import CalculixDisc

    assert solver_registry.group == "femcal.solvers"
    assert available_solvers() == solver_registry.names() and "calculix" in available_solvers()
    assert solver_registry.get("calculix") is CalculixDisc
    assert type(make_solver("calculix")) is CalculixDisc is type(get_solver("calculix"))
    with pytest.raises(ConfigError, match=r"Unknown FE solver 'abaqus'; choose one of calculix"):
        make_solver("abaqus")
    with pytest.raises(ConfigError, match="An FE solver named 'calculix' is already registered"):
        solver_registry.register("calculix", type("Other", (), {}))


def test_module_functions_are_the_registries():
    from femcal.calibration import available_calibrators, get_calibrator
    from femcal.surrogates import available_surrogates, get_surrogate, make_surrogate
    from femcal.surrogates.nn import NeuralSurrogate

    registries = _registries()
    assert available_calibrators() == registries["femcal.calibrators"][0].names()
    assert get_calibrator("pgd") is registries["femcal.calibrators"][0].get("pgd")
    assert available_surrogates() == registries["femcal.surrogates"][0].names()
    assert get_surrogate("nn") is NeuralSurrogate and NeuralSurrogate.registry_name == "nn"
    with pytest.raises(ConfigError, match=r"Unknown surrogate 'lightgmb'; .* mean 'lightgbm'\?"):
        make_surrogate("lightgmb")
