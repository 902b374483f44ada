"""ddp: Dream Diffusion Policy -- diffusion policies that dream through OOD disturbances."""

from ddp.registry import list_plugins, register

__version__ = "0.1.0"

__all__ = ["build", "register", "list_plugins", "load_recipe", "__version__"]


def __getattr__(name):
    # build/load_recipe pull in torch-heavy modules: import them on first use.
    if name == "build":
        from ddp.experiment import build

        return build
    if name == "load_recipe":
        from ddp.recipe import load_recipe

        return load_recipe
    raise AttributeError(f"module 'ddp' has no attribute '{name}'")
