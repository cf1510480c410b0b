"""The `symgs` command line. Each command group lives in its own module and registers its subcommands here."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see symgs_core/__init__.py; set before torch loads

# Modules that define `register(subparsers)`; each subcommand sets `func(args) -> int` as its handler.
COMMAND_MODULES = [
    "service.cli.scene",  # info, render
    "service.cli.detect",  # detect
    "service.cli.codec",  # compress, decompress, evaluate
    "service.cli.train",  # train
    "service.cli.bench",  # bench
    "service.cli.service",  # serve, worker, submit, status, fetch, demo
]


class CliError(Exception):
    """A user-facing error: printed without a traceback, exit status 2."""


def error_text(exc: Exception) -> str:
    """An input error as ``code: message`` when it carries a machine-readable ``code`` (PlyError, DatasetError,
    ArchiveError): the word the HTTP API would answer with, so a script can tell failures apart the same way."""
    code = getattr(exc, "code", None)
    text = str(exc)
    if not code or text.startswith(f"{code}: "):  # ArchiveError's own text already leads with its code
        return text
    return f"{code}: {text}"


def check_seed(option: str, seed: int | None) -> None:
    """The seeds every door takes (``symgs_core.config.SEED_MAX``), named by the option that gave one."""
    from symgs_core.config import SEED_MAX

    if seed is not None and not 0 <= seed <= SEED_MAX:
        raise CliError(f"{option} must be in 0..{SEED_MAX}, got {seed}")


def check_input(what: str, path: Path, *, folder: bool = False) -> None:
    """Refuse an input that is missing, or a folder where a file belongs (and the reverse), naming which."""
    if not path.exists():
        raise CliError(f"{what} {path} does not exist")
    if path.is_dir() != folder:
        raise CliError(f"{what} {path} is a {'file' if folder else 'folder'}, not a {'folder' if folder else 'file'}")


def check_output(option: str, path: Path | None, *, folder: bool = False) -> None:
    """Refuse an output that could not be written, before the work rather than after it (None: not asked for)."""
    if path is None:
        return
    if path.exists():
        if path.is_dir() != folder:
            kind, other = ("a folder", "a file") if folder else ("a file", "a folder")
            raise CliError(f"{option} {path} is {other}; {kind} is expected there")
        target = path
    else:  # the nearest folder above: writing makes the missing ones below it
        target = next(p for p in path.parents if p.exists())
        if not target.is_dir():
            raise CliError(f"{option} {path}: {target} is a file, not a folder")
    if not os.access(target, os.W_OK):
        raise CliError(f"{option} {path}: {target} is not writable")


def check_distinct(paths: dict[str, Path | None]) -> None:
    """Refuse two options (or an input and an output) that name the same file: one would overwrite the other after
    all the work, and the user's own data with it. ``paths`` maps each option's name to its path (None: not given)."""
    seen: dict[Path, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        key = path.resolve()
        if key in seen:
            raise CliError(f"{option} {path} is the same file as {seen[key]}")
        seen[key] = f"{option} {path}" if option.startswith("-") else f"the {option}"


def cannot_write(option: str, path: Path, exc: OSError) -> CliError:
    """A write that failed (a full disk, a folder gone), named by the option that asked for it."""
    return CliError(f"{option} {path}: cannot write {exc.filename or path}: {exc.strerror or exc}")


def write_output(option: str, path: Path, data: bytes) -> None:
    """Write a whole output file (``whole_file``), or refuse in one line."""
    from symgs_core.files import whole_file

    try:
        with whole_file(path) as out:
            out.write(data)
    except OSError as exc:
        raise cannot_write(option, path, exc) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="symgs", description="SymGS: symmetry-aware 3D Gaussian Splatting compression"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # command group not present in this build
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"symgs {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into a command that stopped reading (e.g. `| head`)
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
