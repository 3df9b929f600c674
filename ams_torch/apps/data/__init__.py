"""Simulation datasets on disk (HDF5): layout, checksums, validation and a torch ``Dataset``.

``ams-torch generate`` (:mod:`ams_torch.apps.datagen`) writes one HDF5 file per shard; the layout is
documented in ``docs/dataset_format.md`` (format version 3; version 2 is still read). In short, every
sequence is a group ``seq_{index:06d}`` holding ``positions`` (F, S, N, 3) (float32 or float16,
metres, world frame, one chunk per frame), the head pose per frame, the rest groom and its root
binding, optional velocities (the simulator's and the motion's), guide strands (the dense run's
copies and the guides simulated alone), its draws as JSON attributes, per-array ``units``/``dims``/``sha256``
attributes and per-frame SHA-256 digests; the file holds the scene's head and collider meshes
(``/scene``) and the train/valid/test masks (``/mask``).

- :func:`validate`: check a dataset folder (every file, and that the files make one complete
  dataset: one recipe, one shard count, every shard, every sequence exactly once).
- :class:`HairSequenceDataset`: windows of frames for training, with lazy per-process file
  handles (``DataLoader(num_workers > 0)``), split selection and checksum verification.
"""
from ams_torch.apps.data.dataset import (HairSequenceDataset, read_dataset_sequence, read_scene_meshes,
                                         stored_pinned_counts)
from ams_torch.apps.data.format import (ARRAYS, FORMAT, FORMAT_VERSION, FRAME_DIGESTS, FRAMED, LOCK_FILE, PER_FRAME,
                                        PER_SEQUENCE, POSE_FIELDS, READ_VERSIONS, SHARD_FILE, SPLITS, DatasetError,
                                        alone_name, array_digest, check_together, list_datasets, list_files,
                                        lock_holder, read_header, sequence_checksum, sequence_name)
from ams_torch.apps.data.validation import ValidationReport, validate, validate_file

__all__ = ["FORMAT", "FORMAT_VERSION", "DatasetError", "ValidationReport", "sequence_name", "array_digest",
           "sequence_checksum", "validate_file", "validate", "list_files", "read_header", "check_together",
           "lock_holder", "read_scene_meshes", "read_dataset_sequence", "HairSequenceDataset", "PER_FRAME",
           "PER_SEQUENCE", "FRAMED", "ARRAYS", "SPLITS", "SHARD_FILE", "LOCK_FILE", "FRAME_DIGESTS", "POSE_FIELDS",
           "READ_VERSIONS", "alone_name", "stored_pinned_counts", "list_datasets"]
