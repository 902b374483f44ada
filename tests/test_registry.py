"""The registry: explicit names, duplicates rejected, listing, entry-point plugins."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from dataclasses import dataclass

import pytest

import ddp
from ddp import registry
from ddp.detectors.never import NeverDetector
from ddp.errors import PluginError, RecipeError


def test_builtin_parts_are_registered():
    assert {"dp3", "state_mlp"} <= set(ddp.list_plugins("encoder"))
    assert {"unet1d", "unet1d_wm"} <= set(ddp.list_plugins("denoiser"))
    assert {"ddpm", "ddim", "consistency_flow"} <= set(ddp.list_plugins("scheduler"))
    assert "synthetic_reach" in ddp.list_plugins("dataset")
    assert ddp.list_plugins("scheduler", "dd*") == ["ddim", "ddpm"]
    assert set(ddp.list_plugins()) == set(registry.KINDS)


def test_register_lookup_and_duplicate():
    @dataclass
    class Cfg:
        tau: float = 0.1

    try:
        @ddp.register("detector", "test_threshold")
        class Threshold(NeverDetector):
            """A test detector."""

            Config = Cfg

        plugin = registry.get("detector", "test_threshold")
        assert plugin.factory is Threshold and plugin.config_cls is Cfg and plugin.summary == "A test detector."
        with pytest.raises(PluginError, match="registered twice"):
            ddp.register("detector", "test_threshold")(Threshold)
    finally:
        registry.unregister("detector", "test_threshold")
    assert "test_threshold" not in ddp.list_plugins("detector")


def test_register_requires_config_dataclass():
    with pytest.raises(PluginError, match="must declare a config dataclass"):
        ddp.register("tracker", "no_config")(type("NoConfig", (), {}))


def test_unknown_kind_and_name():
    with pytest.raises(PluginError, match="unknown plugin kind 'encoders'; did you mean 'encoder'"):
        ddp.list_plugins("encoders")
    with pytest.raises(RecipeError, match=r"unknown encoder 'dp4'; did you mean 'dp3'\? \(known: dp3, state_mlp"):
        registry.get("encoder", "dp4")


def _install_fake_dist(site, dist, module, body, ep_name):
    """Lay a package out as pip installs it: module + <dist>.dist-info with entry_points.txt."""
    (site / f"{module}.py").write_text(textwrap.dedent(body))
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[ddp.plugins]\n{ep_name} = {module}\n")
    (info / "RECORD").write_text("")


def test_entry_point_plugins_are_discovered_and_failures_named(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    _install_fake_dist(
        site, "ddp_extra_detector", "ddp_extra_detector",
        """
        from dataclasses import dataclass
        import ddp
        from ddp.detectors.never import NeverDetector

        @dataclass
        class NoisyConfig:
            sigma: float = 0.5

        @ddp.register("detector", "noisy_threshold", config=NoisyConfig)
        class NoisyThreshold(NeverDetector):
            '''Flags OOD at random (an entry-point test plugin).'''
        """,
        "noisy",
    )
    _install_fake_dist(site, "ddp_broken", "ddp_broken_plugin", textwrap.dedent("""
        import ddp
        from ddp.detectors.never import NeverDetector, NeverConfig

        ddp.register("detector", "half_registered", config=NeverConfig)(type("Half", (NeverDetector,), {}))
        raise ImportError('needs libfoo')
        """), "broken")
    script = textwrap.dedent(
        """
        import warnings
        warnings.simplefilter("always")
        import ddp
        from ddp import registry
        with warnings.catch_warnings(record=True) as caught:
            names = ddp.list_plugins("detector")
        print("NAMES", names)
        print("WARN", [str(w.message) for w in caught])
        print("CFG", registry.get("detector", "noisy_threshold").config_cls.__name__)
        try:
            registry.get("detector", "noisy_treshold")
        except Exception as err:
            print("ERR", err)
        """
    )
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True).stdout
    assert "'noisy_threshold'" in out.split("NAMES")[1].splitlines()[0]
    assert "half_registered" not in out.split("NAMES")[1].splitlines()[0]  # a failed plugin leaves no part
    assert "ddp plugin 'broken' (ddp_broken_plugin) failed to import: ImportError: needs libfoo" in out
    assert "CFG NoisyConfig" in out
    assert "did you mean 'noisy_threshold'" in out and "failed to import: broken" in out


def test_a_plugin_cannot_take_over_a_builtin_name(tmp_path):
    """An entry-point plugin that registers ('detector', 'discrepancy') fails to register (named in a warning),
    whichever kind is looked up first; the built-ins of that kind all stay."""
    site = tmp_path / "site"
    site.mkdir()
    _install_fake_dist(
        site, "ddp_hijack", "ddp_hijack",
        """
        from dataclasses import dataclass
        import ddp
        from ddp.detectors.never import NeverDetector

        @dataclass
        class C:
            pass

        @ddp.register("detector", "discrepancy", config=C)
        class Hijack(NeverDetector):
            '''Claims a built-in name.'''
        """,
        "hijack",
    )
    script = textwrap.dedent(
        """
        import warnings
        warnings.simplefilter("always")
        from ddp import registry
        with warnings.catch_warnings(record=True) as caught:
            registry.get("encoder", "dp3")  # another kind first
        print("WARN", [str(w.message) for w in caught])
        print("MODULE", registry.get("detector", "discrepancy").module)
        print("NAMES", registry.list_plugins("detector"))
        """
    )
    root = Path(__file__).resolve().parents[1]  # this checkout's ddp, not another install's
    env = {"PYTHONPATH": f"{site}{os.pathsep}{root}", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True).stdout
    assert "ddp plugin 'hijack' (ddp_hijack) failed to import" in out and "registered twice" in out
    assert "MODULE ddp.detectors.discrepancy" in out
    assert "'never'" in out.split("NAMES")[1] and "'oracle'" in out.split("NAMES")[1]


def test_importing_evaluation_loads_no_env_plugin_or_simulator():
    """Plugins are imported on the registry's first lookup, not by importing ddp.evaluate or the env base."""
    import subprocess
    import sys

    code = ("import sys, ddp.evaluate, ddp.envs.chunked; print(' '.join(sorted(m for m in sys.modules if m.startswith("
            "('metaworld', 'robosuite', 'gymnasium_robotics', 'franky', 'ddp.envs.', 'ddp.detectors.', 'ddp.trackers.')))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["ddp.envs.chunked"]
    code = "import sys; from ddp import registry; registry.get('env', 'synthetic_reach'); print('ddp.envs.metaworld' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "True"  # the first env lookup loads the built-in env modules


def test_a_failing_recipe_plugin_leaves_the_builtins_it_imported(tmp_path):
    """Its own parts go; the built-ins it imported (and that registered during its import) stay: their
    modules stay imported and would never register again (every kind was left empty)."""
    (tmp_path / "half_plugin.py").write_text(textwrap.dedent("""
        import ddp
        from ddp import registry
        from ddp.detectors.never import NeverDetector, NeverConfig

        registry.get("scheduler", "ddim")  # a lookup while importing loads every built-in kind
        ddp.register("detector", "half_registered", config=NeverConfig)(type("Half", (NeverDetector,), {}))
        raise ImportError("needs libfoo")
        """))
    script = textwrap.dedent("""
        from ddp import registry
        from ddp.errors import RecipeError
        try:
            registry.import_plugin_modules(["half_plugin"])
        except RecipeError as err:
            print("ERR", err)
        print("SCHED", registry.list_plugins("scheduler"))
        print("DET", registry.list_plugins("detector"))
        """)
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True).stdout
    assert "cannot import plugin module 'half_plugin': ImportError: needs libfoo" in out
    assert "'ddim'" in out.split("SCHED")[1].splitlines()[0]
    detectors = out.split("DET")[1].splitlines()[0]
    assert "'discrepancy'" in detectors and "half_registered" not in detectors


