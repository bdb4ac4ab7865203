"""Every shell command in README.md and docs/*.md runs as written, in order, from a fresh checkout.

The ```bash blocks of each page run top to bottom, README.md first and then the docs pages, in
one scratch directory holding the repository's `examples/` (so relative paths resolve as in the
docs, and a page may use what README's commands made), with `python` and `dofjax` this
interpreter's. Only sizes shrink (`SMALLER`: fewer samples, smaller images), never the commands
or their order; the quick start's install prefix is what the test environment already did, and
its test command is this suite (checked equal to `.ci/run`'s instead). `dofjax view` serves
forever: it runs until it prints `ready`, then gets Ctrl-C and must exit cleanly. Exit status 3
(a fit that ran but is flagged untrustworthy, as tiny images may be) counts as running.
"""

import os
import queue
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES = ["README.md"] + sorted(
    os.path.join("docs", f) for f in os.listdir(os.path.join(ROOT, "docs")) if f.endswith(".md"))

# (pattern, replacement): sizes only, applied to every command
SMALLER = [
    (r"--count \d+", "--count 2 --size 32x24"),
    (r"--width 1024 --height 768", "--width 256 --height 192"),
]
INSTALL = re.compile(r"^python3 -m venv \.venv && \.venv/bin/pip install -e \"?\.(\[\w+\])?\"? && "
                     r"\.venv/bin/")


def bash_blocks(page: str) -> list[str]:
    """The commands of `page`'s ```bash blocks, in order (continuation lines joined, comments
    and blank lines dropped)."""
    with open(os.path.join(ROOT, page)) as f:
        text = f.read()
    commands = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, re.MULTILINE | re.DOTALL):
        block = block.replace("\\\n", " ")
        for line in block.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line and not line.startswith("#"):
                commands.append(line)
    return commands


def _ci_test_command() -> str:
    with open(os.path.join(ROOT, ".ci", "run")) as f:
        return next(line.split(" 2>&1")[0].strip() for line in f
                    if line.startswith("python -m pytest"))


def _runnable(command: str) -> str | None:
    """`command` as the test runs it: None for the test suite itself."""
    install = INSTALL.match(command)
    if install:
        command = command[install.end():]
    if command.startswith("python -m pytest"):
        assert command == _ci_test_command(), "README's test command differs from .ci/run's"
        return None
    for pattern, replacement in SMALLER:
        command = re.sub(pattern, replacement, command)
    return command


def _environment(bin_dir: str) -> dict:
    env = dict(os.environ, PATH=bin_dir + os.pathsep + os.environ["PATH"], CI="true",
               PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_ENABLE_X64", None)  # as a user runs them: float32
    return env


def _serve_until_ready(command: str, cwd: str, env: dict) -> None:
    """Start a server command, wait (at most 240 s, even if it prints nothing) for "ready", then
    stop it with Ctrl-C."""
    proc = subprocess.Popen(shlex.split(command) + ["--port", "0"], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: queue.Queue = queue.Queue()

    def read():
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)  # end of output: the process ended

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    seen = []
    ready = False
    deadline = time.monotonic() + 240
    try:
        while not ready:
            try:
                line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                break
            if line is None:
                break
            seen.append(line)
            ready = "ready" in line
        assert ready, (
            f"{command}: printed no 'ready' (it exited, or 240 s passed):\n" + "".join(seen))
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            code = None
        finally:
            reader.join(10)
            if not reader.is_alive():
                proc.stdout.close()
        while not lines.empty():
            seen.append(lines.get() or "")
    assert code is not None, f"{command}: did not stop within 30 s of Ctrl-C:\n" + "".join(seen)
    assert code in (0, -signal.SIGINT, 130), "".join(seen)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    """The directory the pages' commands run in, and their environment."""
    root = tmp_path_factory.mktemp("docs")
    shutil.copytree(os.path.join(ROOT, "examples"), root / "examples")
    bin_dir = root / "bin"
    bin_dir.mkdir()
    # a wrapper, not a symlink: a symlinked venv interpreter outside the venv loses its packages
    (bin_dir / "python").write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    (bin_dir / "python").chmod(0o755)
    dofjax_cli = shutil.which("dofjax", path=os.path.dirname(sys.executable))
    assert dofjax_cli, "the dofjax console script is not installed next to this interpreter"
    os.symlink(dofjax_cli, bin_dir / "dofjax")
    return root, _environment(str(bin_dir))


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in PAGES if bash_blocks(p)])
def test_documented_commands_run_as_written(page, scratch):
    cwd, env = scratch
    for command in bash_blocks(page):
        runnable = _runnable(command)
        if runnable is None:
            continue
        if runnable.startswith("dofjax view") or " view " in runnable:
            _serve_until_ready(runnable, str(cwd), env)
            continue
        done = subprocess.run(runnable, shell=True, cwd=cwd, env=env, capture_output=True,
                              text=True, timeout=600)
        assert done.returncode in (0, 3), (
            f"{page}: `{command}` (run as `{runnable}`) exited {done.returncode}:\n"
            f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
