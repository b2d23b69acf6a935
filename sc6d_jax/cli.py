"""The ``sc6d`` command line: a thin dispatcher over sub-command modules.

Each sub-command lives in its own module and exposes ``main(argv: list[str]) -> int``.
Modules are imported only when their command runs, so ``sc6d --help`` stays fast.
Errors of bad input (``ValueError``, ``FileNotFoundError``, ...) are printed as one line
naming the problem and end the process with exit status 2.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

from sc6d_jax._version import __version__

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "objects": ("sc6d_jax.objects.cli", "write the built-in object set as a BOP models/ folder"),
    "render": ("sc6d_jax.render.cli", "render a BOP-format dataset with MuJoCo"),
    "train": ("sc6d_jax.train.cli", "train a model on crops streamed from the renderer"),
    "carry": ("sc6d_jax.train.carry", "copy a run's resumable state (config, newest checkpoint, metrics) for the next leg"),
    "predict": ("sc6d_jax.inference.cli", "estimate poses for a BOP dataset or one image"),
    "eval": ("sc6d_jax.metrics.cli", "BOP19 metrics (AR) of a results CSV"),
    "demo": ("sc6d_jax.demo", "the main job: objects, render, predict, evaluate, pictures"),
    "check": ("sc6d_jax.check", "render-and-check: verify that the renderer and geometry agree"),
}


class UsageError(ValueError):
    """Bad input detected at a public boundary (exit status 2)."""


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = [
        f"sc6d {__version__}: SC6D 6D object pose estimation in JAX",
        "",
        "usage: sc6d [--version] [--help] COMMAND [ARGS...]",
        "",
        "commands:",
    ]
    for name, (module, help_) in COMMANDS.items():
        lines.append(f"  {name.ljust(width)}  {help_}")
    lines += ["", "Run 'sc6d COMMAND --help' for the options of one command."]
    return "\n".join(lines)


def _available(module: str) -> bool:
    return importlib.util.find_spec(module) is not None  # type: ignore[attr-defined]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        print(f"sc6d {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"sc6d: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name = COMMANDS[name][0]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            print(f"sc6d: command {name!r} is not available in this version", file=sys.stderr)
            return 2
        raise
    try:
        return int(module.main(rest) or 0)
    except KeyboardInterrupt:
        print("sc6d: interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, NotADirectoryError, FileExistsError, PermissionError) as exc:
        print(f"sc6d {name}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
