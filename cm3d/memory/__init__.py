"""The cognitive memory bank: an immutable pytree of static maps, recalled by descriptors and verified
by geometry (the paper's memory).

Modules, in the order a query meets them: :mod:`~cm3d.memory.config` (``MemoryConfig``, errors),
:mod:`~cm3d.memory.entry` (a sequence's map entry: static cloud, keyframes, 3D keypoints),
:mod:`~cm3d.memory.bank` (the bank pytree and its slots), :mod:`~cm3d.memory.recall` (hashed 2D
recall), :mod:`~cm3d.memory.matching` and :mod:`~cm3d.memory.verify` (keypoint matching -> Sim(3)
RANSAC -> ICP validation -> decision), :mod:`~cm3d.memory.acceptance` (the acceptance model),
:mod:`~cm3d.memory.identify` (recall + verification), :mod:`~cm3d.memory.update` (relocalise, merge,
:func:`remember`), :mod:`~cm3d.memory.io` (save / load) and :mod:`~cm3d.memory.transaction` (writes
that concurrent runs cannot lose). Every visit has its own unknown scale, so
all transforms are Sim(3). The geometry (RANSAC, ICP, grid search) is :mod:`cm3d.solvers` and
:mod:`cm3d.ops.grid`.
"""

from cm3d.memory.acceptance import acceptance_features, acceptance_score, accepts, model_accepts
from cm3d.memory.bank import (
    GRID_CELL,
    MapCloud,
    MemoryBank,
    add_map,
    capacities,
    empty,
    global_table,
    insert_map,
    map_cloud,
    map_counts,
    remove_map,
    stored_entry,
    without_map,
)
from cm3d.memory.config import (
    ACCEPTANCE_FEATURES,
    CAPACITY_FIELDS,
    DESCRIPTOR_3D_DIMS,
    MemoryConfig,
    MemoryFileError,
    MemoryFullError,
    config_from_dict,
    with_capacities,
)
from cm3d.memory.entry import (
    Keypoints,
    MapEntry,
    SequenceCloud,
    build_entry,
    cloud_descriptor,
    downsample_to_capacity,
    evenly_spread,
    fit_keypoints,
    lift_keypoints,
    sequence_cloud,
)
from cm3d.memory.identify import Identification, identify
from cm3d.memory.io import FORMAT_VERSION, MAGIC, READ_VERSIONS, StoredBank, load, read, save
from cm3d.memory.matching import keypoint_clusters, match_keypoints, up_axis
from cm3d.memory.recall import Recall, recall, select_keyframes
from cm3d.memory.transaction import (CommitReport, MapWrite, Snapshot, check_bank_path, commit, merge_banks, modify,
                                    snapshot)
from cm3d.memory.update import Report, merge_evenly, relocalize, remember, update_map
from cm3d.memory.verify import Verification, even_subsample, verify

__all__ = [
    "ACCEPTANCE_FEATURES", "CAPACITY_FIELDS", "CommitReport", "DESCRIPTOR_3D_DIMS", "FORMAT_VERSION", "GRID_CELL", "MAGIC", "READ_VERSIONS",
    "Identification", "Keypoints", "MapCloud", "MapWrite", "MapEntry", "MemoryBank", "MemoryConfig", "MemoryFileError",
    "MemoryFullError", "Recall", "Report", "SequenceCloud", "Snapshot", "StoredBank", "Verification", "acceptance_features",
    "acceptance_score", "accepts", "add_map", "build_entry", "capacities", "check_bank_path", "commit", "cloud_descriptor", "config_from_dict",
    "downsample_to_capacity", "empty", "even_subsample", "evenly_spread", "fit_keypoints", "global_table",
    "identify", "insert_map", "keypoint_clusters", "lift_keypoints", "load", "map_cloud", "map_counts", "match_keypoints",
    "merge_banks", "merge_evenly", "modify", "read", "model_accepts", "recall", "relocalize", "remember", "remove_map", "save",
    "select_keyframes", "sequence_cloud", "snapshot", "stored_entry", "up_axis", "update_map", "verify", "with_capacities", "without_map",
]
