"""The documentation site builds without warnings (`mkdocs build --strict`, as CI runs it).

mkdocstrings reads the docstrings statically (griffe), so this neither imports nor compiles JAX
programs; it needs the `docs` dependencies, which the `test` extra includes.
"""

import importlib.util
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# mkdocs, the Material theme, mkdocstrings and its Python handler
_MISSING = [m for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers")
            if importlib.util.find_spec(m) is None]


@pytest.mark.skipif(bool(_MISSING), reason=f"docs dependencies not installed "
                    f"({', '.join(_MISSING)}): pip install -e '.[docs]'")
def test_mkdocs_build_strict(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
         "-f", os.path.join(ROOT, "mkdocs.yml"), "-d", str(tmp_path / "site")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    assert (tmp_path / "site" / "api" / "index.html").is_file()
