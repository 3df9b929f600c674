"""Learned guide-to-dense methods of the benchmark (each an :class:`~baselines.protocol.Interpolator`
registered under its built-in name when this package is imported)."""
