"""The fit's defocus model on the command line: `--method`, `--samples`, `--subapertures`
(`fit.recover` and `fit.sweep` share them)."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser, lens_use: str = "") -> None:
    """Add --method / --samples / --subapertures to `p`; `lens_use` ends --method's help."""
    p.add_argument("--method", default="sliced", choices=("sliced", "exact", "pyramid", "lens"),
                   help="the fit's defocus model (exact, lens: polish what a sliced search found"
                   f"{lens_use})")
    p.add_argument("--samples", type=int, help="--method lens: lens points per pixel "
                   "(default 256; 64 is ~3.5x faster)")
    p.add_argument("--subapertures", type=int, default=1,
                   help="--method sliced: aperture sectors composited apart in the polish "
                   "(closer to a lens behind blurred edges; 4 costs up to 4x per step)")


def options(p: argparse.ArgumentParser, a: argparse.Namespace) -> dict:
    """`fit_focus`'s defocus_options from the parsed arguments; `p.error` on options that do not
    apply to the method (the values themselves are the library's to check)."""
    if a.samples is not None and a.method != "lens":
        p.error("--samples is for --method lens only")
    if a.subapertures != 1 and a.method != "sliced":
        p.error("--subapertures is for --method sliced only")
    return ({"method": a.method} | ({"samples": a.samples} if a.samples is not None else {})
            | ({"subapertures": a.subapertures} if a.subapertures != 1 else {}))
