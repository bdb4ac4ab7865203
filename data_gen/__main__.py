"""``python -m data_gen``: a thin argparse layer over `load_config`, `dry_run` and `run`."""

from __future__ import annotations

import argparse
import sys

from dofjax import _compile_cache as compile_cache


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m data_gen",
        description="Generate defocus targets with known focus distance and aperture.",
    )
    parser.add_argument("--out", required=True, help="output directory (resumes if it exists)")
    parser.add_argument("--count", type=int, required=True, help="number of samples")
    parser.add_argument("--seed", type=int, required=True, help="data set seed (>= 0)")
    parser.add_argument("--config", default=None, help="JSON config laid over the defaults")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--size", default=None, help="image size WxH, overrides config.size")
    parser.add_argument("--dry-run", action="store_true", help="print the plan, render nothing")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    compile_cache.add_argument(parser)  # shared by the workers too
    args = parser.parse_args(argv)

    from ._config import ConfigError, load_config, parse_size
    from ._run import dry_run, run

    try:
        size = parse_size(args.size) if args.size else None
        cfg = load_config(args.config, size=size)
        if args.count < 1:
            raise ConfigError(f"--count: must be >= 1, got {args.count}")
        if args.seed < 0:
            raise ConfigError(f"--seed: must be >= 0, got {args.seed}")
        if args.workers < 1:
            raise ConfigError(f"--workers: must be >= 1, got {args.workers}")
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.dry_run:
        print(dry_run(cfg, args.count, args.seed))
        return 0
    try:
        cache = compile_cache.use_compilation_cache(args.jax_cache)
        summary = run(args.out, args.count, args.seed, cfg, workers=args.workers,
                      progress=not args.no_progress, jax_cache_dir=cache)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary.text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
