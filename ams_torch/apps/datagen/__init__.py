"""Dataset generation: simulate a recipe's sequences into sharded HDF5 files, resumably.

The job list of a recipe (:mod:`ams_torch.apps.recipe`) is its batch groups: group g simulates
sequences g·batch … (g+1)·batch − 1 as one batched run (one groom, B head motions). Shard i of
n (0-based, 0 <= i < n) takes the groups with g % n == i, so every sharding simulates the same
groups the same way and any shard on any machine produces the same data.

Crash safety. Each finished group is first written to its own file under
``OUT/.partial/<shard stem>/group-<g>.h5`` (written to a temporary name, renamed when complete);
when every group of the shard is there, they are copied into ``OUT/<name>-shard-<i>-of-<n>.h5``
(again temporary name, then rename) and the work folder is removed. A run that is killed keeps
its finished groups; the next run deletes any temporary file, skips the finished groups and
simulates the rest. Nothing partial is ever renamed into place.

One run per folder. A run holds an exclusive ``flock`` on ``OUT/.lock`` (pid, host and start
time written in it) for its whole length; a second run on the same folder refuses with a
message naming the holder (or waits for it with ``wait=True``). The kernel drops the lock when
its process dies, so a killed run never leaves a stale lock. A folder that holds a dataset of
another recipe or another shard count is refused.

Backends: :func:`generate` (this process, one or several shards one after the other) and
:func:`generate_ray` (one Ray task per batch group, one GPU each where the cluster has GPUs).

Guides alone: for each count of ``[store].guides`` the batch group also simulates those guide
strands alone (:func:`guide_simulators`) in the same frame loop. Suites: :func:`generate_suite`
generates a folder of recipes, each into its own dataset folder.
"""
from ams_torch.apps.datagen.ray_backend import generate_ray, start_local_ray
from ams_torch.apps.datagen.shards import (LOCK_FILE, OutputError, generate, generate_shard, lock_holder, output_lock,
                                           parse_shard, shard_filename)
from ams_torch.apps.datagen.simulate import guide_order, guide_simulators, nonfinite_inputs, simulate_group
from ams_torch.apps.datagen.suite import generate_suite, suite_recipes

__all__ = ["shard_filename", "simulate_group", "generate_shard", "generate", "generate_ray", "start_local_ray",
           "parse_shard", "output_lock", "lock_holder", "OutputError", "LOCK_FILE", "nonfinite_inputs",
           "guide_order", "guide_simulators", "generate_suite", "suite_recipes"]
