"""pipeline.yaml as the API reads it: the schema of a run (:class:`PipelineConfig` and its sections), the
presets, and the functions that load and check a config, as the command line, ``run`` and ``report`` use them.

>>> from codedvideo.api.config import PipelineConfig, preset_options
>>> PipelineConfig().reconstruct.method
'omp'
>>> preset_options("fast")
'--stride 2'

A value out of its bounds raises :class:`codedvideo.ConfigError` naming its key (:func:`validated`,
:func:`load_config`).
"""

from __future__ import annotations

from codedvideo.engine.config import (
    BUMP_CODES,
    P_CODES,
    PRESET_KEYS,
    PRESETS,
    CodeConfig,
    DictionaryConfig,
    NoiseConfig,
    OutputConfig,
    PipelineConfig,
    ReconstructConfig,
    ReportConfig,
    SceneConfig,
    DEFAULT_CACHE,
    DEFAULT_CACHE_BUDGET,
    auto_tolerance,
    default_config_path,
    load_config,
    preset_options,
    resolve_preset,
    validated,
)

__all__ = ["BUMP_CODES", "DEFAULT_CACHE", "DEFAULT_CACHE_BUDGET", "P_CODES", "PRESETS", "PRESET_KEYS", "CodeConfig",
           "DictionaryConfig", "NoiseConfig", "OutputConfig", "PipelineConfig", "ReconstructConfig", "ReportConfig",
           "SceneConfig", "auto_tolerance", "default_config_path", "load_config", "preset_options", "resolve_preset",
           "validated"]