def test_a_plugin_imported_before_any_lookup_cannot_take_a_builtin_name(tmp_path):
    """A recipe's plugins: module (or user code) registering a built-in's name before the first lookup took
    it: then the built-in's own registration failed, and with it every later lookup in the process."""
    (tmp_path / "early_plugin.py").write_text(textwrap.dedent("""
        from dataclasses import dataclass
        import ddp
        from ddp.detectors.never import NeverDetector

        @dataclass
        class C:
            pass

        @ddp.register("detector", "oracle", config=C)
        class Early(NeverDetector):
            '''Claims a built-in name before the built-ins load.'''
        """))
    script = textwrap.dedent("""
        from ddp import registry
        from ddp.errors import DDPError
        from ddp.schema import validate
        try:
            validate({"name": "x", "plugins": ["early_plugin"]}, "plugged.yaml")
        except DDPError as err:
            print("ERR", err)
        validate({"name": "x"}, "other.yaml")  # an unrelated recipe still builds
        print("MODULE", registry.get("detector", "oracle").module)
        """)
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{Path(__file__).resolve().parents[1]}"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "detector 'oracle' is registered twice: by ddp.detectors.oracle and by early_plugin" in out.stdout
    assert "MODULE ddp.detectors.oracle" in out.stdout


def test_plugin_names_are_strings():
    with pytest.raises(PluginError, match="plugin names are non-empty strings; .* gave 3"):
        ddp.register("detector", 3, config=dataclass(type("C", (), {})))(type("D", (NeverDetector,), {}))
