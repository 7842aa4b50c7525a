"""The CogniMap3D pipeline as one pure step function (paper, Fig. 2): :func:`prepare` (host) ->
:func:`step` (``run_sequence = jit(lax.scan(step))``) -> :func:`collect` (host) -> :mod:`cm3d.outputs`;
:func:`run` does it for several visits with one memory bank. Modules: docs/pipeline.md."""

from cm3d.pipeline.config import PipelineConfig, TrackCheckConfig, bank_config, config_for, small_config  # noqa: F401
from cm3d.pipeline.landmarks import advance_landmarks, landmark_observations, seed_landmarks  # noqa: F401
from cm3d.pipeline.memory_graph import (MemoryStep, RecallReport, memory_refinement, memory_surface,  # noqa: F401
                                        recall_verify_update, sequence_query, window_entry)
from cm3d.pipeline.prepare import (Features, Inputs, pad_inputs, padded_length, piece_spec, prepare,  # noqa: F401
                                   prepare_chunks, scale_intrinsics)
from cm3d.pipeline.photometric import PhotometricCheck, check_refinement, warp_errors  # noqa: F401
from cm3d.pipeline.run import (RunReport, SequenceResult, WindowRecord, collect, initial_state,  # noqa: F401
                               prior_result, recalled_earlier_map, run)
from cm3d.pipeline.state import (Landmarks, MapState, MemoryCursor, Window, begin_sequence,  # noqa: F401
                                 empty_bank_host, empty_landmarks, empty_window, fresh_state, init_state)
from cm3d.pipeline.step import (StepOutputs, WindowResult, _run_sequence, buffer_frame, run_frames,  # noqa: F401
                                run_sequence, static_mask, step, step_jit, window_end)
from cm3d.pipeline.window import (factor_graph, gate_refinement, prior_consistent_tracks,  # noqa: F401
                                  rescale_window, structure_only_cost)
