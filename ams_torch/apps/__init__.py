"""Applications built on the library: head motions, scene files, dataset recipes and generation,
dataset reading and validation, rendering, parameter identification through rollouts, and the
``ams-torch`` command line.

The top layer: it may import every other subpackage. Its modules load on first access
(``ams_torch.apps.scene``), so ``import ams_torch`` stays light (no h5py, no matplotlib).
"""
import importlib

_MODULES = ("motion", "scene", "recipe", "datagen", "data", "render", "cli", "identify")

__all__ = list(_MODULES)


def __getattr__(name):
    if name in _MODULES:
        return importlib.import_module(f"ams_torch.apps.{name}")
    raise AttributeError(f"module 'ams_torch.apps' has no attribute {name!r}")
