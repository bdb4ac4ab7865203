"""Synthetic data for depth from defocus: scenes, cameras and targets with known ground truth.

``python -m data_gen --out DIR --count N --seed S [--config CONFIG.json]`` writes, per sample, the
scene JSON, the sharp RGB-D EXR, the (noisy) target EXR with the truth as ``dofjax:`` attributes,
and one line of ``DIR/manifest.jsonl``. See `data_gen._run` for the layout and resume rules,
`data_gen._kinds` for the scene kinds, `data_gen._noise` for the noise models and
`default_config.json` for every configuration key.
"""

from ._config import KINDS as KINDS
from ._config import ConfigError as ConfigError
from ._config import default_config as default_config
from ._config import load_config as load_config
from ._config import validate_config as validate_config
from ._kinds import KindScene as KindScene
from ._kinds import make_scene as make_scene
from ._noise import NOISE_MODELS as NOISE_MODELS
from ._noise import apply_noise as apply_noise
from ._noise import draw_noise_params as draw_noise_params
from ._noise import quantize_srgb8 as quantize_srgb8
from ._noise import sample_rng as sample_rng
from ._run import RunSummary as RunSummary
from ._run import build_sample as build_sample
from ._run import collect as collect
from ._run import dry_run as dry_run
from ._run import finished_record as finished_record
from ._run import generate_sample as generate_sample
from ._run import plan_sample as plan_sample
from ._run import read_manifest as read_manifest
from ._run import run as run
from ._run import sample_files as sample_files
from ._run import write_manifest as write_manifest
