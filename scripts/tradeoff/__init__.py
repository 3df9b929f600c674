"""The pieces of ``scripts/bench_tradeoff.py`` (the speed–accuracy trade, docs/tradeoff.md).

- :mod:`tradeoff.scenes`: the benchmark scenes, settings and one error run of a setting;
- :mod:`tradeoff.energy`: the one-step energy probe (geometric stiffness, SPEC §4);
- :mod:`tradeoff.timing`: interleaved, repeated timing of both paths, the quiet-machine wait;
- :mod:`tradeoff.choose`: the Pareto fronts, the presets' rule and which scenes vote;
- :mod:`tradeoff.report`, :mod:`tradeoff.plots`: docs/tradeoff.md and its figures.
"""
