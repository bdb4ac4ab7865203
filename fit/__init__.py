"""Command-line scripts around `dofjax.fit_focus` (thin: parse, load, one library call, print/save).

- `python -m fit.demo`: render an example scene, make a target with known focus and aperture,
  recover them from a wrong guess and print true vs recovered.
- `python -m fit.recover TARGET.exr --sharp SHARP.exr | --scene SCENE.json`: fit one target.
- `python -m fit.sweep OUT_DIR/manifest.jsonl`: fit a data_gen data set, tables and plots.
"""

from ._table import format_table as format_table, result_rows as result_rows
