"""Start the viewer: bind the port first (a port in use fails before any work), load and
render the input, compile the live defocus, say "ready", then serve with uvicorn until Ctrl-C
(the exact method's program goes on compiling beside it; its first frame waits for it)."""

from __future__ import annotations

import errno
import os
import socket
import sys
import threading
import time
import webbrowser

from ._app import MAX_UPLOAD, create_app
from ._engine import Engine
from ._source import check_input, load_source


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on (host, port); port 0 picks a free one. OSError names the port."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(128)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise OSError(f"port {port} on {host} is in use: choose another with --port, or "
                          "leave --port out for a free one") from None
        raise OSError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"http://{f'[{host}]' if ':' in host else host}:{port}/"


def serve(path: str, *, host: str = "127.0.0.1", port: int = 0, open_browser: bool = False,
          target: str | None = None, width=None, height=None, layers=None, spp: int = 1,
          sample=None, window=None, max_upload: int = MAX_UPLOAD, fit_options=None,
          out=sys.stdout) -> int:
    """Run `dofjax view` (blocks until interrupted); returns the exit status."""
    import uvicorn

    import dofjax

    start = time.perf_counter()
    engine = None
    check_input(path)
    if target is not None and not os.path.isfile(target):
        raise FileNotFoundError(f"{target}: no such file")
    sock = bind(host, port)
    url = url_of(sock)
    # This process is the viewer's own: let XLA reuse large frames' memory instead of faulting
    # it in on every call (before the first computation; large live frames render faster).
    dofjax.tune_host_memory()
    try:
        print(f"dofjax view: {url} (loading {path})", file=out, flush=True)
        if host not in ("127.0.0.1", "localhost", "::1"):
            print(f"dofjax view: listening on {host}: whoever can reach this address can use "
                  "the viewer and upload targets to it", file=out, flush=True)
        source = load_source(path, width=width, height=height, layers=layers, spp=spp,
                             sample=sample)
        engine = Engine(source, window=window, fit_options=fit_options)
        if target is not None:
            engine.set_target(dofjax.read_image(target), target)
        h, w = source.depth.shape
        print(f"dofjax view: {source.name}, {w}x{h}, rendered in "
              f"{time.perf_counter() - start:.1f} s; compiling the defocus", file=out, flush=True)
        engine.warm_up(background=True)
        app = create_app(engine, max_upload=max_upload)
        print(f"dofjax view: ready at {url} ({time.perf_counter() - start:.1f} s); Ctrl-C stops",
              file=out, flush=True)

        def report():
            engine.final_ready.wait()
            print(f"dofjax view: the exact method is compiled too "
                  f"({time.perf_counter() - start:.1f} s)", file=out, flush=True)

        threading.Thread(target=report, daemon=True).start()
        if open_browser:
            webbrowser.open(url)
        config = uvicorn.Config(app, log_level="warning", lifespan="off")
        server = uvicorn.Server(config)
        server.run(sockets=[sock])
    except KeyboardInterrupt:
        pass
    finally:
        sock.close()
    print("dofjax view: stopped", file=out, flush=True)
    if engine is not None and any(t.is_alive() for t in threading.enumerate()
                                  if t is not threading.main_thread() and t.daemon):
        # XLA may still be compiling or running a program in a background thread (the exact
        # method's warm-up, a reference or fit job), and it cannot be cancelled: finalising the
        # interpreter under it crashes (SIGSEGV). Nothing is left to save: leave without.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0
