"""The benchmark's built-in methods: importing this module registers them in
:data:`baselines.protocol.BUILTINS`."""
from baselines import learned  # noqa: F401  (registers the learned methods)
