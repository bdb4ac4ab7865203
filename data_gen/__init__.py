"""Synthetic data for depth from defocus: scenes, cameras and targets with known ground truth.

``python -m data_gen --out DIR --count N --seed S [--config CONFIG.json]`` writes, per sample, the
scene JSON, the sharp RGB-D EXR, the (noisy) target EXR with the truth as ``dofjax:`` attributes,
and one line of ``DIR/manifest.jsonl``. See `data_gen._run` for the layout and resume rules,
`data_gen._kinds` for the scene kinds, `data_gen._noise` for the noise models and
`default_config.json` for every configuration key.
"""

from ._config import (
    KINDS as KINDS,
    ConfigError as ConfigError,
    default_config as default_config,
    load_config as load_config,
    validate_config as validate_config,
)
from ._kinds import KindScene as KindScene, make_scene as make_scene
from ._noise import (
    NOISE_MODELS as NOISE_MODELS,
    apply_noise as apply_noise,
    draw_noise_params as draw_noise_params,
    quantize_srgb8 as quantize_srgb8,
    sample_rng as sample_rng,
)
from ._run import (
    RunSummary as RunSummary,
    build_sample as build_sample,
    collect as collect,
    dry_run as dry_run,
    finished_record as finished_record,
    generate_sample as generate_sample,
    plan_sample as plan_sample,
    read_manifest as read_manifest,
    run as run,
    sample_files as sample_files,
    write_manifest as write_manifest,
)
