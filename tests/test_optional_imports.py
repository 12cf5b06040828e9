"""``import torchrl_options`` needs the core dependencies only.

The optional parts (ale-py for Atari, Ray for sweeps, Hydra/omegaconf for the recipes, matplotlib for plots,
h5py for HDF5 trajectory files, minigrid for the MiniGrid levels) are imported inside the functions that use them.
A subprocess hides them, as if they were not installed, and imports every module of the package and every public
name of every subpackage.
"""
import os
import subprocess
import sys
import textwrap

OPTIONAL = ("ale_py", "ray", "hydra", "omegaconf", "matplotlib", "h5py", "minigrid")

# A module set to None in sys.modules is one Python treats as absent: ``import x`` raises ModuleNotFoundError and
# ``importlib.util.find_spec("x")`` returns None, as libraries probing for optional packages expect. A meta path
# finder refuses any submodule too, in case something imports ``x.y`` by a route that skips the parent.
_SCRIPT = textwrap.dedent(
    """
    import importlib
    import importlib.abc
    import pkgutil
    import sys

    OPTIONAL = {optional!r}

    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in OPTIONAL:
                raise ModuleNotFoundError(f"{{name}} is hidden by the test", name=name)
            return None

    for name in OPTIONAL:
        sys.modules[name] = None
    sys.meta_path.insert(0, Refuse())
    for name in OPTIONAL:  # the hiding works
        try:
            importlib.import_module(name)
        except ImportError:
            pass
        else:
            raise SystemExit(f"{{name}} was not hidden")

    import torchrl_options

    for name in torchrl_options.__all__:
        getattr(torchrl_options, name)
    modules = ["torchrl_options"]
    for info in pkgutil.walk_packages(torchrl_options.__path__, "torchrl_options."):
        module = importlib.import_module(info.name)
        modules.append(info.name)
        for name in getattr(module, "__all__", ()):
            getattr(module, name)  # every public name resolves
    loaded = sorted(k for k, v in sys.modules.items() if k.split(".")[0] in OPTIONAL and v is not None)
    if loaded:
        raise SystemExit(f"optional modules were loaded: {{loaded}}")
    print(len(modules), "modules")
    """
).format(optional=OPTIONAL)


def test_import_without_optional_dependencies():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run(
        [sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, cwd=root, timeout=600
    )
    assert result.returncode == 0, result.stdout + result.stderr
    count = int(result.stdout.split()[-2])
    assert count > 40, result.stdout  # it walked the whole package, not only the top level
